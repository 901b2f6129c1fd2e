//! Adaptive orbits side by side in SIMD lanes. Every lane runs the one-orbit driver of
//! [`crate::adaptive`] as a future that waits at each of its steps; once every busy lane waits,
//! the batch ([`TaylorLanes`]) takes one step for all of them at once, and each lane's driver
//! goes on to its next step. The driver is the scalar one, the batch computes in each lane what
//! the scalar integrator computes, so every orbit's result is bit-identical to its scalar run.
//!
//! Taylor methods only: their step is one fixed sequence of operations whatever its size, so
//! lanes never diverge in control flow (DOP853 rejects steps lane by lane). In use for
//! `taylor-dd`, and for f64 Taylor at small τ; DOP853 runs one orbit at a time, through
//! [`integrate_feed_scalar`] (see [`crate::run::integrate_feed_adaptive`]).

use crate::adaptive::Abandoned;
use crate::adaptive::{integrate, relative, to_f64_phase, AdaptiveIntegrator, Protocol, Watch};
use crate::batch::{BatchFeed, Feed, Isa, IDLE_POLL};
use crate::dop853::StepFailure;
use crate::orbit::{OrbitConfig, OrbitResult, Requests};
use crate::section::Crossing;
use crate::tangent::Phase;
use crate::taylor::{Lanewise, Scalar, TaylorLanes, TaylorSeries};
use core::cell::{Cell, RefCell};
use core::future::Future;
use core::pin::Pin;
use core::task::{Context, Poll, Waker};

/// A feed's hooks seen from one orbit: its crossings go to the feed as they are located, and
/// the feed may abandon it. The feed is shared by every lane of a thread, hence the cell.
pub struct FeedWatch<'a, 'f, F> {
    pub feed: &'a RefCell<&'f mut F>,
    pub id: usize,
}

impl<const N: usize, F: BatchFeed<N>> Watch<N> for FeedWatch<'_, '_, F> {
    fn crossing(&mut self, c: &Crossing<N>) {
        self.feed.borrow_mut().on_crossing(self.id, c);
    }
    fn cancelled(&mut self) -> bool {
        self.feed.borrow_mut().cancelled(self.id)
    }
}

/// Integrates the orbits `feed` supplies one at a time, each through `run` (an adaptive
/// driver under the given watch), until the feed says [`Feed::Done`].
pub fn integrate_feed_scalar<const N: usize, F: BatchFeed<N>>(
    feed: &mut F,
    mut run: impl FnMut([f64; N], [f64; N], &mut FeedWatch<'_, '_, F>) -> OrbitOutcome<N>,
) {
    let feed = RefCell::new(feed);
    loop {
        let next = feed.borrow_mut().next(true);
        match next {
            Feed::Orbit(id, q, p) => {
                let r = run(q, p, &mut FeedWatch { feed: &feed, id });
                report(&feed, id, r);
            }
            Feed::Wait => {}
            Feed::Done => return,
        }
    }
}

/// How one adaptive orbit ended.
pub type OrbitOutcome<const N: usize> = Result<OrbitResult<N>, Abandoned>;

fn report<const N: usize, F: BatchFeed<N>>(
    feed: &RefCell<&mut F>,
    id: usize,
    outcome: OrbitOutcome<N>,
) {
    let mut feed = feed.borrow_mut();
    match outcome {
        Ok(r) => feed.finished(id, r),
        Err(Abandoned { steps }) => feed.abandoned(id, steps),
    }
}

/// Where a lane's step request stands.
#[derive(Clone, Copy, Debug)]
enum Slot {
    Idle,
    Asked(f64),
    Done(Result<(), StepFailure>),
}

/// The future of one lane's step: ready once the batch has answered.
struct LaneStep<'b> {
    slot: &'b Cell<Slot>,
}

impl Future for LaneStep<'_> {
    type Output = Result<(), StepFailure>;
    fn poll(self: Pin<&mut Self>, _: &mut Context<'_>) -> Poll<Self::Output> {
        match self.slot.get() {
            Slot::Done(r) => {
                self.slot.set(Slot::Idle);
                Poll::Ready(r)
            }
            _ => Poll::Pending,
        }
    }
}

/// One lane of a [`TaylorLanes`] batch as the driver sees an integrator.
struct LaneOrbit<'b, 'h, H, T: Lanewise, const N: usize, const K: usize, const L: usize> {
    batch: &'b RefCell<TaylorLanes<'h, H, T, N, K, L>>,
    slot: &'b Cell<Slot>,
    lane: usize,
    ham: &'h H,
    /// Initial energy, in the lane's precision.
    h0: T::Lane,
}

