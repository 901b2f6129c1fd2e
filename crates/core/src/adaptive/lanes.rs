//! Adaptive orbits side by side in SIMD lanes. Every lane runs the one-orbit driver of
//! [`crate::adaptive::driver`] as a future that waits at each of its steps; once every busy lane
//! waits, the batch ([`LaneBatch`]: [`TaylorLanes`] or [`Dop853Batch`]) takes one step for all of
//! them at once, and each lane's driver goes on to its next step. The driver is the scalar one, the
//! batch computes in each lane what the scalar integrator computes, so every orbit's result is
//! bit-identical to its scalar run. A Taylor step is one fixed sequence of operations whatever
//! its size; a DOP853 batch step makes passes until every asked lane has an accepted attempt.
//! In the restart protocol the loop around the batch also takes each lane's quiet steps for its
//! driver ([`quiet_restart_step`]: those that change only the orbit's totals), so a lane's
//! future wakes only for the steps its driver's own tests pick out: crossings, samples, watch
//! polls, possible early stops, failures and the orbit's last step.
//! In use for `taylor-dd`, and for f64 Taylor and DOP853 at small τ; otherwise orbits run one
//! at a time through [`integrate_feed_scalar`] (see [`crate::run::integrate_feed_adaptive`]).

use crate::adaptive::dop853::{Dense, Dop853Config, Dop853Lanes};
use crate::adaptive::driver::Abandoned;
use crate::adaptive::driver::{
    integrate, quiet_restart_step, relative, AdaptiveIntegrator, Pace, Protocol, QuietRules, Watch,
};
use crate::adaptive::stepping::{to_f64_phase, LaneSteps, Lanewise, Scalar, StepEnd, StepFailure};
use crate::adaptive::taylor::TaylorLanes;
use crate::arith::real::{Lanes, Real};
use crate::orbit::{OrbitConfig, OrbitResult, Requests};
use crate::phase::Phase;
use crate::section::Crossing;
use crate::systems::hamiltonian::Hamiltonian;
use crate::systems::series::TaylorSeries;
use crate::tangent_map::batch::{BatchFeed, Feed, Isa, IDLE_POLL};
use core::cell::{Cell, RefCell};
use core::future::Future;
use core::pin::Pin;
use core::task::{Context, Poll, Waker};

/// A feed's hooks seen from one orbit: its crossings go to the feed as they are located, and
/// the feed may abandon it. The feed is shared by every lane of a thread, hence the cell.
pub struct FeedWatch<'a, 'f, F> {
    /// The feed, shared by the thread's lanes.
    pub feed: &'a RefCell<&'f mut F>,
    /// The orbit's id in the feed.
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
    /// A step to the time given, after a renormalisation when the flag is set.
    Asked(f64, bool),
    /// The step's outcome, and the renormalisation's factor when one was asked.
    Done(Option<f64>, Result<(), StepFailure>),
}

/// The future of one lane's step: ready once the batch has answered.
struct LaneStep<'b> {
    slot: &'b Cell<Slot>,
}

impl Future for LaneStep<'_> {
    type Output = (Option<f64>, Result<(), StepFailure>);
    fn poll(self: Pin<&mut Self>, _: &mut Context<'_>) -> Poll<Self::Output> {
        match self.slot.get() {
            Slot::Done(factor, r) => {
                self.slot.set(Slot::Idle);
                Poll::Ready((factor, r))
            }
            _ => Poll::Pending,
        }
    }
}

