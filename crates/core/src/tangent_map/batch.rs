//! The batched stepper: `L` orbits advanced in lockstep, one per SIMD lane.
//!
//! A single orbit is a chain of dependent operations and leaves most of a core idle; `L`
//! independent orbits in structure-of-arrays form fill the vector units. The step is the same
//! generic code as the scalar one (on [`Lanes<L>`]), and the per-step checks run vectorised on
//! the fast path; only lanes where something happens (a crossing, a rescaling, a possible early
//! stop, the end) drop to the scalar [`Tracker`](crate::orbit) that the one-orbit driver uses.
//! Every lane therefore produces bit for bit the result of [`integrate`](crate::orbit::integrate)
//! for its orbit. A lane whose orbit ends is refilled from the caller's [`BatchFeed`] at once,
//! so the lanes stay full however unequal the orbits' lengths (early stops), and each result
//! reaches the caller the moment its orbit ends.

use crate::arith::real::{dot, lane_bits, Lanes, Real};
use crate::indicators::{
    alignment_factor, in_band, may_be_below, out_of_band_bits, sali, MINORS_RESOLVE, RESCALE_ABOVE,
    RESCALE_BELOW,
};
use crate::orbit::{
    escape_radius2, initial_vectors, integrate, steps_to, OrbitConfig, OrbitResult, Requests,
    Tracker, ENERGY_CHECK_EVERY,
};
use crate::phase::Phase;
use crate::section::{
    locate_upward_lanes, locate_upward_lanes_settling, CellLattice, Crossing, CrossingStep,
};
use crate::systems::hamiltonian::Hamiltonian;
use crate::tangent_map::map::{AnyShape, CorrectedDkd, EdgeIncrement, StepShape, TangentMap};

// `LaneState::energy_phase` has a bit per phase of the energy checks.
const _: () = assert!(ENERGY_CHECK_EVERY <= 64);

/// A copy of `a` made one vector at a time (see its use in [`feed_loop`]). With 4 lanes each
/// element is one 256-bit load that LLVM can neither merge with its neighbour into a 512-bit
/// move nor split: a volatile read of the array type goes as four scalar loads and stores per
/// vector (32 memory operations a step), and the crossing test then read q1 back as a vector
/// from the four stores, which store forwarding cannot serve.
#[inline(always)]
fn vector_copy<const N: usize, const L: usize>(a: &[Lanes<L>; N]) -> [Lanes<L>; N] {
    #[cfg(all(target_arch = "x86_64", target_feature = "avx"))]
    if L == 4 {
        return core::array::from_fn(|i| {
            let v: core::arch::x86_64::__m256d;
            // SAFETY: an aligned 32-byte read (`Lanes` is 32-aligned, and with 4 lanes 32 bytes)
            // of an initialised element of a live array (AVX is compiled in: see the `cfg`).
            unsafe {
                core::arch::asm!(
                    "vmovapd {v}, ymmword ptr [{p}]",
                    v = out(ymm_reg) v,
                    p = in(reg) &a[i] as *const Lanes<L>,
                    options(pure, readonly, nostack, preserves_flags),
                );
                core::mem::transmute_copy::<core::arch::x86_64::__m256d, Lanes<L>>(&v)
            }
        });
    }
    // SAFETY: reads of initialised, aligned elements of a live array.
    core::array::from_fn(|i| unsafe { core::ptr::read_volatile(&a[i]) })
}

fn get_lane<const N: usize, const K: usize, const L: usize>(
    x: &Phase<Lanes<L>, N, K>,
    inc: &EdgeIncrement<Lanes<L>, N, K>,
    l: usize,
) -> (Phase<f64, N, K>, EdgeIncrement<f64, N, K>) {
    let v = |a: &[Lanes<L>; N]| -> [f64; N] { core::array::from_fn(|i| a[i].0[l]) };
    (
        Phase {
            q: v(&x.q),
            p: v(&x.p),
            dq: core::array::from_fn(|k| v(&x.dq[k])),
            dp: core::array::from_fn(|k| v(&x.dp[k])),
        },
        EdgeIncrement {
            orbit: v(&inc.orbit),
            dev: core::array::from_fn(|k| v(&inc.dev[k])),
        },
    )
}

fn set_lane<const N: usize, const K: usize, const L: usize>(
    x: &mut Phase<Lanes<L>, N, K>,
    inc: &mut EdgeIncrement<Lanes<L>, N, K>,
    l: usize,
    sx: &Phase<f64, N, K>,
    sinc: &EdgeIncrement<f64, N, K>,
) {
    for i in 0..N {
        x.q[i].0[l] = sx.q[i];
        x.p[i].0[l] = sx.p[i];
        inc.orbit[i].0[l] = sinc.orbit[i];
        for k in 0..K {
            x.dq[k][i].0[l] = sx.dq[k][i];
            x.dp[k][i].0[l] = sx.dp[k][i];
            inc.dev[k][i].0[l] = sinc.dev[k][i];
        }
    }
}

/// Whether SALI of lane `l`'s first two deviation vectors is below `theta`, decided as the
/// tracker decides it (the exact SALI on the same bits), after [`may_be_below`]'s screen: a
/// few multiply-adds that clear most lanes where the exact SALI takes three roots and two
/// divisions in a chain.
#[inline(never)]
fn lane_sali_below<const N: usize, const K: usize, const L: usize>(
    x: &Phase<Lanes<L>, N, K>,
    l: usize,
    theta: f64,
) -> bool {
    let v = |a: &[Lanes<L>; N]| -> [f64; N] { core::array::from_fn(|i| a[i].0[l]) };
    let (w1, w2) = ((v(&x.dq[0]), v(&x.dp[0])), (v(&x.dq[1]), v(&x.dp[1])));
    may_be_below((&w1.0, &w1.1), (&w2.0, &w2.1), theta)
        && sali((&w1.0, &w1.1), (&w2.0, &w2.1)) < theta
}

struct Job<'h, H, const N: usize, const K: usize> {
    id: usize,
    tracker: Tracker<'h, H, K>,
    result: OrbitResult<N>,
}

/// What a [`BatchFeed`] answers when a lane asks for work.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Feed<const N: usize> {
    /// Integrate the orbit from (q, p); the id comes back with its result.
    Orbit(usize, [f64; N], [f64; N]),
    /// Nothing now; more may come (an idle lane asks again at the next poll, see
    /// [`poll_interval`]).
    Wait,
    /// Nothing more will come.
    Done,
}