impl<H: TaylorSeries<N>, T: Lanewise, const N: usize, const K: usize, const L: usize>
    AdaptiveIntegrator<N, K> for LaneOrbit<'_, '_, H, T, N, K, L>
{
    fn t(&self) -> f64 {
        self.batch.borrow().t(self.lane)
    }
    fn state(&self) -> Phase<f64, N, K> {
        self.batch.borrow().state_f64(self.lane)
    }
    fn renormalise(&mut self) -> f64 {
        self.batch.borrow_mut().unit_vectors(self.lane)
    }
    fn step(&mut self, t_end: f64) -> impl Future<Output = Result<(), StepFailure>> {
        self.slot.set(Slot::Asked(t_end));
        LaneStep { slot: self.slot }
    }
    fn interpolate(&self, t: f64) -> Phase<f64, N, K> {
        to_f64_phase(&self.batch.borrow().interpolate(self.lane, t))
    }
    fn t_prev(&self) -> f64 {
        self.batch.borrow().t_prev(self.lane)
    }
    fn steps(&self) -> u64 {
        self.batch.borrow().steps(self.lane)
    }
    fn energy_error(&self, at: Option<f64>) -> f64 {
        let batch = self.batch.borrow();
        let energy = match at {
            None => batch.energy(self.lane),
            Some(t) => {
                let y = batch.interpolate(self.lane, t);
                self.ham.energy(&y.q, &y.p)
            }
        };
        relative((energy - self.h0).to_f64(), self.h0.to_f64())
    }
}

/// What every Taylor lane integrates with.
pub struct TaylorSetup<'a, H> {
    pub ham: &'a H,
    pub delta: f64,
    pub protocol: Protocol,
    pub config: &'a OrbitConfig,
    pub requests: &'a Requests,
}

/// Lanes per batch of [`integrate_feed_taylor`]. More lanes make a step cheaper per orbit but
/// put more orbits in flight, and in a fast-PSS run every orbit in flight beyond the frontier
/// may be dropped when an earlier orbit labels its cell. `taylor-dd`, δ = 1e-5, 400×400,
/// τ = 0.5, t = 1e4, 2 threads (2026-11-24): one orbit per thread 42.3 s; 4 lanes 24.6 s (32 %
/// of the steps dropped; 27.4 s in AVX2 code); 8 AVX-512 lanes 28.7 s (47 % dropped). With
/// its high orders in f64 (2026-11-25, `taylor::lead_order`) the step is far cheaper and the
/// lanes' lead narrower: τ = 0.5 7.5–7.7 s in 4 lanes against 7.75–7.9 s one at a time,
/// τ = 0.01 88.7 against 113 s.
pub const TAYLOR_LANES: usize = 4;

/// Integrates the orbits `feed` supplies with the Taylor method in number type `S` (`f64` or
/// `DoubleDouble`), [`TAYLOR_LANES`] at a time in SIMD lanes, each exactly as
/// [`integrate_adaptive_watched`](crate::adaptive::integrate_adaptive_watched) would with
/// [`TaylorOrbit`](crate::adaptive::TaylorOrbit); `start` gives the initial state of the orbit
/// from (q, p). Hands each result to the feed the moment its orbit ends.
pub fn integrate_feed_taylor<H, S, const N: usize, const K: usize>(
    setup: &TaylorSetup<'_, H>,
    start: impl Fn([f64; N], [f64; N]) -> Phase<S, N, K>,
    feed: &mut impl BatchFeed<N>,
) where
    H: TaylorSeries<N>,
    S: Scalar + Lanewise<Lane = S> + SimdOf<TAYLOR_LANES>,
{
    integrate_feed_taylor_on::<H, S, N, K, TAYLOR_LANES>(Isa::detect(), setup, start, feed)
}

/// [`integrate_feed_taylor`] with `L` lanes, its steps compiled for `isa` (AVX-512 where the
/// host has it: 32 vector registers hold a double-double jet's sums without spilling; the same
/// operations, so the same bits; an `isa` the host lacks falls back to the pinned level).
pub fn integrate_feed_taylor_on<H, S, const N: usize, const K: usize, const L: usize>(
    isa: Isa,
    setup: &TaylorSetup<'_, H>,
    start: impl Fn([f64; N], [f64; N]) -> Phase<S, N, K>,
    feed: &mut impl BatchFeed<N>,
) where
    H: TaylorSeries<N>,
    S: Scalar + Lanewise<Lane = S> + SimdOf<L>,
{
    drive::<H, S, <S as SimdOf<L>>::Simd, N, K, L>(isa, setup, &start, feed)
}

/// The type holding `L` numbers of `Self` in SIMD lanes.
pub trait SimdOf<const L: usize> {
    type Simd: Lanewise<Lane = Self>;
}

impl<const L: usize> SimdOf<L> for f64 {
    type Simd = crate::real::Lanes<L>;
}

impl<const L: usize> SimdOf<L> for crate::dd::DoubleDouble {
    type Simd = crate::dd::DoubleDouble<crate::real::Lanes<L>>;
}