/// A batch of integrations side by side in SIMD lanes, as the lanes' drivers use it.
pub trait LaneBatch<const N: usize, const K: usize, const L: usize> {
    /// The number type of one lane's state.
    type Lane: Scalar;
    /// Starts lane `l` afresh from `y` at time 0.
    fn start(&mut self, l: usize, y: &Phase<Self::Lane, N, K>);
    /// One step of every lane with `t_end[l]` set, its steps compiled for `isa`; first the
    /// lanes with `renormalise[l]` set are renormalised, all at once, and their factors come
    /// back (each lane's as [`AdaptiveIntegrator::renormalise`] computes it alone).
    fn step_on(
        &mut self,
        isa: Isa,
        renormalise: &[bool; L],
        t_end: &[Option<f64>; L],
    ) -> LaneSteps<L>;
    /// Lane `l`'s current time.
    fn t(&self, l: usize) -> f64;
    /// Where lane `l`'s last step started.
    fn t_prev(&self, l: usize) -> f64;
    /// Lane `l`'s accepted steps.
    fn steps(&self, l: usize) -> u64;
    /// Lane `l`'s state rounded to f64.
    fn state_f64(&self, l: usize) -> Phase<f64, N, K>;
    /// [`AdaptiveIntegrator::step_end`] of lane `l`.
    fn step_end(&self, l: usize) -> StepEnd<f64, K>;
    /// [`AdaptiveIntegrator::renormalise`] of lane `l`.
    fn renormalise(&mut self, l: usize) -> f64;
    /// The energy of lane `l` at its step's end, or at `t` within the step.
    fn energy(&self, l: usize, at: Option<f64>) -> Self::Lane;
    /// The energy of lane `l`'s state rounded to f64, where the batch forms it instead of
    /// [`Self::energy`] at every step (see [`AdaptiveIntegrator::energy_estimate`]).
    fn energy_f64(&self, _l: usize) -> Option<f64> {
        None
    }
    /// [`AdaptiveIntegrator::prepare_dense`] of lane `l`.
    fn prepare_dense(&mut self, _l: usize) {}
    /// Lane `l`'s state at `t` within its last step, rounded to f64.
    fn interpolate(&self, l: usize, t: f64) -> Phase<f64, N, K>;
}

impl<H, T, const N: usize, const K: usize, const L: usize> LaneBatch<N, K, L>
    for TaylorLanes<'_, H, T, N, K, L>
where
    H: TaylorSeries<N>,
    T: Lanewise + Real<Lead = Lanes<L>>,
{
    type Lane = T::Lane;
    fn start(&mut self, l: usize, y: &Phase<T::Lane, N, K>) {
        TaylorLanes::start(self, l, 0.0, y)
    }
    fn step_on(
        &mut self,
        isa: Isa,
        renormalise: &[bool; L],
        t_end: &[Option<f64>; L],
    ) -> LaneSteps<L> {
        #[cfg(target_arch = "x86_64")]
        if isa == Isa::Avx512 && isa.available() {
            // SAFETY: the host has every feature the function is compiled for (checked above).
            return unsafe { taylor_step_avx512(self, renormalise, t_end) };
        }
        let _ = isa;
        self.renormalise_and_step(renormalise, t_end)
    }
    fn t(&self, l: usize) -> f64 {
        TaylorLanes::t(self, l)
    }
    fn t_prev(&self, l: usize) -> f64 {
        TaylorLanes::t_prev(self, l)
    }
    fn steps(&self, l: usize) -> u64 {
        TaylorLanes::steps(self, l)
    }
    fn state_f64(&self, l: usize) -> Phase<f64, N, K> {
        TaylorLanes::state_f64(self, l)
    }
    fn step_end(&self, l: usize) -> StepEnd<f64, K> {
        TaylorLanes::step_end(self, l)
    }
    fn renormalise(&mut self, l: usize) -> f64 {
        let mut mask = [false; L];
        mask[l] = true;
        self.unit_vectors(&mask)[l]
    }
    fn energy_f64(&self, l: usize) -> Option<f64> {
        TaylorLanes::energy_f64(self, l)
    }
    fn energy(&self, l: usize, at: Option<f64>) -> T::Lane {
        match at {
            None => TaylorLanes::energy(self, l),
            Some(t) => {
                let y = TaylorLanes::interpolate(self, l, t);
                self.hamiltonian().energy(&y.q, &y.p)
            }
        }
    }
    fn interpolate(&self, l: usize, t: f64) -> Phase<f64, N, K> {
        to_f64_phase(&TaylorLanes::interpolate(self, l, t))
    }
}