/// The batched driver's source of orbits and sink of results, with hooks that let the caller
/// watch crossings as they are found and abandon orbits it no longer needs (the fast-PSS
/// engine abandons orbits whose cell another orbit will, or very likely will, label). Hooks
/// never change the results of the orbits that complete.
pub trait BatchFeed<const N: usize> {
    /// The next orbit for a free lane. `all_idle` is true when no lane has an orbit: the feed
    /// may then block until it has one or knows there are none.
    fn next(&mut self, all_idle: bool) -> Feed<N>;
    /// Orbit `id` ended with `result`.
    fn finished(&mut self, id: usize, result: OrbitResult<N>);
    /// Called for every upward crossing of orbit `id` when it is located.
    fn on_crossing(&mut self, _id: usize, _crossing: &Crossing<N>) {}
    /// The crossings `crossings` of orbits `ids` (pairwise, in order), located together: one
    /// [`BatchFeed::on_crossing`] each unless the feed does better with the whole group (the
    /// embedded fast-PSS feed finds every crossing's cell first, so that the divisions go as
    /// vectors instead of one pair at a time between calls).
    fn on_crossings(&mut self, ids: &[usize], crossings: &[Crossing<N>]) {
        for (&id, c) in ids.iter().zip(crossings) {
            self.on_crossing(id, c);
        }
    }
    /// Whether each result carries its orbit's crossings, as `integrate`'s does. A feed that
    /// books them as they come through [`BatchFeed::on_crossing`] says no: a regular orbit at
    /// τ = 0.5 crosses 1 500 times, and the list's growth (copies, allocations, page faults)
    /// is a visible cost in a fast-PSS run (figures: docs/performance.md).
    fn keeps_crossings(&self) -> bool {
        true
    }
    /// The lattice whose cell is all the feed uses of a crossing (a grid's cells on the (q_2,
    /// p_2) plane), if it uses no more. Then the driver ends a crossing's search as soon as its
    /// cell is certain ([`locate_upward_lanes_settling`]), and the crossings handed to
    /// [`BatchFeed::on_crossing`] and kept in results are points of the orbit within a radius
    /// of the crossing that keeps them in its cell: at τ = 0.5 one partial step and the rest
    /// of it instead of three or four, most of the search's cost. The lattice is a value
    /// rather than a callback so that the test inlines into the search.
    fn books_by_cell(&self) -> Option<CellLattice> {
        None
    }
    /// Polled every [`poll_interval`] steps: true abandons orbit `id` (no result is reported).
    fn cancelled(&mut self, _id: usize) -> bool {
        false
    }
    /// Orbit `id` was abandoned after `steps` steps.
    fn abandoned(&mut self, _id: usize, _steps: u64) {}
}

/// A feed borrowed mutably is a feed, so that a `&mut dyn BatchFeed` can drive the copies of
/// the drivers compiled once in this crate ([`crate::run::integrate_feed_henon_heiles`]).
impl<const N: usize, F: BatchFeed<N> + ?Sized> BatchFeed<N> for &mut F {
    fn next(&mut self, all_idle: bool) -> Feed<N> {
        (**self).next(all_idle)
    }
    fn finished(&mut self, id: usize, result: OrbitResult<N>) {
        (**self).finished(id, result)
    }
    fn on_crossing(&mut self, id: usize, crossing: &Crossing<N>) {
        (**self).on_crossing(id, crossing)
    }
    fn on_crossings(&mut self, ids: &[usize], crossings: &[Crossing<N>]) {
        (**self).on_crossings(ids, crossings)
    }
    fn keeps_crossings(&self) -> bool {
        (**self).keeps_crossings()
    }
    fn books_by_cell(&self) -> Option<CellLattice> {
        (**self).books_by_cell()
    }
    fn cancelled(&mut self, id: usize) -> bool {
        (**self).cancelled(id)
    }
    fn abandoned(&mut self, id: usize, steps: u64) {
        (**self).abandoned(id, steps)
    }
}

/// Steps between polls of [`BatchFeed::cancelled`] (and between requests for work of idle
/// lanes): 64 steps, or a time of 4 when that is more. A poll reads shared claims at random
/// places, about as costly as a step, so polls are spaced out (figures: docs/performance.md),
/// and a claim ages little in a time of 4 against orbits of 1e4.
pub fn poll_interval(tau: f64) -> u64 {
    let by_time = (4.0 / tau).ceil();
    if by_time.is_finite() && by_time > 64.0 {
        by_time.min(1e6) as u64
    } else {
        64
    }
}

/// Steps between the requests for work of idle lanes when they come before the next
/// [`poll_interval`]: a feed may answer [`Feed::Wait`] for a moment (the fast-PSS engine does
/// while the outcomes of the orbits that just ended are on their way to the ledger), and an
/// idle lane steps at the full cost.
pub(crate) const IDLE_POLL: u64 = 8;

/// Integrates every initial condition of `ics` as [`integrate`](crate::orbit::integrate) would,
/// `L` at a time in SIMD lanes, and hands each result to `sink` with its index as soon as it
/// is done (so in completion order, not input order).
pub fn integrate_batch<H: Hamiltonian<N>, const N: usize, const K: usize, const L: usize>(
    map: &TangentMap<'_, H>,
    ics: &[([f64; N], [f64; N])],
    config: &OrbitConfig,
    requests: &Requests,
    sink: impl FnMut(usize, OrbitResult<N>),
) {
    integrate_batch_on::<H, N, K, L>(Isa::detect(), map, ics, config, requests, sink)
}

/// [`integrate_batch`] on the instruction set the caller chooses (see [`integrate_feed_on`]).
pub fn integrate_batch_on<H: Hamiltonian<N>, const N: usize, const K: usize, const L: usize>(
    isa: Isa,
    map: &TangentMap<'_, H>,
    ics: &[([f64; N], [f64; N])],
    config: &OrbitConfig,
    requests: &Requests,
    sink: impl FnMut(usize, OrbitResult<N>),
) {
    let mut feed = IcsFeed::new(ics, sink);
    integrate_feed_on::<H, N, K, L>(isa, map, config, requests, &mut feed)
}

/// The orbits from a list of initial conditions, each result handed to `sink`.
pub(crate) struct IcsFeed<'a, const N: usize, S> {
    ics: &'a [([f64; N], [f64; N])],
    next: usize,
    sink: S,
}

impl<'a, const N: usize, S> IcsFeed<'a, N, S> {
    pub(crate) fn new(ics: &'a [([f64; N], [f64; N])], sink: S) -> Self {
        IcsFeed { ics, next: 0, sink }
    }
}

impl<const N: usize, S: FnMut(usize, OrbitResult<N>)> BatchFeed<N> for IcsFeed<'_, N, S> {
    fn next(&mut self, _all_idle: bool) -> Feed<N> {
        match self.ics.get(self.next) {
            Some(&(q, p)) => {
                self.next += 1;
                Feed::Orbit(self.next - 1, q, p)
            }
            None => Feed::Done,
        }
    }
    fn finished(&mut self, id: usize, result: OrbitResult<N>) {
        (self.sink)(id, result)
    }
}

/// What every lane's orbit is integrated with.
struct Setup<'a, 'h, H, const N: usize, const K: usize> {
    map: &'a TangentMap<'h, H>,
    config: &'a OrbitConfig,
    requests: &'a Requests,
    /// The initial deviation vectors (δq, δp).
    initial: ([[f64; N]; K], [[f64; N]; K]),
}