type LaneFuture<'a, const N: usize> = Pin<Box<dyn Future<Output = OrbitOutcome<N>> + 'a>>;

fn drive<H, S, T, const N: usize, const K: usize, const L: usize>(
    isa: Isa,
    setup: &TaylorSetup<'_, H>,
    start: &impl Fn([f64; N], [f64; N]) -> Phase<S, N, K>,
    feed: &mut impl BatchFeed<N>,
) where
    H: TaylorSeries<N>,
    S: Scalar + Lanewise<Lane = S>,
    T: Lanewise<Lane = S>,
{
    let ham = setup.ham;
    let batch = RefCell::new(TaylorLanes::<H, T, N, K, L>::new(ham, setup.delta));
    let slots: [Cell<Slot>; L] = core::array::from_fn(|_| Cell::new(Slot::Idle));
    let feed = RefCell::new(feed);
    let mut lanes: [Option<(usize, LaneFuture<'_, N>)>; L] = core::array::from_fn(|_| None);
    let mut context = Context::from_waker(Waker::noop());
    // Polls lane `l`'s orbit; reports it and frees the lane when it has ended (returns true
    // then).
    let mut poll = |l: usize, lanes: &mut [Option<(usize, LaneFuture<'_, N>)>; L]| {
        let (id, future) = lanes[l].as_mut().expect("a busy lane");
        if let Poll::Ready(outcome) = future.as_mut().poll(&mut context) {
            report(&feed, *id, outcome);
            lanes[l] = None;
            true
        } else {
            debug_assert!(matches!(slots[l].get(), Slot::Asked(_)));
            false
        }
    };
    let (mut exhausted, mut waiting) = (false, false);
    let mut round = 0u64;
    loop {
        // Idle lanes take work: at once after a lane frees up, every few rounds while the
        // feed says to wait.
        if !exhausted && (!waiting || round.is_multiple_of(IDLE_POLL)) {
            waiting = false;
            for l in 0..L {
                if lanes[l].is_some() {
                    continue;
                }
                let all_idle = lanes.iter().all(Option::is_none);
                let next = feed.borrow_mut().next(all_idle);
                match next {
                    Feed::Orbit(id, q, p) => {
                        let y = start(q, p);
                        batch.borrow_mut().start(l, 0.0, &y);
                        let integ = LaneOrbit {
                            batch: &batch,
                            slot: &slots[l],
                            lane: l,
                            ham,
                            h0: ham.energy(&y.q, &y.p),
                        };
                        let watch = FeedWatch { feed: &feed, id };
                        let (protocol, config, requests) =
                            (setup.protocol, setup.config, setup.requests);
                        lanes[l] = Some((
                            id,
                            Box::pin(async move {
                                let (mut integ, mut watch) = (integ, watch);
                                integrate(
                                    ham, &mut integ, protocol, config, requests, false, &mut watch,
                                )
                                .await
                            }),
                        ));
                        poll(l, &mut lanes);
                    }
                    Feed::Wait => {
                        waiting = true;
                        break;
                    }
                    Feed::Done => {
                        exhausted = true;
                        break;
                    }
                }
            }
        }
        if lanes.iter().all(Option::is_none) {
            if exhausted {
                return;
            }
            // Nothing in flight: the next request may block until the feed has work.
            waiting = false;
            continue;
        }
        round += 1;
        let asked: [Option<f64>; L] = core::array::from_fn(|l| match slots[l].get() {
            Slot::Asked(t) => Some(t),
            _ => None,
        });
        let outcomes = step_on(isa, &mut batch.borrow_mut(), &asked);
        for l in 0..L {
            if let Some(r) = outcomes[l] {
                slots[l].set(Slot::Done(r));
                // A lane that frees up asks for work at once (the feed may have some now).
                waiting &= !poll(l, &mut lanes);
            }
        }
    }
}

/// [`TaylorLanes::step`] compiled for the instruction set `isa`.
fn step_on<H: TaylorSeries<N>, T: Lanewise, const N: usize, const K: usize, const L: usize>(
    isa: Isa,
    batch: &mut TaylorLanes<'_, H, T, N, K, L>,
    asked: &[Option<f64>; L],
) -> [Option<Result<(), StepFailure>>; L] {
    #[cfg(target_arch = "x86_64")]
    if isa == Isa::Avx512 && isa.available() {
        // SAFETY: the host has every feature the function is compiled for (checked above).
        return unsafe { step_avx512(batch, asked) };
    }
    let _ = isa;
    batch.step(asked)
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx512vl,avx512dq,avx512bw,avx512cd")]
unsafe fn step_avx512<
    H: TaylorSeries<N>,
    T: Lanewise,
    const N: usize,
    const K: usize,
    const L: usize,
>(
    batch: &mut TaylorLanes<'_, H, T, N, K, L>,
    asked: &[Option<f64>; L],
) -> [Option<Result<(), StepFailure>>; L] {
    batch.step(asked)
}