/// DOP853 lanes with the dense output of each lane's last step, built on demand.
pub struct Dop853Batch<'h, H, const N: usize, const K: usize, const L: usize> {
    lanes: Dop853Lanes<'h, H, N, K, L>,
    dense: [Option<Dense<N, K>>; L],
}

impl<'h, H: Hamiltonian<N>, const N: usize, const K: usize, const L: usize>
    Dop853Batch<'h, H, N, K, L>
{
    /// `L` idle lanes with the given tolerances.
    pub fn new(ham: &'h H, config: Dop853Config) -> Self {
        Dop853Batch {
            lanes: Dop853Lanes::new(ham, config),
            dense: [None; L],
        }
    }
}

impl<H: Hamiltonian<N>, const N: usize, const K: usize, const L: usize> LaneBatch<N, K, L>
    for Dop853Batch<'_, H, N, K, L>
{
    type Lane = f64;
    fn start(&mut self, l: usize, y: &Phase<f64, N, K>) {
        self.lanes.start(l, 0.0, y);
        self.dense[l] = None;
    }
    fn step_on(
        &mut self,
        isa: Isa,
        renormalise: &[bool; L],
        t_end: &[Option<f64>; L],
    ) -> LaneSteps<L> {
        for (l, end) in t_end.iter().enumerate() {
            if end.is_some() {
                self.dense[l] = None;
            }
        }
        #[cfg(target_arch = "x86_64")]
        if isa == Isa::Avx512 && isa.available() {
            // SAFETY: the host has every feature the function is compiled for (checked above).
            return unsafe { dop853_step_avx512(&mut self.lanes, renormalise, t_end) };
        }
        let _ = isa;
        self.lanes.renormalise_and_step(renormalise, t_end)
    }
    fn t(&self, l: usize) -> f64 {
        self.lanes.t(l)
    }
    fn t_prev(&self, l: usize) -> f64 {
        self.lanes.t_prev(l)
    }
    fn steps(&self, l: usize) -> u64 {
        self.lanes.steps(l)
    }
    fn state_f64(&self, l: usize) -> Phase<f64, N, K> {
        self.lanes.state(l)
    }
    fn step_end(&self, l: usize) -> StepEnd<f64, K> {
        self.lanes.step_end(l)
    }
    fn renormalise(&mut self, l: usize) -> f64 {
        let mut mask = [false; L];
        mask[l] = true;
        self.lanes.renormalise(&mask)[l]
    }
    fn energy(&self, l: usize, at: Option<f64>) -> f64 {
        match at {
            None => self.lanes.energy(l),
            Some(t) => {
                let y = self.interpolate(l, t);
                self.lanes.hamiltonian().energy(&y.q, &y.p)
            }
        }
    }
    fn prepare_dense(&mut self, l: usize) {
        if self.dense[l].is_none() {
            let mut d = Dense::empty();
            self.lanes.dense_output(l, &mut d);
            self.dense[l] = Some(d);
        }
    }
    fn interpolate(&self, l: usize, t: f64) -> Phase<f64, N, K> {
        self.dense[l]
            .as_ref()
            .expect("interpolate after prepare_dense")
            .at(t)
    }
}

/// One lane of a [`LaneBatch`] as the driver sees an integrator.
struct LaneOrbit<'b, B, S, const L: usize> {
    batch: &'b RefCell<B>,
    slot: &'b Cell<Slot>,
    /// While a restart-protocol request is out, what the loop around the batch needs to take
    /// quiet steps for the driver.
    quiet: &'b RefCell<Option<QuietRequest<S>>>,
    lane: usize,
    /// Initial energy, in the lane's precision.
    h0: S,
}

/// A lane's restart-protocol request as the loop around the batch sees it: the rules under
/// which it may take quiet steps for the driver, where the orbit stands after those it took,
/// and the orbit's initial energy (for the energy checks).
#[derive(Clone, Copy)]
struct QuietRequest<S> {
    rules: QuietRules,
    pace: Pace,
    h0: S,
}