/// The lanes: their phase points, the orbits in them, and what the vectorised screening
/// compares against.
struct LaneState<'h, H, const N: usize, const K: usize, const L: usize> {
    x: Phase<Lanes<L>, N, K>,
    inc: EdgeIncrement<Lanes<L>, N, K>,
    jobs: [Option<Job<'h, H, N, K>>; L],
    /// Initial energy of each lane's orbit.
    h0: Lanes<L>,
    /// Half the energy-drift limit times the orbit's energy scale: a conservative screen for
    /// the tracker's check (a spurious flag costs one scalar pass that does nothing).
    drift_screen: Lanes<L>,
    active: [bool; L],
    /// Steps taken by the driver, all lanes together.
    step: u64,
    /// `step` when each lane's orbit came in: the orbit has taken `step - start[l]` steps.
    start: [u64; L],
    /// The step of each lane's next time-series sample (`u64::MAX`: none).
    sample_at: [u64; L],
    /// A driver step at or before the first one at which some lane's orbit takes its last
    /// step or a sample ([`LaneState::lane_due`]).
    due: u64,
    /// Bit k: some lane's orbit is due for its energy check (every [`ENERGY_CHECK_EVERY`] of
    /// its steps) at the driver steps ≡ k modulo that period.
    energy_phase: u64,
    /// The orbits' last step, and whether the tracker is due at every step.
    n_final: u64,
    every_step: bool,
    /// The feed said Done.
    exhausted: bool,
    /// The steps before this one are a quiet window (see [`QuietRules`]); 0 when none is open.
    quiet_until: u64,
}

impl<'h, H: Hamiltonian<N>, const N: usize, const K: usize, const L: usize>
    LaneState<'h, H, N, K, L>
{
    fn new(map: &TangentMap<'h, H>, n_final: u64, every_step: bool) -> Self {
        let x = Phase::zero();
        LaneState {
            inc: map.edge_increment(&x),
            x,
            jobs: core::array::from_fn(|_| None),
            h0: Lanes([0.0; L]),
            drift_screen: Lanes([0.0; L]),
            active: [false; L],
            step: 0,
            start: [0; L],
            sample_at: [u64::MAX; L],
            due: 0,
            energy_phase: 0,
            n_final,
            every_step,
            exhausted: false,
            quiet_until: 0,
        }
    }

    /// Steps taken by lane `l`'s orbit.
    fn n(&self, l: usize) -> u64 {
        self.step - self.start[l]
    }

    /// The first driver step after this one at which lane `l`'s orbit takes its last step or
    /// a sample (every step when the tracker is due at every step), as [`screen`] tests them.
    fn lane_due(&self, l: usize) -> u64 {
        if !self.active[l] {
            return u64::MAX;
        }
        if self.every_step {
            return self.step + 1;
        }
        let n_next = self.n(l) + 1;
        let mut n_due = self.n_final.max(n_next);
        if self.sample_at[l] >= n_next {
            n_due = n_due.min(self.sample_at[l]);
        }
        self.start[l] + n_due
    }

    /// Lane `l`'s orbit came in or its next sample moved: keeps `due` at or before its turn,
    /// and the energy checks' phases up to date.
    fn lane_changed(&mut self, l: usize) {
        self.due = self.due.min(self.lane_due(l));
        self.energy_phase = (0..L).filter(|&l| self.active[l]).fold(0, |bits, l| {
            bits | 1 << (self.start[l] % ENERGY_CHECK_EVERY)
        });
    }

    /// Whether some lane's per-orbit tests may be due at this step: its energy check, its
    /// last step or a sample.
    fn due_now(&mut self) -> bool {
        let rare = self.step >= self.due;
        if rare {
            self.due = (0..L).map(|l| self.lane_due(l)).min().unwrap_or(u64::MAX);
        }
        rare | (self.energy_phase >> (self.step % ENERGY_CHECK_EVERY) & 1 != 0)
    }

    /// Puts the feed's next orbit (if any) into lane `l`, whose orbit has left; an empty lane
    /// holds zeros and is never flagged (its `active` is false).
    fn fill(
        &mut self,
        l: usize,
        all_idle: bool,
        setup: &Setup<'_, 'h, H, N, K>,
        feed: &mut impl BatchFeed<N>,
    ) {
        let next = if self.exhausted {
            Feed::Done
        } else {
            feed.next(all_idle)
        };
        let map = setup.map;
        let (sx, job) = match next {
            Feed::Orbit(id, q, p) => {
                let (dq, dp) = setup.initial;
                let sx = Phase { q, p, dq, dp };
                let mut result = OrbitResult::empty();
                let mut tracker = Tracker::new(map, &sx, setup.config, setup.requests);
                tracker.begin(&mut result);
                let h0 = map.hamiltonian().energy(&q, &p);
                let scale = if h0.abs() > 1e-300 { h0.abs() } else { 1.0 };
                self.h0.0[l] = h0;
                self.drift_screen.0[l] = 0.5 * setup.config.thresholds.energy_drift * scale;
                let job = Job {
                    id,
                    tracker,
                    result,
                };
                (sx, Some(job))
            }
            Feed::Wait | Feed::Done => {
                self.exhausted |= next == Feed::Done;
                if !self.active[l] {
                    // Still empty: its zeros are a fixed point of the step, so there is
                    // nothing to reset. Idle lanes ask every few steps while a worker waits
                    // for leases, and resetting them each time costs a visible share of its CPU.
                    return;
                }
                (Phase::zero(), None)
            }
        };
        set_lane(&mut self.x, &mut self.inc, l, &sx, &map.edge_increment(&sx));
        // The new orbit was not at the window's check.
        self.quiet_until = 0;
        self.active[l] = job.is_some();
        self.start[l] = self.step;
        self.sample_at[l] = job
            .as_ref()
            .map_or(u64::MAX, |j| j.tracker.next_sample_step());
        self.jobs[l] = job;
        self.lane_changed(l);
    }
}

/// The instruction sets the batched driver can be compiled for. The build pins x86-64-v3
/// (AVX2 + FMA) for every crate; hosts with AVX-512 also run a copy of the driver compiled
/// for it (32 vector registers; 8 lanes in one register, or 4 lanes whose whole state fits in
/// registers), chosen at run time. Both perform
/// the same IEEE operations in the same order in every lane (Rust never reassociates or
/// contracts floating-point arithmetic, and the AVX-512 forms of add, multiply, FMA, divide,
/// square root and compare round exactly as the AVX2 ones), so the choice changes speed,
/// never bits; `tests/batch.rs` checks it on hosts that have AVX-512.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Isa {
    /// The pinned target level, on every host.
    Pinned,
    /// AVX-512 (F, VL, DQ, BW, CD), on hosts that have it.
    Avx512,
}

impl Isa {
    /// The best the host offers, or [`Isa::Pinned`] where the engine choices say so
    /// ([`crate::engine::EngineChoices::pinned_simd`], for comparisons).
    pub fn detect() -> Isa {
        static BEST: std::sync::OnceLock<Isa> = std::sync::OnceLock::new();
        let best = *BEST.get_or_init(|| {
            if Isa::Avx512.available() {
                Isa::Avx512
            } else {
                Isa::Pinned
            }
        });
        if crate::engine::choices().pinned_simd {
            Isa::Pinned
        } else {
            best
        }
    }

    /// Whether this host can run code compiled for `self`.
    pub fn available(self) -> bool {
        match self {
            Isa::Pinned => true,
            #[cfg(target_arch = "x86_64")]
            Isa::Avx512 => {
                std::arch::is_x86_feature_detected!("avx512f")
                    && std::arch::is_x86_feature_detected!("avx512vl")
                    && std::arch::is_x86_feature_detected!("avx512dq")
                    && std::arch::is_x86_feature_detected!("avx512bw")
                    && std::arch::is_x86_feature_detected!("avx512cd")
            }
            #[cfg(not(target_arch = "x86_64"))]
            Isa::Avx512 => false,
        }
    }

    /// Lanes per batch that suit this instruction set: one vector register per variable.
    /// AVX-512's 32 registers hold 8 lanes' state and increments without spills; pinned code's
    /// 16 cannot hold two groups of four, so it runs 4 (`batch_profile` figures:
    /// docs/performance.md).
    pub fn lanes(self) -> usize {
        match self {
            Isa::Pinned => 4,
            Isa::Avx512 => 8,
        }
    }
}

/// Integrates the orbits `feed` supplies, `L` at a time in SIMD lanes, each exactly as
/// [`integrate`](crate::orbit::integrate) would, and hands each result to the feed the moment
/// its orbit ends. Returns when the feed says [`Feed::Done`] and every lane is empty. Runs the
/// copy compiled for [`Isa::detect`].
pub fn integrate_feed<H: Hamiltonian<N>, const N: usize, const K: usize, const L: usize>(
    map: &TangentMap<'_, H>,
    config: &OrbitConfig,
    requests: &Requests,
    feed: &mut impl BatchFeed<N>,
) {
    integrate_feed_on::<H, N, K, L>(Isa::detect(), map, config, requests, feed)
}

/// [`integrate_feed`] with the instruction set chosen by the caller. The AVX-512 copy serves
/// 4 lanes or more (see [`Isa::lanes`] for the speeds); an `isa` the host lacks falls back to
/// [`Isa::Pinned`].
pub fn integrate_feed_on<H: Hamiltonian<N>, const N: usize, const K: usize, const L: usize>(
    isa: Isa,
    map: &TangentMap<'_, H>,
    config: &OrbitConfig,
    requests: &Requests,
    feed: &mut impl BatchFeed<N>,
) {
    match CorrectedDkd::of(map) {
        Some(shape) => feed_on::<H, N, K, L, _>(isa, shape, map, config, requests, feed),
        None => feed_on::<H, N, K, L, _>(isa, AnyShape, map, config, requests, feed),
    }
}