/// [`AdaptiveIntegrator::energy_error`] of lane `l`, whose initial energy was `h0`.
fn lane_energy_error<B: LaneBatch<N, K, L>, const N: usize, const K: usize, const L: usize>(
    batch: &B,
    l: usize,
    h0: B::Lane,
    at: Option<f64>,
) -> f64 {
    let energy = batch.energy(l, at);
    relative((energy - h0).to_f64(), h0.to_f64())
}

/// [`AdaptiveIntegrator::energy_estimate`] of lane `l`, whose initial energy was `h0`.
fn lane_energy_estimate<B: LaneBatch<N, K, L>, const N: usize, const K: usize, const L: usize>(
    batch: &B,
    l: usize,
    h0: B::Lane,
) -> Option<f64> {
    let energy = batch.energy_f64(l)?;
    let h0 = h0.to_f64();
    Some(relative(energy - h0, h0))
}

impl<B, const N: usize, const K: usize, const L: usize> AdaptiveIntegrator<N, K>
    for LaneOrbit<'_, B, <B as LaneBatch<N, K, L>>::Lane, L>
where
    B: LaneBatch<N, K, L>,
{
    fn t(&self) -> f64 {
        self.batch.borrow().t(self.lane)
    }
    fn state(&self) -> Phase<f64, N, K> {
        self.batch.borrow().state_f64(self.lane)
    }
    fn renormalise(&mut self) -> f64 {
        self.batch.borrow_mut().renormalise(self.lane)
    }
    fn step(&mut self, t_end: f64) -> impl Future<Output = Result<(), StepFailure>> {
        self.slot.set(Slot::Asked(t_end, false));
        let step = LaneStep { slot: self.slot };
        async move { step.await.1 }
    }
    fn renormalise_and_step(
        &mut self,
        renormalise: bool,
        t_end: f64,
    ) -> impl Future<Output = (Option<f64>, Result<(), StepFailure>)> {
        self.slot.set(Slot::Asked(t_end, renormalise));
        LaneStep { slot: self.slot }
    }
    fn restart_step<'a>(
        &'a mut self,
        renormalise: bool,
        pace: &'a mut Pace,
        rules: &'a QuietRules,
    ) -> impl Future<Output = (Option<f64>, Result<(), StepFailure>)> + 'a {
        *self.quiet.borrow_mut() = Some(QuietRequest {
            rules: *rules,
            pace: *pace,
            h0: self.h0,
        });
        let quiet = self.quiet;
        let step = self.renormalise_and_step(renormalise, (pace.n + 1) as f64 * rules.tau);
        async move {
            let answer = step.await;
            if let Some(request) = quiet.borrow_mut().take() {
                *pace = request.pace;
            }
            answer
        }
    }
    fn prepare_dense(&mut self) {
        self.batch.borrow_mut().prepare_dense(self.lane)
    }
    fn interpolate(&self, t: f64) -> Phase<f64, N, K> {
        self.batch.borrow().interpolate(self.lane, t)
    }
    fn t_prev(&self) -> f64 {
        self.batch.borrow().t_prev(self.lane)
    }
    fn steps(&self) -> u64 {
        self.batch.borrow().steps(self.lane)
    }
    fn step_end(&self) -> StepEnd<f64, K> {
        self.batch.borrow().step_end(self.lane)
    }
    fn energy_error(&self, at: Option<f64>) -> f64 {
        lane_energy_error(&*self.batch.borrow(), self.lane, self.h0, at)
    }
    fn energy_estimate(&self) -> Option<f64> {
        lane_energy_estimate(&*self.batch.borrow(), self.lane, self.h0)
    }
}

/// What every lane integrates with.
pub struct LaneSetup<'a, H> {
    /// The Hamiltonian.
    pub ham: &'a H,
    /// Tolerance δ of the adaptive method.
    pub delta: f64,
    /// How the lanes meet the renormalisation times.
    pub protocol: Protocol,
    /// What to integrate.
    pub config: &'a OrbitConfig,
    /// What to compute besides the final SALI and mLE.
    pub requests: &'a Requests,
}

/// Lanes per batch of an adaptive run up to [`FEWER_LANES_ABOVE_T_FINAL`]. More lanes make a
/// step cheaper per orbit but put more orbits in flight, and in a fast-PSS run every orbit in
/// flight beyond the frontier may be dropped when an earlier orbit labels its cell. Four lanes
/// beat both one orbit per thread and eight AVX-512 lanes (figures: docs/performance.md).
pub const LANES: usize = 4;

/// Lanes per batch of an adaptive run past [`FEWER_LANES_ABOVE_T_FINAL`] at τ of at least
/// [`crate::method::F64_TAYLOR_LANES_BELOW_TAU`] (in practice taylor-dd at τ = 0.5): the longer
/// the regular orbits run, the more of the orbits in flight an earlier orbit's crossings
/// overtake late, and where steps are not cut by τ a lane's step saves least. At small τ,
/// where a lane's step saves most, four stay ahead even in long runs (figures:
/// docs/performance.md).
pub const LONG_RUN_LANES: usize = 2;

/// The t_final above which [`LONG_RUN_LANES`] may replace [`LANES`].
pub const FEWER_LANES_ABOVE_T_FINAL: f64 = 3e4;

/// Integrates the orbits `feed` supplies with the Taylor method in number type `S` (`f64` or
/// `DoubleDouble`), `L` at a time in SIMD lanes, each exactly as
/// [`integrate_adaptive_watched`](crate::adaptive::driver::integrate_adaptive_watched) would with
/// [`TaylorOrbit`](crate::adaptive::driver::TaylorOrbit); `start` gives the initial state of the
/// orbit from (q, p). Hands each result to the feed the moment its orbit ends. Its steps are
/// compiled for `isa` (AVX-512 where the host has it: 32 vector registers hold a double-double
/// jet's sums without spilling; the same operations, so the same bits; an `isa` the host lacks
/// falls back to the pinned level).
pub fn integrate_feed_taylor_on<H, S, const N: usize, const K: usize, const L: usize>(
    isa: Isa,
    setup: &LaneSetup<'_, H>,
    start: impl Fn([f64; N], [f64; N]) -> Phase<S, N, K>,
    feed: &mut impl BatchFeed<N>,
) where
    H: TaylorSeries<N>,
    S: Scalar + Lanewise<Lane = S> + SimdOf<L>,
{
    let mut batch = TaylorLanes::<H, <S as SimdOf<L>>::Simd, N, K, L>::new(setup.ham, setup.delta);
    if S::EXTENDED && !setup.requests.energy {
        batch.screen_energy();
    }
    drive::<_, H, N, K, L>(isa, setup, batch, &start, feed)
}

/// Integrates the orbits `feed` supplies with DOP853, `L` at a time in SIMD lanes, each
/// exactly as [`integrate_adaptive_watched`](crate::adaptive::driver::integrate_adaptive_watched)
/// would with [`Dop853Orbit`](crate::adaptive::driver::Dop853Orbit), its steps compiled for `isa`.
/// Hands each result to the feed the moment its orbit ends.
pub fn integrate_feed_dop853_on<
    H: Hamiltonian<N>,
    const N: usize,
    const K: usize,
    const L: usize,
>(
    isa: Isa,
    setup: &LaneSetup<'_, H>,
    start: impl Fn([f64; N], [f64; N]) -> Phase<f64, N, K>,
    feed: &mut impl BatchFeed<N>,
) {
    let batch = Dop853Batch::<H, N, K, L>::new(setup.ham, Dop853Config::with_delta(setup.delta));
    drive::<_, H, N, K, L>(isa, setup, batch, &start, feed)
}

/// The type holding `L` numbers of `Self` in SIMD lanes.
pub trait SimdOf<const L: usize> {
    /// `L` lanes of `Self`.
    type Simd: Lanewise<Lane = Self> + Real<Lead = Lanes<L>>;
}

impl<const L: usize> SimdOf<L> for f64 {
    type Simd = Lanes<L>;
}