/// [`integrate_feed_on`] with the loop compiled for the steps' `shape`.
fn feed_on<H: Hamiltonian<N>, const N: usize, const K: usize, const L: usize, S: StepShape>(
    isa: Isa,
    shape: S,
    map: &TangentMap<'_, H>,
    config: &OrbitConfig,
    requests: &Requests,
    feed: &mut impl BatchFeed<N>,
) {
    #[cfg(target_arch = "x86_64")]
    if isa == Isa::Avx512 && L >= 4 && isa.available() {
        // SAFETY: the host has every feature the function is compiled for (checked above).
        return unsafe { feed_loop_avx512::<H, N, K, L, S>(shape, map, config, requests, feed) };
    }
    let _ = isa;
    feed_loop::<H, N, K, L, false, S>(shape, map, config, requests, feed)
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx512vl,avx512dq,avx512bw,avx512cd")]
unsafe fn feed_loop_avx512<
    H: Hamiltonian<N>,
    const N: usize,
    const K: usize,
    const L: usize,
    S: StepShape,
>(
    shape: S,
    map: &TangentMap<'_, H>,
    config: &OrbitConfig,
    requests: &Requests,
    feed: &mut impl BatchFeed<N>,
) {
    // The state stays resident with 8 lanes, where that is faster, and not with 4, where it is
    // slower. The resident loop keeps the map's own dispatch: compiled for a fixed shape it
    // keeps its state in memory (`batch_profile` figures: docs/performance.md).
    if L >= 8 {
        let _ = shape;
        feed_loop::<H, N, K, L, true, AnyShape>(AnyShape, map, config, requests, feed)
    } else {
        feed_loop::<H, N, K, L, false, S>(shape, map, config, requests, feed)
    }
}

/// The driver itself, inlined into each instruction set's copy so that the step and the
/// screening (all `#[inline(always)]`) are compiled for it. `RESIDENT`: the lanes' state stays
/// in registers across steps and goes to memory only for the steps that need the scalar paths
/// (the AVX-512 copy with 8 lanes, one register per variable; with AVX2's 16 registers it
/// spills, and 4 lanes in the AVX-512 copy run slower resident; figures:
/// docs/performance.md).
#[inline(always)]
fn feed_loop<
    H: Hamiltonian<N>,
    const N: usize,
    const K: usize,
    const L: usize,
    const RESIDENT: bool,
    S: StepShape,
>(
    shape: S,
    map: &TangentMap<'_, H>,
    config: &OrbitConfig,
    requests: &Requests,
    feed: &mut impl BatchFeed<N>,
) {
    let n_final = steps_to(config.t_final, map.tau());
    if n_final == 0 {
        loop {
            match feed.next(true) {
                Feed::Orbit(id, q, p) => {
                    feed.finished(id, integrate::<H, N, K>(map, q, p, config, requests))
                }
                Feed::Wait => continue,
                Feed::Done => return,
            }
        }
    }
    let ham = map.hamiltonian();
    let setup = Setup {
        map,
        config,
        requests,
        initial: initial_vectors::<N, K>(config.deviation),
    };
    let mut st = LaneState::<H, N, K, L>::new(map, n_final, requests.every_step());
    for l in 0..L {
        st.fill(l, false, &setup, feed);
    }
    let chaotic = config.thresholds.chaotic;
    let screen_rules = ScreenRules {
        n_final,
        r2_max: escape_radius2(ham, config),
        well_r2: ham.well_radius() * ham.well_radius(),
        factor: alignment_factor(chaotic),
        crossings: requests.crossings,
        early: config.thresholds.early_stop,
        every_step: requests.every_step(),
        minors: (config.thresholds.early_stop && chaotic >= MINORS_RESOLVE)
            .then_some(4.0 * chaotic * chaotic),
    };
    // The 4-lane loop's quiet windows (the 8-lane resident loop keeps every screen: any more
    // work in it makes LLVM give up keeping its state in registers).
    let quiet_rules = if L == 4 && !RESIDENT && !requests.every_step() {
        QuietRules::new(shape, map, config)
    } else {
        None
    };
    let poll = poll_interval(map.tau());
    // Crossings found but not yet located: located together when the queue is full or before
    // an orbit with one queued leaves its lane. Each lane's entries are in time order, so
    // every orbit's crossings are appended in time order.
    let mut queued = CrossingQueue::<N>::new();
    // The state between steps when `RESIDENT` (`st.x` and `st.inc` hold it only around the
    // scalar paths).
    let (mut x_kept, mut inc_kept) = (st.x, st.inc);

    loop {
        if !st.active.iter().any(|&a| a) {
            if st.exhausted {
                return;
            }
            st.fill(0, true, &setup, feed);
            for l in 1..L {
                if st.active[0] {
                    st.fill(l, false, &setup, feed);
                }
            }
            if RESIDENT {
                (x_kept, inc_kept) = (st.x, st.inc);
            }
            continue;
        }
        st.step += 1;
        let step = st.step;
        // One vector at a time: copied as whole arrays, LLVM moves two 4-lane vectors in one
        // 512-bit register in the AVX-512 copy, and on Intel cores a 512-bit instruction in
        // every step shuts the second vector port (`batch_profile` figures:
        // docs/performance.md). Volatile reads cannot be merged.
        let (q_prev, p_prev): ([Lanes<L>; N], [Lanes<L>; N]) = if RESIDENT {
            (x_kept.q, x_kept.p)
        } else {
            (vector_copy(&st.x.q), vector_copy(&st.x.p))
        };
        // The step and the screening work on a local copy (stored back at once unless
        // `RESIDENT`): screening the stored state makes the compiler reload it in pieces that
        // defeat store forwarding, a large share of the 8-lane AVX-512 loop (figures:
        // docs/performance.md).
        let x = if RESIDENT {
            shape.advance(map, &mut x_kept, &mut inc_kept);
            x_kept
        } else {
            let mut x = st.x;
            shape.advance(map, &mut x, &mut st.inc);
            st.x = x;
            x
        };

        let quiet = step < st.quiet_until;
        let Flags {
            mut flagged,
            only_aligned,
            only_crossed,
            calm,
            left,
        } = screen(
            ham,
            &x,
            &mut st,
            &screen_rules,
            quiet_rules.as_ref().map(|r| (r, quiet)),
            &q_prev[0],
        );
        if let (true, Some(r)) = (calm, &quiet_rules) {
            st.quiet_until = step + r.steps;
        }
        if left != 0 {
            st.quiet_until = 0;
        }
        let full_poll = step.is_multiple_of(poll);
        let idle_poll =
            step.is_multiple_of(IDLE_POLL) && !st.exhausted && st.active.iter().any(|&a| !a);
        // The scalar paths below read and write the lanes' state in `st`. (Storing it only
        // where they need it is slower: reading lanes of the local copy makes LLVM keep that
        // copy in memory.)
        let scalar = flagged != 0 || full_poll || idle_poll;
        if RESIDENT && scalar {
            (st.x, st.inc) = (x_kept, inc_kept);
        }
        if full_poll || idle_poll {
            for l in 0..L {
                let cancel = match st.jobs[l].as_ref() {
                    Some(j) => full_poll && feed.cancelled(j.id),
                    None => !st.exhausted,
                };
                if cancel {
                    if st.jobs[l].is_some() {
                        // The lane's queued crossings first, while its orbit is still there.
                        queued.flush(map, &mut st.jobs, feed);
                    }
                    if let Some(j) = st.jobs[l].take() {
                        feed.abandoned(j.id, st.n(l));
                    }
                    st.fill(l, false, &setup, feed);
                    flagged &= !(1 << l);
                }
            }
        }
        while flagged != 0 {
            let l = flagged.trailing_zeros() as usize;
            let bit = 1u64 << l;
            flagged &= flagged - 1;
            // The root-free alignment pre-filter cannot resolve angles below ~3e-7 (cos² is 1
            // to f64's precision), and at τ = 0.01 a chaotic orbit spends thousands of steps
            // there on its way to the threshold: most flagged steps of a 400×400 run. When
            // that is the only flag, the exact SALI (the tracker's own function on
            // the same bits) settles it at a fraction of the scalar pass.
            if only_aligned & bit != 0 && !lane_sali_below(&st.x, l, chaotic) {
                continue;
            }
            let n = st.n(l);
            let t_prev = (n - 1) as f64 * map.tau();
            if only_crossed & bit != 0 {
                // Nothing else is due, so the tracker's pass would only flag the crossing, and
                // at τ = 0.5 that pass on every crossing is a large share of the stepping
                // thread's time (figures: docs/performance.md).
                if queued.push_lane(l, &q_prev, &p_prev, t_prev, st.x.q[0].0[l]) {
                    queued.flush(map, &mut st.jobs, feed);
                }
                continue;
            }
            let job = st.jobs[l].as_mut().expect("flagged lanes are active");
            let qp: [f64; N] = core::array::from_fn(|i| q_prev[i].0[l]);
            let pp: [f64; N] = core::array::from_fn(|i| p_prev[i].0[l]);
            let (mut sx, mut sinc) = get_lane(&st.x, &st.inc, l);
            let q1_end = sx.q[0];
            let mut crossed = false;
            let stop = job.tracker.after_step(
                map,
                n,
                &qp,
                &pp,
                &mut sx,
                &mut sinc,
                &mut job.result,
                Some(&mut crossed),
            );
            if crossed && queued.push_lane(l, &q_prev, &p_prev, t_prev, q1_end) {
                queued.flush(map, &mut st.jobs, feed);
            }
            if stop || n == n_final {
                queued.flush(map, &mut st.jobs, feed);
                let mut j = st.jobs[l].take().expect("active");
                j.tracker.finish(n, &sx, &mut j.result);
                feed.finished(j.id, j.result);
                st.fill(l, false, &setup, feed);
            } else {
                let job = st.jobs[l].as_ref().expect("active");
                st.sample_at[l] = job.tracker.next_sample_step();
                st.lane_changed(l);
                set_lane(&mut st.x, &mut st.inc, l, &sx, &sinc);
            }
        }
        if RESIDENT && scalar {
            (x_kept, inc_kept) = (st.x, st.inc);
        }
    }
}

/// Quiet windows: after a step at which every active lane is calm — within |q| ≤ `r2`'s
/// root and |p| ≤ `p2`'s, its deviation vectors' squared norms inside `band`, and (with the
/// early stop) the sine of their angle above 2θ_q — the next `steps − 1` steps screen only
/// what can still happen in them: crossings, the per-orbit tests due (energy, samples, the
/// last step) and each lane's |q| against the radius. The other tests of the tracker cannot
/// fire there: with Γ the [`StepShape::stretch_bound`] of the window (positions within the
/// radius at every step's end, as screened; momenta from the check's bound), every
/// deviation vector's norm changes by at most Γ, so a squared norm inside `band` (2Γ² inside
/// the rescaling band) stays inside the rescaling band; and the sine of the angle between
/// two vectors shrinks by at most Γ⁴ (the map's smallest singular value is at least 1/Γ),
/// so with θ_q = Γ⁴θ it stays above 2θ, and SALI ≥ that sine never falls below θ. A lane
/// that leaves the radius gets the tracker's full pass at that step and ends the window, as
/// does every new orbit (it was not at the check). The lanes' results are those of the
/// scalar driver, bit for bit: a skipped test is one that would have found nothing.
/// The screening these windows skip is a large share of the stepping loop. A bound above
/// [`QUIET_ANGLE_STRETCH`] gives longer windows but leaves lanes restless at larger SALI, and
/// fewer steps are quiet (figures: docs/performance.md).
struct QuietRules {
    /// From a calm step to the next full screen.
    steps: u64,
    r2: f64,
    p2: f64,
    band: (f64, f64),
    /// [`alignment_factor`] of θ_q, with the early stop.
    factor: Option<f64>,
}

/// The radius and momentum bound of the quiet windows: Hénon–Heiles orbits below the escape
/// energy stay within |q| < 1 and |p|² ≤ 2H; larger ones are screened at every step.
const QUIET_RADIUS: f64 = 1.0;
const QUIET_MOMENTUM: f64 = 1.0;
/// The longest window, and the most a window may stretch the angles (Γ⁴ ≤ this). A lane is
/// restless while its vectors' sine is below 2Γ⁴θ, or below ~3.7e-7 where the root-free
/// test's slack (1e-13 in sin²) decides: at θ = 1e-8 and Γ⁴ ≤ 10 the two meet.
const QUIET_STEPS_MAX: u64 = 64;
const QUIET_ANGLE_STRETCH: f64 = 10.0;

impl QuietRules {
    /// The rules for `map`'s steps taken in `shape`, if the shape and the system bound the
    /// stretch and the window would be two steps or more.
    fn new<H: Hamiltonian<N>, const N: usize, S: StepShape>(
        shape: S,
        map: &TangentMap<'_, H>,
        config: &OrbitConfig,
    ) -> Option<Self> {
        let radius = QUIET_RADIUS.min(escape_radius2(map.hamiltonian(), config).sqrt());
        let early = config.thresholds.early_stop;
        let fits = |stretch: f64| {
            stretch * stretch <= 2f64.powi(64) && (!early || stretch.powi(4) <= QUIET_ANGLE_STRETCH)
        };
        let (mut steps, mut stretch) = (0, 0.0);
        for n in 2..=QUIET_STEPS_MAX {
            match shape.stretch_bound(map, radius, QUIET_MOMENTUM, n) {
                Some(g) if fits(g) => (steps, stretch) = (n, g),
                _ => break,
            }
        }
        if steps < 2 {
            return None;
        }
        let g2 = stretch * stretch;
        Some(QuietRules {
            steps,
            r2: radius * radius,
            p2: QUIET_MOMENTUM * QUIET_MOMENTUM,
            band: (2.0 * g2 * RESCALE_BELOW, RESCALE_ABOVE / (2.0 * g2)),
            factor: early.then(|| alignment_factor(config.thresholds.chaotic * g2 * g2)),
        })
    }

    /// The active lanes' bits that are not calm (see [`QuietRules`]) in the state `x`, whose
    /// |q|², deviation vectors' squared norms and the first two vectors' dot product are
    /// given. The `not_*` compares count NaN as not calm.
    #[inline(always)]
    fn restless<const N: usize, const K: usize, const L: usize>(
        &self,
        x: &Phase<Lanes<L>, N, K>,
        r2: Lanes<L>,
        n2: &[Lanes<L>; K],
        c: Lanes<L>,
    ) -> u64 {
        let p2 = dot(&x.p, &x.p);
        let mut bits =
            r2.not_le_bits(Lanes::splat(self.r2)) | p2.not_le_bits(Lanes::splat(self.p2));
        for n2k in n2 {
            bits |= n2k.not_lt_bits(Lanes::splat(self.band.1));
            bits |= n2k.not_gt_bits(Lanes::splat(self.band.0));
        }
        if let Some(factor) = self.factor {
            bits |= (c * c).ge_bits(n2[0] * n2[1] * Lanes::splat(factor));
        }
        bits
    }
}

/// What the vectorised screening compares against, fixed for a run.
struct ScreenRules {
    n_final: u64,
    r2_max: f64,
    /// Squared well radius: a lane beyond it goes to the tracker at every step (its energy is
    /// checked there at every step).
    well_r2: f64,
    factor: f64,
    crossings: bool,
    early: bool,
    /// The tracker is due at every step (energy recorded at every step).
    every_step: bool,
    /// 4θ² for [`minors_may_be_below`] at the early-stop threshold θ, where that test can
    /// resolve it.
    minors: Option<f64>,
}

/// The lanes that need scalar work after a step, as bits (lane `l` is bit `l`).
struct Flags {
    /// Active lanes where the tracker, a crossing or the alignment check is due.
    flagged: u64,
    /// Lanes where nothing but the alignment check may be due.
    only_aligned: u64,
    /// Lanes where nothing but a crossing may be due.
    only_crossed: u64,
    /// At a check: every active lane is calm, so a quiet window may follow.
    calm: bool,
    /// In a quiet window: the active lanes that left its radius (the window ends).
    left: u64,
}

/// Counts the step just taken in every lane and screens the new state: which lanes need the
/// scalar bookkeeping? Every condition under which `Tracker::after_step` acts must raise the
/// flag. `x` is the lanes' new state (the driver's local copy of `st.x`: screening the stored
/// state makes the compiler reload it in pieces that defeat store forwarding) and `q1_prev`
/// holds q1 before the step.
///
/// Two forms of the same conditions. With 4 lanes (one 256-bit vector) each condition is one
/// vector compare and a mask extraction, so a step where no lane needs anything costs no
/// per-lane work, where the element-wise form takes a large share of the stepping thread's
/// time at τ = 0.5. The AVX-512 driver's 8 lanes keep the element-wise form: there the
/// 256-bit masks make LLVM split the whole step into 256-bit halves, while it compiles the
/// element-wise form into 512-bit compares (figures: docs/performance.md).
#[inline(always)]
fn screen<H: Hamiltonian<N>, const N: usize, const K: usize, const L: usize>(
    ham: &H,
    x: &Phase<Lanes<L>, N, K>,
    st: &mut LaneState<'_, H, N, K, L>,
    rules: &ScreenRules,
    quiet: Option<(&QuietRules, bool)>,
    q1_prev: &Lanes<L>,
) -> Flags {
    let r2 = dot(&x.q, &x.q);
    let norms = || {
        let mut n2 = [Lanes([0.0; L]); K];
        for k in 0..K {
            n2[k] = dot(&x.dq[k], &x.dq[k]) + dot(&x.dp[k], &x.dp[k]);
        }
        let c = dot(&x.dq[0], &x.dq[1]) + dot(&x.dp[0], &x.dp[1]);
        (n2, c)
    };
    // The per-lane step counts are tested only at the steps `due_now` announces (a quarter of
    // the steps with 4 lanes), not at every step.
    let due_now = st.due_now();
    let (start, sample_at, step) = (&st.start, &st.sample_at, st.step);
    let n = |l: usize| step - start[l];
    let energy_at = |l: usize| n(l).is_multiple_of(ENERGY_CHECK_EVERY) | (n(l) >= rules.n_final);
    let hard_at = |l: usize| rules.every_step | (n(l) >= rules.n_final) | (n(l) == sample_at[l]);
    if L == 4 {
        let (hard, energy_due) = if due_now {
            let hard = lane_bits::<L>(hard_at);
            (hard, lane_bits::<L>(energy_at) | hard)
        } else {
            (0, 0)
        };
        // In a quiet window the lanes are held within its radius instead of the escape one.
        let in_window = matches!(quiet, Some((_, true)));
        let r2_max = match quiet {
            Some((q, true)) => q.r2,
            _ => rules.r2_max,
        };
        // The `not_*` compares are true for NaN too, which is the point.
        let outside = r2.not_le_bits(Lanes::splat(r2_max));
        let mut f = hard | outside | r2.not_le_bits(Lanes::splat(rules.well_r2));
        let active = lane_bits::<L>(|l| st.active[l]);
        if energy_due & active != 0 {
            let dh = ham.energy(&x.q, &x.p) - st.h0;
            let dh_abs = Lanes(core::array::from_fn(|l| dh.0[l].abs()));
            f |= energy_due & dh_abs.not_le_bits(st.drift_screen);
        }
        let crossed = if rules.crossings {
            q1_prev.lt_bits(Lanes::splat(0.0)) & x.q[0].ge_bits(Lanes::splat(0.0))
        } else {
            0
        };
        if in_window {
            return Flags {
                flagged: (f | crossed) & active,
                only_aligned: 0,
                only_crossed: !f,
                calm: false,
                left: outside & active,
            };
        }
        let (n2, c) = norms();
        for n2k in &n2 {
            f |= out_of_band_bits(*n2k);
        }
        let mut aligned = if rules.early {
            (c * c).ge_bits(n2[0] * n2[1] * Lanes::splat(rules.factor))
        } else {
            0
        };
        if aligned & active != 0 {
            if let Some(four_theta2) = rules.minors {
                aligned &= minors_may_be_below(x, &n2, four_theta2);
            }
        }
        let calm = quiet.is_some_and(|(q, _)| q.restless(x, r2, &n2, c) & active == 0);
        return Flags {
            flagged: (f | crossed | aligned) & active,
            only_aligned: !f & !crossed,
            only_crossed: !f & !aligned,
            calm,
            left: 0,
        };
    }
    let (n2, c) = norms();
    let (hard, energy_due): ([bool; L], [bool; L]) = if due_now {
        (
            core::array::from_fn(hard_at),
            core::array::from_fn(|l| rules.every_step | energy_at(l)),
        )
    } else {
        ([false; L], [false; L])
    };
    let dh = if energy_due.iter().any(|&d| d) {
        ham.energy(&x.q, &x.p) - st.h0
    } else {
        Lanes([0.0; L])
    };
    let mut flagged = [false; L];
    let mut only_aligned = [false; L];
    let mut only_crossed = [false; L];
    // `!(a <= b)` is true for NaN too, which is the point.
    #[allow(clippy::neg_cmp_op_on_partial_ord)]
    for l in 0..L {
        let mut f = energy_due[l] & !(dh.0[l].abs() <= st.drift_screen.0[l]);
        f |= hard[l];
        f |= !(r2.0[l] <= rules.r2_max) | !(r2.0[l] <= rules.well_r2);
        for n2k in &n2 {
            f |= !in_band(n2k.0[l]);
        }
        let crossed = rules.crossings & (q1_prev.0[l] < 0.0) & (x.q[0].0[l] >= 0.0);
        let aligned = rules.early & (c.0[l] * c.0[l] >= n2[0].0[l] * n2[1].0[l] * rules.factor);
        only_aligned[l] = !f & !crossed;
        only_crossed[l] = !f & !aligned;
        flagged[l] = (f | crossed | aligned) & st.active[l];
    }
    Flags {
        flagged: lane_bits::<L>(|l| flagged[l]),
        only_aligned: lane_bits::<L>(|l| only_aligned[l]),
        only_crossed: lane_bits::<L>(|l| only_crossed[l]),
        calm: false,
        left: 0,
    }
}

/// [`may_be_below`] in every lane at once, for the first two deviation vectors of `x` with
/// squared norms `n2[0]`, `n2[1]`: the lanes where SALI may be below θ, as bits. Lanes whose
/// alignment the root-free pre-filter cannot settle (within ~3e-7 of alignment) stay there for
/// thousands of steps on their way to the threshold at τ = 0.01; the minors settle them here
/// in a few vector multiply-adds instead of one scalar pass per lane and step. The test keeps
/// a factor 2 of margin, so its rounding never decides what the exact SALI would not.
#[inline(always)]
fn minors_may_be_below<const N: usize, const K: usize, const L: usize>(
    x: &Phase<Lanes<L>, N, K>,
    n2: &[Lanes<L>; K],
    four_theta2: f64,
) -> u64 {
    let z1 = |i: usize| if i < N { x.dq[0][i] } else { x.dp[0][i - N] };
    let z2 = |i: usize| if i < N { x.dq[1][i] } else { x.dp[1][i - N] };
    let mut g = Lanes::<L>::splat(0.0);
    for i in 0..2 * N {
        for j in i + 1..2 * N {
            let m = z1(i).mul_add(z2(j), -(z1(j) * z2(i)));
            g = m.mul_add(m, g);
        }
    }
    g.lt_bits(Lanes::splat(four_theta2) * n2[0] * n2[1])
}

/// Crossings located together, whatever the driver's lane count: a search is a chain of
/// dependent operations, and 8 searches side by side (two 4-lane vectors) fill the pipeline
/// better than 4; 16 gain nothing more (`crossing_cost` figures: docs/performance.md).
const LOCATE_LANES: usize = 8;

/// Crossings waiting to be located, at most [`LOCATE_LANES`].
struct CrossingQueue<const N: usize> {
    lane: [usize; LOCATE_LANES],
    steps: [CrossingStep<N>; LOCATE_LANES],
    len: usize,
}

impl<const N: usize> CrossingQueue<N> {
    fn new() -> Self {
        CrossingQueue {
            lane: [0; LOCATE_LANES],
            steps: [CrossingStep::ZERO; LOCATE_LANES],
            len: 0,
        }
    }

    /// Queues the crossing of lane `l` in the step that starts at its lane of (`q`, `p`) at
    /// time `t` and ends with q1 = `q1_end`; true when the queue is full. Written into the
    /// slot number by number: a `CrossingStep` assembled first goes through the stack in
    /// pieces of 8 bytes read back as 16 and 32, two failed store forwards per crossing
    /// (figures: docs/performance.md).
    fn push_lane<const L: usize>(
        &mut self,
        l: usize,
        q: &[Lanes<L>; N],
        p: &[Lanes<L>; N],
        t: f64,
        q1_end: f64,
    ) -> bool {
        let slot = &mut self.steps[self.len];
        for i in 0..N {
            slot.q[i] = q[i].0[l];
            slot.p[i] = p[i].0[l];
        }
        slot.t = t;
        slot.q1_end = q1_end;
        self.lane[self.len] = l;
        self.len += 1;
        self.len == LOCATE_LANES
    }

    /// Locates every queued crossing and hands it to its orbit and the feed.
    fn flush<H: Hamiltonian<N>, const K: usize, const L: usize>(
        &mut self,
        map: &TangentMap<'_, H>,
        jobs: &mut [Option<Job<'_, H, N, K>>; L],
        feed: &mut impl BatchFeed<N>,
    ) {
        if self.len == 0 {
            return;
        }
        let steps = &self.steps[..self.len];
        let found = if let Some(cells) = feed.books_by_cell() {
            locate_upward_lanes_settling::<H, N, LOCATE_LANES>(map, steps, &|c, r| {
                cells.same_cell_within(c.q[1], c.p[1], r)
            })
        } else {
            locate_upward_lanes::<H, N, LOCATE_LANES>(map, steps)
        };
        let keep = feed.keeps_crossings();
        let mut ids = [0; LOCATE_LANES];
        for (k, c) in found.iter().take(self.len).enumerate() {
            let job = jobs[self.lane[k]]
                .as_mut()
                .expect("queued lanes are active");
            if keep {
                job.result.crossings.push(*c);
            }
            ids[k] = job.id;
        }
        feed.on_crossings(&ids[..self.len], &found[..self.len]);
        self.len = 0;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Quiet windows open for SBAB2C on Hénon–Heiles from τ = 0.01 (14 steps) to τ = 0.05 (2
    /// steps), and not at τ = 0.1 or 0.5 (there two steps may stretch angles tenfold), nor
    /// for a scheme without a stretch bound; their tests hold the margins they are built on.
    #[test]
    fn quiet_windows_where_the_stretch_allows() {
        let ham = crate::HenonHeiles;
        let rules = |scheme: &str, tau: f64| {
            let map = TangentMap::new(&ham, &crate::Scheme::by_name(scheme).unwrap(), tau);
            let cfg = OrbitConfig::new(tau, 1e4);
            match CorrectedDkd::of(&map) {
                Some(shape) => QuietRules::new(shape, &map, &cfg),
                None => QuietRules::new(AnyShape, &map, &cfg),
            }
        };
        let steps = |tau: f64| rules("sbab2c", tau).map(|r| r.steps);
        assert_eq!(
            [0.005, 0.01, 0.02, 0.05, 0.1, 0.5].map(steps),
            [Some(28), Some(14), Some(7), Some(2), None, None]
        );
        assert!(rules("saba2c", 0.01).is_none());
        let r = rules("sbab2c", 0.01).unwrap();
        let map = TangentMap::new(&ham, &crate::Scheme::by_name("sbab2c").unwrap(), 0.01);
        let g = CorrectedDkd::of(&map)
            .unwrap()
            .stretch_bound(&map, 1.0, 1.0, r.steps)
            .unwrap();
        assert!(g.powi(4) <= QUIET_ANGLE_STRETCH);
        assert_eq!(
            r.band,
            (2.0 * g * g * RESCALE_BELOW, RESCALE_ABOVE / (2.0 * g * g))
        );
        assert_eq!(r.factor, Some(alignment_factor(1e-8 * g.powi(4))));
    }

    /// The vector test answers, lane by lane, as the scalar one the tracker's path applies,
    /// on pairs of vectors at angles from 1e-4 down to 1e-12 (around the 1e-8 threshold and
    /// below the ~3e-7 the root-free pre-filter resolves), parallel and antiparallel.
    #[test]
    fn minors_in_lanes_equal_the_scalar_test() {
        let theta = 1e-8;
        let base = [0.3, -1.1, 0.7, 0.25];
        let tilt = [-0.4, 0.2, 0.9, -0.6];
        let (mut below, mut total) = (0, 0);
        for e in 0..33 {
            let angle = 10f64.powf(-4.0 - e as f64 / 4.0);
            let mut x = Phase::<Lanes<4>, 2, 2> {
                q: [Lanes::splat(0.0); 2],
                p: [Lanes::splat(0.0); 2],
                dq: [[Lanes::splat(0.0); 2]; 2],
                dp: [[Lanes::splat(0.0); 2]; 2],
            };
            for l in 0..4 {
                let sign = if l % 2 == 0 { 1.0 } else { -1.0 };
                let scale = [1.0, 3e-4, 2e5, 0.7][l];
                let w1: [f64; 4] = core::array::from_fn(|i| base[i] * scale);
                let w2: [f64; 4] =
                    core::array::from_fn(|i| sign * (base[i] + angle * (l + 1) as f64 * tilt[i]));
                for i in 0..2 {
                    (x.dq[0][i].0[l], x.dp[0][i].0[l]) = (w1[i], w1[2 + i]);
                    (x.dq[1][i].0[l], x.dp[1][i].0[l]) = (w2[i], w2[2 + i]);
                }
            }
            let n2: [Lanes<4>; 2] =
                core::array::from_fn(|k| dot(&x.dq[k], &x.dq[k]) + dot(&x.dp[k], &x.dp[k]));
            let bits = minors_may_be_below(&x, &n2, 4.0 * theta * theta);
            for l in 0..4 {
                let v = |a: &[Lanes<4>; 2]| -> [f64; 2] { core::array::from_fn(|i| a[i].0[l]) };
                let (w1, w2) = ((v(&x.dq[0]), v(&x.dp[0])), (v(&x.dq[1]), v(&x.dp[1])));
                let scalar = may_be_below((&w1.0, &w1.1), (&w2.0, &w2.1), theta);
                assert_eq!(bits >> l & 1 == 1, scalar, "angle {angle:e}, lane {l}");
                below += scalar as usize;
                total += 1;
            }
        }
        // Both answers occur.
        assert!(below > 20 && below < total - 20, "{below} of {total}");
    }
}