impl<const L: usize> SimdOf<L> for crate::arith::dd::DoubleDouble {
    type Simd = crate::arith::dd::DoubleDouble<Lanes<L>>;
}

type LaneFuture<'a, const N: usize> = Pin<Box<dyn Future<Output = OrbitOutcome<N>> + 'a>>;

fn drive<B, H, const N: usize, const K: usize, const L: usize>(
    isa: Isa,
    setup: &LaneSetup<'_, H>,
    batch: B,
    start: &impl Fn([f64; N], [f64; N]) -> Phase<B::Lane, N, K>,
    feed: &mut impl BatchFeed<N>,
) where
    B: LaneBatch<N, K, L>,
    H: Hamiltonian<N>,
{
    let ham = setup.ham;
    let batch = RefCell::new(batch);
    let slots: [Cell<Slot>; L] = core::array::from_fn(|_| Cell::new(Slot::Idle));
    // In place (a `Cell` copied each request out and back in at every step of every lane).
    let quiet: [RefCell<Option<QuietRequest<B::Lane>>>; L] =
        core::array::from_fn(|_| RefCell::new(None));
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
            debug_assert!(matches!(slots[l].get(), Slot::Asked(..)));
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
                        batch.borrow_mut().start(l, &y);
                        *quiet[l].borrow_mut() = None;
                        let integ = LaneOrbit::<_, _, L> {
                            batch: &batch,
                            slot: &slots[l],
                            quiet: &quiet[l],
                            lane: l,
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
            Slot::Asked(t, _) => Some(t),
            _ => None,
        });
        let renormalise: [bool; L] =
            core::array::from_fn(|l| matches!(slots[l].get(), Slot::Asked(_, true)));
        let (outcomes, factors) = batch.borrow_mut().step_on(isa, &renormalise, &asked);
        for l in 0..L {
            let Some(r) = outcomes[l] else { continue };
            let factor = renormalise[l].then_some(factors[l]);
            // A quiet restart step is the driver's too, taken here: the lane asks for its
            // next step without waking its future (the driver's per-step work in each lane's
            // future is a large share of an f64 Taylor run; figures: docs/performance.md).
            if let (Ok(()), Some(request)) = (r, quiet[l].borrow_mut().as_mut()) {
                let b = batch.borrow();
                let (b, h0) = (&*b, request.h0);
                if quiet_restart_step(
                    &request.rules,
                    &mut request.pace,
                    factor,
                    b.t(l),
                    b.steps(l),
                    &b.step_end(l),
                    lane_energy_estimate(b, l, h0),
                    || lane_energy_error(b, l, h0, None),
                ) {
                    let next = (request.pace.n + 1) as f64 * request.rules.tau;
                    slots[l].set(Slot::Asked(next, true));
                    continue;
                }
            }
            slots[l].set(Slot::Done(factor, r));
            // A lane that frees up asks for work at once (the feed may have some now).
            waiting &= !poll(l, &mut lanes);
        }
    }
}

/// [`TaylorLanes::renormalise_and_step`] compiled for AVX-512.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx512vl,avx512dq,avx512bw,avx512cd")]
unsafe fn taylor_step_avx512<H, T, const N: usize, const K: usize, const L: usize>(
    batch: &mut TaylorLanes<'_, H, T, N, K, L>,
    renormalise: &[bool; L],
    asked: &[Option<f64>; L],
) -> LaneSteps<L>
where
    H: TaylorSeries<N>,
    T: Lanewise + Real<Lead = Lanes<L>>,
{
    batch.renormalise_and_step(renormalise, asked)
}

/// [`Dop853Lanes::renormalise_and_step`] compiled for AVX-512.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx512vl,avx512dq,avx512bw,avx512cd")]
unsafe fn dop853_step_avx512<H: Hamiltonian<N>, const N: usize, const K: usize, const L: usize>(
    batch: &mut Dop853Lanes<'_, H, N, K, L>,
    renormalise: &[bool; L],
    asked: &[Option<f64>; L],
) -> LaneSteps<L> {
    batch.renormalise_and_step(renormalise, asked)
}
