//! The one-orbit driver for adaptive integrators (DOP853, Taylor), in the two protocols:
//!
//! - `restart` (the seed paper's): integrate exactly to every multiple of τ, compute the
//!   indicators there, renormalise the deviation vectors to unit length and carry the predicted
//!   step over;
//! - `free`: natural steps; renormalise at step ends; indicators at the multiples of τ come from
//!   the step's dense output.
//!
//! Both give the same SALI in exact arithmetic (the variational equations are linear, so the
//! renormalisation only rescales). Deviation vectors are renormalised to unit length here, not
//! by powers of two as in the tangent-map driver, because the error control weighs components
//! by their size.

use crate::adaptive::dop853::{Dense, Dop853};
use crate::adaptive::stepping::{
    to_f64_phase, unit_vectors, Lanewise, Scalar, StepEnd, StepFailure,
};
use crate::adaptive::taylor::Taylor;
use crate::indicators::{gali, in_band, may_be_aligned, norm2, sali, GrowthHistory};
use crate::orbit::{
    sample_steps, steps_to, Class, OrbitConfig, OrbitResult, Requests, Sample, Status,
};
use crate::phase::Phase;
use crate::section::{bracketed_root, Crossing};
use crate::systems::hamiltonian::Hamiltonian;
use crate::systems::series::TaylorSeries;
use core::future::Future;
use core::pin::pin;
use core::task::{Context, Poll, Waker};

/// How an adaptive method meets the renormalisation times.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Protocol {
    /// Stop exactly at every multiple of τ (the paper's protocol).
    #[default]
    Restart,
    /// Natural steps; sample at multiples of τ through dense output.
    Free,
}

impl Protocol {
    /// The protocol's kebab-case name, as serialised.
    pub fn as_str(self) -> &'static str {
        match self {
            Protocol::Restart => "restart",
            Protocol::Free => "free",
        }
    }
}

/// An adaptive integrator of the orbit and its deviation vectors.
pub trait AdaptiveIntegrator<const N: usize, const K: usize> {
    /// The time reached.
    fn t(&self) -> f64;
    /// The current state, rounded to f64.
    fn state(&self) -> Phase<f64, N, K>;
    /// Scales every deviation vector to unit length (in the integrator's own precision) and
    /// returns the length the first one had (the factor removed).
    fn renormalise(&mut self) -> f64;
    /// One accepted step ending at or before `t_end` (exactly at it when within reach). A
    /// scalar integrator steps when called and its future is ready at once; a lane of a SIMD
    /// batch ([`crate::adaptive::lanes`]) waits until the batch steps.
    fn step(&mut self, t_end: f64) -> impl Future<Output = Result<(), StepFailure>>;
    /// [`Self::renormalise`] when `renormalise` is set (its factor comes back), then
    /// [`Self::step`]: one request, so that a SIMD batch renormalises all its lanes at once
    /// (lane by lane it is a large share of a run; figures: docs/performance.md).
    fn renormalise_and_step(
        &mut self,
        renormalise: bool,
        t_end: f64,
    ) -> impl Future<Output = (Option<f64>, Result<(), StepFailure>)> {
        let factor = renormalise.then(|| self.renormalise());
        let step = self.step(t_end);
        async move { (factor, step.await) }
    }
    /// The restart protocol's next request: [`Self::renormalise_and_step`] to the multiple of
    /// τ after `pace.n`. An integrator that can take the driver's quiet steps itself (a SIMD
    /// batch, [`crate::adaptive::lanes`]) may go on through every step that [`quiet_restart_step`]
    /// accepts under `rules`, advancing `pace` as it does, and come back with the first step
    /// that needs the driver: the driver's per-step work is then done for all lanes in one
    /// loop instead of in each lane's future.
    fn restart_step<'a>(
        &'a mut self,
        renormalise: bool,
        pace: &'a mut Pace,
        rules: &'a QuietRules,
    ) -> impl Future<Output = (Option<f64>, Result<(), StepFailure>)> + 'a {
        self.renormalise_and_step(renormalise, (pace.n + 1) as f64 * rules.tau)
    }
    /// Makes the last step's interpolant available to [`Self::interpolate`] and
    /// [`Self::energy_error`]; it is built only when asked for (DOP853's costs 3 evaluations).
    fn prepare_dense(&mut self) {}
    /// The state at `t` within the last step (after [`Self::prepare_dense`]).
    fn interpolate(&self, t: f64) -> Phase<f64, N, K>;
    /// Start of the last step.
    fn t_prev(&self) -> f64;
    /// Accepted steps so far.
    fn steps(&self) -> u64;
    /// |H − H0|/|H0| in the integrator's own precision, now or (`Some(t)`) at a time within
    /// the last step.
    fn energy_error(&self, at: Option<f64>) -> f64;
    /// |H − H0|/|H0| from the state rounded to f64 after the last step, where that is far
    /// cheaper than [`Self::energy_error`] (double-double lanes): a screen that lets the driver
    /// skip the exact error where it could not change a decision and is not reported.
    fn energy_estimate(&self) -> Option<f64> {
        None
    }
    /// [`StepEnd::of`] the state rounded to f64, read right after a step (before any
    /// renormalisation). A SIMD batch forms it for all its lanes at once.
    fn step_end(&self) -> StepEnd<f64, K> {
        StepEnd::of(&self.state())
    }
}

/// |h − h0| relative to |h0| (absolute when h0 is ~0).
pub(crate) fn relative(dh: f64, h0: f64) -> f64 {
    dh.abs() / if h0.abs() > 1e-300 { h0.abs() } else { 1.0 }
}

/// DOP853 with the dense output of its last step.
pub struct Dop853Orbit<'h, H, const N: usize, const K: usize> {
    /// The underlying DOP853 integrator.
    pub inner: Dop853<'h, H, N, K>,
    dense: Dense<N, K>,
    /// Whether `dense` belongs to the last step.
    dense_ready: bool,
    t_prev: f64,
    ham: &'h H,
    h0: f64,
}

impl<'h, H: Hamiltonian<N>, const N: usize, const K: usize> Dop853Orbit<'h, H, N, K> {
    /// Wraps `inner`, taking the energy reference from its current state.
    pub fn new(ham: &'h H, inner: Dop853<'h, H, N, K>) -> Self {
        let t = inner.t;
        let h0 = ham.energy(&inner.y.q, &inner.y.p);
        Dop853Orbit {
            dense: Dense::empty(),
            dense_ready: false,
            inner,
            t_prev: t,
            ham,
            h0,
        }
    }
}

impl<H: Hamiltonian<N>, const N: usize, const K: usize> AdaptiveIntegrator<N, K>
    for Dop853Orbit<'_, H, N, K>
{
    fn t(&self) -> f64 {
        self.inner.t
    }
    fn state(&self) -> Phase<f64, N, K> {
        self.inner.y
    }
    fn renormalise(&mut self) -> f64 {
        let length = unit_vectors(&mut self.inner.y);
        self.inner.state_changed();
        length
    }
    fn step(&mut self, t_end: f64) -> impl Future<Output = Result<(), StepFailure>> {
        self.t_prev = self.inner.t;
        self.dense_ready = false;
        core::future::ready(self.inner.step(t_end, None))
    }
    fn prepare_dense(&mut self) {
        if !self.dense_ready {
            self.inner.dense_output(&mut self.dense);
            self.dense_ready = true;
        }
    }
    fn interpolate(&self, t: f64) -> Phase<f64, N, K> {
        debug_assert!(self.dense_ready, "interpolate before prepare_dense");
        self.dense.at(t)
    }
    fn t_prev(&self) -> f64 {
        self.t_prev
    }
    fn steps(&self) -> u64 {
        self.inner.ctl.accepted
    }
    fn energy_error(&self, at: Option<f64>) -> f64 {
        let y = at.map_or(self.inner.y, |t| self.interpolate(t));
        relative(self.ham.energy(&y.q, &y.p) - self.h0, self.h0)
    }
}

/// The Taylor method as an adaptive integrator; the step's polynomial is the dense output.
pub struct TaylorOrbit<'h, H, T: crate::arith::real::Real, const N: usize, const K: usize> {
    /// The underlying Taylor integrator.
    pub inner: Taylor<'h, H, T, N, K>,
    ham: &'h H,
    h0: T,
}

impl<'h, H: TaylorSeries<N>, T: Scalar + Lanewise<Lane = T>, const N: usize, const K: usize>
    TaylorOrbit<'h, H, T, N, K>
{
    /// Wraps `inner`, taking the energy reference from its current state.
    pub fn new(ham: &'h H, inner: Taylor<'h, H, T, N, K>) -> Self {
        let h0 = ham.energy(&inner.y.q, &inner.y.p);
        TaylorOrbit { inner, ham, h0 }
    }
}

impl<H: TaylorSeries<N>, T: Scalar + Lanewise<Lane = T>, const N: usize, const K: usize>
    AdaptiveIntegrator<N, K> for TaylorOrbit<'_, H, T, N, K>
{
    fn t(&self) -> f64 {
        self.inner.t()
    }
    fn state(&self) -> Phase<f64, N, K> {
        to_f64_phase(&self.inner.y)
    }
    fn renormalise(&mut self) -> f64 {
        unit_vectors(&mut self.inner.y)
    }
    fn step(&mut self, t_end: f64) -> impl Future<Output = Result<(), StepFailure>> {
        core::future::ready(self.inner.step(t_end))
    }
    fn interpolate(&self, t: f64) -> Phase<f64, N, K> {
        to_f64_phase(&self.inner.interpolate(t))
    }
    fn t_prev(&self) -> f64 {
        self.inner.t_prev()
    }
    fn steps(&self) -> u64 {
        self.inner.steps
    }
    fn energy_error(&self, at: Option<f64>) -> f64 {
        let y = at.map_or(self.inner.y, |t| self.inner.interpolate(t));
        relative(
            (self.ham.energy(&y.q, &y.p) - self.h0).to_f64(),
            self.h0.to_f64(),
        )
    }
}

/// The running totals of one orbit that every step may change: a `Copy` value, so that a SIMD
/// batch can take the restart protocol's quiet steps for the driver ([`quiet_restart_step`])
/// with the very arithmetic the driver uses.
#[derive(Clone, Copy, Debug)]
pub(crate) struct Tally {
    /// Σ ln of the renormalisation factors of the first vector, but for those in `growth`.
    ln_growth: f64,
    /// The product of the factors since the last fold into `ln_growth`: a logarithm at every
    /// renormalisation is a visible share of an f64 Taylor run in lanes (figures:
    /// docs/performance.md).
    growth: f64,
    energy_max: f64,
    /// MEGNO and the FLI, when requested.
    history: GrowthHistory,
}

impl Tally {
    const NEW: Tally = Tally {
        ln_growth: 0.0,
        growth: 1.0,
        energy_max: 0.0,
        history: GrowthHistory::NEW,
    };

    /// Takes ln‖w₁‖ at a step end at `t` into the MEGNO and FLI history, from the first vector's
    /// squared norm `n2` there (before any renormalisation).
    #[inline(always)]
    fn note_growth(&mut self, t: f64, n2: f64) {
        let ln_norm = self.ln_growth + self.growth.ln() + 0.5 * n2.ln();
        self.history.note(t, ln_norm);
    }

    /// Takes note of a renormalisation that removed `factor` from the first vector. Factors
    /// are multiplied up and their product's logarithm folded in before it could leave f64's
    /// range (a factor stays near 2^128 at most: a squared norm past 2^256 is renormalised
    /// early). ln Π instead of Σ ln rounds differently, by ~1e-16 of the sum.
    #[inline(always)]
    fn grew(&mut self, factor: f64) {
        self.growth *= factor;
        if !(1e-150..=1e150).contains(&self.growth) {
            self.ln_growth += self.growth.ln();
            self.growth = 1.0;
        }
    }

    /// At a step end: escape, non-finite, energy. Returns the status that stops the orbit.
    #[inline(always)]
    fn at_step_end<const K: usize>(
        &mut self,
        checks: &EndChecks,
        sums: &StepEnd<f64, K>,
        estimate: Option<f64>,
        energy_error: impl FnOnce() -> f64,
    ) -> Option<Status> {
        let r2 = sums.r2;
        if r2.is_nan() || sums.n2.iter().any(|x| !x.is_finite()) || !sums.p2.is_finite() {
            return Some(Status::NonFinite);
        }
        // Every step end: an adaptive step costs far more than an energy evaluation. The
        // estimate (off the exact error by the rounding of the state, ~1e-16) decides only far
        // below the threshold, and only when the maximum is not reported.
        let drift = checks.drift;
        let e = match estimate {
            Some(e) if checks.screen && e < 0.5 * drift => e,
            _ => energy_error(),
        };
        self.energy_max = self.energy_max.max(e);
        if r2 > checks.r2_max {
            // Above the escape energy a drift past the limit inside the well stopped the orbit
            // there, and one beyond it is the orbit's way out (its error is in `energy_max`);
            // below it, an orbit that gained that much energy blew up, nothing escaped.
            #[allow(clippy::neg_cmp_op_on_partial_ord)]
            return Some(if checks.well_r2.is_infinite() && !(e <= drift) {
                Status::EnergyDrift
            } else {
                Status::Escaped
            });
        }
        if e > drift && r2 <= checks.well_r2 {
            return Some(Status::EnergyDrift);
        }
        None
    }
}

/// What [`Tally::at_step_end`] checks against, fixed for an orbit.
#[derive(Clone, Copy, Debug)]
pub(crate) struct EndChecks {
    r2_max: f64,
    /// [`Hamiltonian::way_out_r2`]: beyond it a drift past the limit does not stop the orbit.
    well_r2: f64,
    drift: f64,
    /// Whether an energy estimate may stand in for the exact error: only when the maximum is
    /// not reported, and against a threshold far above the estimate's rounding.
    screen: bool,
}

/// Where a restart-protocol orbit stands after its last step: the multiples of τ reached, q₁
/// there (for the crossing test) and its totals.
#[derive(Clone, Copy, Debug)]
pub struct Pace {
    pub(crate) n: u64,
    q1: f64,
    tally: Tally,
}

/// What makes a restart-protocol step need the driver, for one request: everything
/// [`integrate`] tests after such a step besides its totals.
#[derive(Clone, Copy, Debug)]
pub struct QuietRules {
    pub(crate) tau: f64,
    n_final: u64,
    /// The multiple of τ of the next sample (u64::MAX: none).
    next_sample: u64,
    crossings: bool,
    /// The early stop's threshold, when the early stop is on.
    early_stop: Option<f64>,
    checks: EndChecks,
    /// [`watch_poll`] of τ.
    watch_poll: u64,
    /// [`Requests::growth`].
    growth: bool,
}

/// Takes a restart-protocol step that ended at `t` into `pace` when it needs nothing of the
/// driver but its totals: it reached its multiple of τ, which is neither the last nor a
/// sample, nor a watch poll; no crossing, no possible early stop, no escape, drift or
/// non-finite value. The tests are the driver's own (the cheap ones first; the totals through
/// the driver's [`Tally`]), so a step taken here leaves the totals bit for bit as the driver
/// would. Returns false, `pace` untouched, otherwise.
#[allow(clippy::too_many_arguments)]
#[inline(always)]
pub(crate) fn quiet_restart_step<const K: usize>(
    rules: &QuietRules,
    pace: &mut Pace,
    factor: Option<f64>,
    t: f64,
    steps: u64,
    sums: &StepEnd<f64, K>,
    estimate: Option<f64>,
    energy_error: impl FnOnce() -> f64,
) -> bool {
    let n = pace.n + 1;
    let quiet = n < rules.n_final
        && n != rules.next_sample
        && t >= n as f64 * rules.tau
        && !steps.is_multiple_of(rules.watch_poll)
        && !(rules.crossings && pace.q1 < 0.0 && sums.q1 >= 0.0)
        && !rules
            .early_stop
            .is_some_and(|th| may_be_aligned(sums.n2[0], sums.n2[1], sums.cross, th));
    if !quiet {
        return false;
    }
    let mut tally = pace.tally;
    if let Some(f) = factor {
        tally.grew(f);
    }
    if tally
        .at_step_end(&rules.checks, sums, estimate, energy_error)
        .is_some()
    {
        return false;
    }
    if rules.growth {
        tally.note_growth(t, sums.n2[0]);
    }
    *pace = Pace {
        n,
        q1: sums.q1,
        tally,
    };
    true
}

/// Bookkeeping at the multiples of τ and at step ends.
struct Books<'a, const K: usize> {
    config: &'a OrbitConfig,
    requests: &'a Requests,
    checks: EndChecks,
    samples: Vec<u64>,
    next_sample: usize,
    /// [`watch_poll`] of τ.
    watch_poll: u64,
}

impl<const K: usize> Books<'_, K> {
    fn mle<const N: usize>(&self, tally: &Tally, y: &Phase<f64, N, K>, t: f64) -> f64 {
        if t > 0.0 {
            (tally.ln_growth + tally.growth.ln() + 0.5 * norm2(&y.dq[0], &y.dp[0]).ln()) / t
        } else {
            0.0
        }
    }

    /// The rules of a quiet restart step for the next request.
    fn quiet_rules(&self, n_final: u64) -> QuietRules {
        let th = self.config.thresholds;
        QuietRules {
            tau: self.config.tau,
            n_final,
            next_sample: self
                .samples
                .get(self.next_sample)
                .copied()
                .unwrap_or(u64::MAX),
            crossings: self.requests.crossings,
            early_stop: th.early_stop.then_some(th.chaotic),
            checks: self.checks,
            watch_poll: self.watch_poll,
            growth: self.requests.growth,
        }
    }

    /// At t = nτ: samples and the early stop. Returns true when the orbit stops.
    fn at_tau<const N: usize>(
        &mut self,
        n: u64,
        tally: &Tally,
        sums: &StepEnd<f64, K>,
        state: impl Fn() -> Phase<f64, N, K>,
        energy_error: impl FnOnce() -> f64,
        out: &mut OrbitResult<N>,
    ) -> bool {
        let t = n as f64 * self.config.tau;
        if self.next_sample < self.samples.len() && self.samples[self.next_sample] == n {
            self.next_sample += 1;
            let y = &state();
            out.series.push(Sample {
                t,
                sali: sali((&y.dq[0], &y.dp[0]), (&y.dq[1], &y.dp[1])),
                gali: if self.requests.gali {
                    gali(&y.dq, &y.dp)
                } else {
                    Vec::new()
                },
                mle: self.mle(tally, y, t),
                energy_error: energy_error(),
                growth: self.requests.growth.then(|| tally.history.values()),
            });
        }
        let th = self.config.thresholds;
        // The root-free screen first: SALI's three roots and two divisions at every multiple
        // of τ are a visible share of a restart-protocol run (figures: docs/performance.md).
        th.early_stop && may_be_aligned(sums.n2[0], sums.n2[1], sums.cross, th.chaotic) && {
            let y = state();
            sali((&y.dq[0], &y.dp[0]), (&y.dq[1], &y.dp[1])) < th.chaotic
        }
    }
}

/// Locates an upward crossing of q1 = 0 inside the last step from its dense output (Newton
/// with dq1/dt = p1 inside a bisection bracket).
fn locate_dense<I: AdaptiveIntegrator<N, K>, const N: usize, const K: usize>(
    integ: &mut I,
) -> Crossing<N> {
    integ.prepare_dense();
    let (lo, hi) = (integ.t_prev(), integ.t());
    let (t, y) = bracketed_root(
        lo,
        hi,
        0.5 * (lo + hi),
        4.0 * f64::EPSILON * hi.abs().max(1.0),
        |t| {
            let y = integ.interpolate(t);
            (y.q[0], y.p[0], y)
        },
    );
    Crossing { t, q: y.q, p: y.p }
}

/// SALI at a multiple of τ inside a free step is computed only where [`stop_window`] says it may
/// be below this many times the chaotic threshold: the factor covers the dense output's own
/// error, which the bound (about the exact flow) does not see.
const STOP_MARGIN: f64 = 4.0;

/// A rate R with SALI(t) ≥ SALI(s) e^{−R|t − s|} for t, s in one step whose ends have
/// positions `q0`, `q1`.
///
/// With v' = A v, A = [[0, I], [−D²V, 0]], the unit vectors u, w obey u' = Au − (u·Au)u, so
/// d = u ∓ w has |d'| ≤ 4‖A‖ |d| (|u·Au − w·Aw| ≤ 2‖A‖ |d|), and SALI = min |u ∓ w| shrinks
/// no faster than e^{−4‖A‖t}. ‖A‖₂ = max(1, ‖D²V‖₂) ≤ max(1, ‖D²V‖_F), here taken at both ends
/// and doubled for the path between them. For Hénon–Heiles ‖D²V‖₂ = 1 + 2|q| and
/// 2‖D²V‖_F ≥ 2√2 ≥ 1 + 2|q| while |q| ≤ 0.91, which holds on the bounded part of every energy
/// surface up to H ≈ 0.15 (|q| ≤ 0.68 at H = 1/8), so there the rate is a bound; elsewhere the
/// doubling is a margin, not a proof. [`STOP_MARGIN`] covers the interpolant's own error.
fn sali_decay_rate<H: Hamiltonian<N>, const N: usize>(
    ham: &H,
    q0: &[f64; N],
    q1: &[f64; N],
) -> f64 {
    let frobenius = |q: &[f64; N]| {
        let h = ham.hessian(q);
        h.iter().flatten().map(|x| x * x).sum::<f64>().sqrt()
    };
    4.0 * 2.0 * frobenius(q0).max(frobenius(q1)).max(1.0)
}

/// The times in [t0, t1] where SALI may be below `bound`, given its values at both ends and a
/// decay rate from [`sali_decay_rate`]; `None` when it stays above everywhere.
fn stop_window(
    (t0, s0): (f64, f64),
    (t1, s1): (f64, f64),
    rate: f64,
    bound: f64,
) -> Option<(f64, f64)> {
    // Nowhere below iff ln(s0/b) + ln(s1/b) ≥ R (t1 − t0) with both terms positive: one
    // exponential decides the common case.
    if s0 > bound && s1 > bound && s0 * s1 >= bound * bound * (rate * (t1 - t0)).exp() {
        return None;
    }
    let lo = if s0 > bound {
        t0 + (s0 / bound).ln() / rate
    } else {
        t0
    };
    let hi = if s1 > bound {
        t1 - (s1 / bound).ln() / rate
    } else {
        t1
    };
    (lo <= hi).then_some((lo, hi))
}

/// What a caller learns of one adaptive orbit while it runs, and how it stops it early (the
/// fast-PSS engine claims the cells an orbit crosses and abandons orbits it no longer needs).
pub trait Watch<const N: usize> {
    /// An upward crossing, as soon as it is located (only with `Requests::crossings`).
    fn crossing(&mut self, _crossing: &Crossing<N>) {}
    /// Polled at the multiples of τ where the orbit's steps are a multiple of
    /// [`watch_poll`]`(τ)`: true abandons the orbit.
    fn cancelled(&mut self) -> bool {
        false
    }
}

/// A watch borrowed mutably is a watch, so that a `&mut dyn Watch` can drive the copies of the
/// drivers compiled once in this crate ([`crate::run::run_adaptive_henon_heiles`]).
impl<const N: usize, W: Watch<N> + ?Sized> Watch<N> for &mut W {
    fn crossing(&mut self, crossing: &Crossing<N>) {
        (**self).crossing(crossing)
    }
    fn cancelled(&mut self) -> bool {
        (**self).cancelled()
    }
}

/// Steps between polls of [`Watch::cancelled`]: the tangent-map driver's
/// [`poll_interval`](crate::tangent_map::batch::poll_interval), 64 steps or a time of 4 when that
/// is more. A poll wakes the orbit's driver in lanes and reads shared claims, so polling every few
/// steps costs a visible share of a run (figures: docs/performance.md), and a claim ages
/// little in a time of 4 against orbits of 1e4.
pub fn watch_poll(tau: f64) -> u64 {
    crate::tangent_map::batch::poll_interval(tau)
}

/// Watches nothing.
pub struct Unwatched;

impl<const N: usize> Watch<N> for Unwatched {}

/// An orbit given up at a caller's request ([`Watch::cancelled`]) after this many steps.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Abandoned {
    /// Steps taken before the orbit was given up.
    pub steps: u64,
}

/// Integrates the orbit held by `integ` (deviation vectors already set) to `config.t_final`.
pub fn integrate_adaptive<H, I, const N: usize, const K: usize>(
    ham: &H,
    integ: &mut I,
    protocol: Protocol,
    config: &OrbitConfig,
    requests: &Requests,
) -> OrbitResult<N>
where
    H: Hamiltonian<N>,
    I: AdaptiveIntegrator<N, K>,
{
    now(integrate(
        ham,
        integ,
        protocol,
        config,
        requests,
        false,
        &mut Unwatched,
    ))
    .expect("an unwatched orbit is never abandoned")
}

/// [`integrate_adaptive`] under a [`Watch`].
pub fn integrate_adaptive_watched<H, I, const N: usize, const K: usize>(
    ham: &H,
    integ: &mut I,
    protocol: Protocol,
    config: &OrbitConfig,
    requests: &Requests,
    watch: &mut impl Watch<N>,
) -> Result<OrbitResult<N>, Abandoned>
where
    H: Hamiltonian<N>,
    I: AdaptiveIntegrator<N, K>,
{
    now(integrate(
        ham, integ, protocol, config, requests, false, watch,
    ))
}

/// The output of a future that never waits (a driver over a scalar integrator).
fn now<F: Future>(f: F) -> F::Output {
    match pin!(f).poll(&mut Context::from_waker(Waker::noop())) {
        Poll::Ready(out) => out,
        Poll::Pending => unreachable!("a scalar integrator's step is ready at once"),
    }
}

/// [`integrate_adaptive_watched`]; with `every_tau`, the free protocol computes SALI at every
/// multiple of τ (the reference its stop window is tested against). A future, so that orbits in
/// the lanes of a SIMD batch ([`crate::adaptive::lanes`]) each run this one driver and wait at
/// their steps for the batch; over a scalar integrator it never waits.
pub(crate) async fn integrate<H, I, const N: usize, const K: usize>(
    ham: &H,
    integ: &mut I,
    protocol: Protocol,
    config: &OrbitConfig,
    requests: &Requests,
    every_tau: bool,
    watch: &mut impl Watch<N>,
) -> Result<OrbitResult<N>, Abandoned>
where
    H: Hamiltonian<N>,
    I: AdaptiveIntegrator<N, K>,
{
    assert!(K >= 2, "SALI needs two deviation vectors");
    let y0 = integ.state();
    let tau = config.tau;
    let n_final = steps_to(config.t_final, tau);
    let radius = config.escape_radius.unwrap_or_else(|| ham.escape_radius());
    let drift = config.thresholds.energy_drift;
    let mut books: Books<'_, K> = Books {
        config,
        requests,
        checks: EndChecks {
            r2_max: radius * radius,
            well_r2: ham.way_out_r2(ham.energy(&y0.q, &y0.p), radius),
            drift,
            screen: !requests.energy && drift >= 1e-10,
        },
        samples: sample_steps(requests.samples_per_decade, n_final),
        next_sample: 0,
        watch_poll: watch_poll(tau),
    };
    let mut out = OrbitResult::empty();
    let mut status = Status::Ok;
    // The multiples of τ reached (`pace.n`), q1 at the last step's end (renormalising leaves q
    // alone) and the totals.
    let mut pace = Pace {
        n: 0,
        q1: y0.q[0],
        tally: Tally::NEW,
    };
    // The time the indicators refer to at the end.
    let mut t_end_state = 0.0;
    // `None`: the integrator's current state (the restart protocol ends on a step's end and
    // changes nothing after it, so the state is read once, at the end).
    let mut end_state = Some(y0);
    let mut q_prev = y0.q;
    let mut sali_prev = sali((&y0.dq[0], &y0.dp[0]), (&y0.dq[1], &y0.dp[1]));
    // The renormalisation due at the end of the last step, made with the next step's request.
    let mut renormalise = false;

    'outer: while pace.n < n_final {
        let (target, (factor, stepped)) = match protocol {
            Protocol::Restart => {
                let rules = books.quiet_rules(n_final);
                let n_asked = pace.n;
                let answer = integ.restart_step(renormalise, &mut pace, &rules).await;
                if pace.n > n_asked {
                    // Quiet steps taken for the driver: each ended on its multiple of τ.
                    t_end_state = pace.n as f64 * tau;
                    end_state = None;
                }
                ((pace.n + 1) as f64 * tau, answer)
            }
            Protocol::Free => {
                let target = n_final as f64 * tau;
                (
                    target,
                    integ.renormalise_and_step(renormalise, target).await,
                )
            }
        };
        renormalise = false;
        if let Some(factor) = factor {
            pace.tally.grew(factor);
        }
        if let Err(e) = stepped {
            status = match e {
                StepFailure::StepTooSmall { .. } => Status::StepLimit,
                StepFailure::NonFinite { .. } => Status::NonFinite,
            };
            break;
        }
        let sums = integ.step_end();
        let estimate = integ.energy_estimate();
        if let Some(s) = pace
            .tally
            .at_step_end(&books.checks, &sums, estimate, || integ.energy_error(None))
        {
            status = s;
            break;
        }
        if requests.growth {
            pace.tally.note_growth(integ.t(), sums.n2[0]);
        }
        let q1_before = core::mem::replace(&mut pace.q1, sums.q1);
        if requests.crossings && q1_before < 0.0 && sums.q1 >= 0.0 {
            let c = locate_dense(integ);
            watch.crossing(&c);
            out.crossings.push(c);
        }
        match protocol {
            Protocol::Restart => {
                if integ.t() < target {
                    // Within a long interval the vectors may grow past f64's range (C1 at
                    // τ = 1e4: e^(λτ) ≈ 1e195 per vector, squared past 1e308): renormalise
                    // early, but only when a squared norm leaves the band, so short intervals
                    // (the paper's τ ≤ 0.5) keep the protocol bit for bit; the step control
                    // sees the vectors' scale, so where it triggers the steps change.
                    if sums.n2.iter().any(|&x| !in_band(x)) {
                        pace.tally.grew(integ.renormalise());
                    }
                    continue;
                }
                pace.n += 1;
                t_end_state = pace.n as f64 * tau;
                end_state = None;
                let state = || integ.state();
                let energy = || integ.energy_error(None);
                if books.at_tau(pace.n, &pace.tally, &sums, state, energy, &mut out) {
                    status = Status::ChaoticEarlyStop;
                    break;
                }
            }
            Protocol::Free => {
                // The multiples of τ inside this step, through the dense output; only those
                // that matter: samples, t_final, and those where the early stop could fire.
                let (t0, t1) = (integ.t_prev(), integ.t());
                let y1 = integ.state();
                let sali1 = sali((&y1.dq[0], &y1.dp[0]), (&y1.dq[1], &y1.dp[1]));
                // The last multiple of τ in the step: the largest n ≤ n_final whose n·τ, formed
                // as the loop below forms it, is at most t1.
                let mut n_last = ((t1 / tau) as u64).clamp(pace.n, n_final);
                while n_last < n_final && (n_last + 1) as f64 * tau <= t1 {
                    n_last += 1;
                }
                while n_last > pace.n && n_last as f64 * tau > t1 {
                    n_last -= 1;
                }
                let stop_window = if every_tau {
                    Some((t0, t1))
                } else if config.thresholds.early_stop {
                    let rate = sali_decay_rate(ham, &q_prev, &y1.q);
                    stop_window(
                        (t0, sali_prev),
                        (t1, sali1),
                        rate,
                        STOP_MARGIN * config.thresholds.chaotic,
                    )
                } else {
                    None
                };
                sali_prev = sali1;
                q_prev = y1.q;
                // The window in multiples of τ, one of slack either side for the rounding.
                let window = stop_window.map(|(lo, hi)| {
                    (
                        ((lo / tau).floor() as u64).saturating_sub(1),
                        (hi / tau).ceil() as u64 + 1,
                    )
                });
                while pace.n < n_last {
                    let mut next = if n_last == n_final { n_final } else { u64::MAX };
                    if let Some(&s) = books.samples.get(books.next_sample) {
                        next = next.min(s);
                    }
                    if let Some((first, last)) = window {
                        let first = first.max(pace.n + 1);
                        if first <= last {
                            next = next.min(first);
                        }
                    }
                    pace.n = next.min(n_last);
                    if next > n_last {
                        break;
                    }
                    let t = pace.n as f64 * tau;
                    let at = (t != t1).then_some(t);
                    if at.is_some() {
                        integ.prepare_dense();
                    }
                    let y = at.map_or_else(|| integ.state(), |t| integ.interpolate(t));
                    t_end_state = t;
                    end_state = Some(y);
                    let sums = StepEnd::of(&y);
                    let energy = || integ.energy_error(at);
                    if books.at_tau(pace.n, &pace.tally, &sums, || y, energy, &mut out) {
                        status = Status::ChaoticEarlyStop;
                        break 'outer;
                    }
                }
            }
        }
        if pace.n < n_final {
            renormalise = true;
            if integ.steps().is_multiple_of(books.watch_poll) && watch.cancelled() {
                return Err(Abandoned {
                    steps: integ.steps(),
                });
            }
        }
    }

    out.status = status;
    out.steps = integ.steps();
    out.energy_error_max = requests.energy.then_some(pace.tally.energy_max);
    if matches!(status, Status::Ok | Status::ChaoticEarlyStop) {
        // The end state was taken before any later renormalisation (none happens once n
        // reaches n_final or the orbit stops), so its scale matches `ln_growth`.
        let y = end_state.unwrap_or_else(|| integ.state());
        out.t_reached = t_end_state;
        out.q_end = y.q;
        out.p_end = y.p;
        out.sali = sali((&y.dq[0], &y.dp[0]), (&y.dq[1], &y.dp[1]));
        out.mle = books.mle(&pace.tally, &y, t_end_state);
        out.growth = requests.growth.then(|| pace.tally.history.values());
        out.gali = if requests.gali {
            gali(&y.dq, &y.dp)
        } else {
            Vec::new()
        };
        out.class = Some(if status == Status::ChaoticEarlyStop {
            Class::Chaotic
        } else {
            config.thresholds.classify(out.sali)
        });
    } else {
        out.t_reached = integ.t();
        let y = integ.state();
        out.q_end = y.q;
        out.p_end = y.p;
        out.sali = f64::NAN;
        out.mle = f64::NAN;
        out.growth = None;
        out.class = None;
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::adaptive::dop853::Dop853Config;
    use crate::adaptive::stepping::{unit_deviations, unit_deviations_lanes};
    use crate::arith::real::Lanes;
    use crate::orbit::initial_vectors;
    use crate::section::on_section;
    use crate::systems::hamiltonian::HenonHeiles;
    use crate::Deviation;

    /// The lanes' renormalisation is the scalar one in every masked lane, bit for bit (f64
    /// and double-double), and leaves the other lanes alone.
    #[test]
    fn lanes_renormalise_as_the_scalar_driver_does() {
        use crate::arith::dd::DoubleDouble;
        let mut seed = 0.37f64;
        let mut next = move || {
            seed = (seed * 3.7 + 0.19).fract();
            2.0 * seed - 1.0
        };
        let masks = [
            [true; 4],
            [true, false, true, false],
            [false, false, false, true],
        ];
        for (round, mask) in (0..300).zip(masks.iter().cycle()) {
            // Vectors of every scale, with components of like size (where a fused sum
            // would round differently).
            let scale = 10f64.powi(round % 9 * 4 - 16);
            let mut next = || scale * next();
            let words: [[[[f64; 2]; 2]; 2]; 4] = core::array::from_fn(|_| {
                core::array::from_fn(|_| [[next(), next()], [next(), next()]])
            });
            let lo = |x: f64| x * 1e-17;
            // f64 lanes.
            let mut dq: [[Lanes<4>; 2]; 2] = core::array::from_fn(|k| {
                core::array::from_fn(|i| Lanes::from_fn(|l| words[l][0][k][i]))
            });
            let mut dp: [[Lanes<4>; 2]; 2] = core::array::from_fn(|k| {
                core::array::from_fn(|i| Lanes::from_fn(|l| words[l][1][k][i]))
            });
            let factors = unit_deviations_lanes(&mut dq, &mut dp, mask);
            // Double-double lanes.
            let dd = |x: f64| DoubleDouble { hi: x, lo: lo(x) };
            let mut ddq: [[DoubleDouble<Lanes<4>>; 2]; 2] = core::array::from_fn(|k| {
                core::array::from_fn(|i| DoubleDouble {
                    hi: Lanes::from_fn(|l| words[l][0][k][i]),
                    lo: Lanes::from_fn(|l| lo(words[l][0][k][i])),
                })
            });
            let mut ddp: [[DoubleDouble<Lanes<4>>; 2]; 2] = core::array::from_fn(|k| {
                core::array::from_fn(|i| DoubleDouble {
                    hi: Lanes::from_fn(|l| words[l][1][k][i]),
                    lo: Lanes::from_fn(|l| lo(words[l][1][k][i])),
                })
            });
            let dd_factors = unit_deviations_lanes(&mut ddq, &mut ddp, mask);
            for l in 0..4 {
                let (mut q, mut p) = (words[l][0], words[l][1]);
                let (mut qd, mut pd) = (q.map(|v| v.map(dd)), p.map(|v| v.map(dd)));
                let f = unit_deviations(&mut q, &mut p);
                let fd = unit_deviations(&mut qd, &mut pd);
                if !mask[l] {
                    (q, p) = (words[l][0], words[l][1]);
                    (qd, pd) = (q.map(|v| v.map(dd)), p.map(|v| v.map(dd)));
                }
                for k in 0..2 {
                    for i in 0..2 {
                        assert_eq!(dq[k][i].0[l].to_bits(), q[k][i].to_bits(), "{mask:?}");
                        assert_eq!(dp[k][i].0[l].to_bits(), p[k][i].to_bits(), "{mask:?}");
                        assert_eq!(ddq[k][i].lane(l), qd[k][i], "{mask:?}");
                        assert_eq!(ddp[k][i].lane(l), pd[k][i], "{mask:?}");
                    }
                }
                if mask[l] {
                    assert_eq!(factors[l].to_bits(), f.to_bits());
                    assert_eq!(dd_factors[l].to_bits(), fd.to_bits());
                }
            }
        }
    }

    fn start(q2: f64, p2: f64) -> Phase<f64, 2, 2> {
        let (q, p) = on_section(&HenonHeiles, 0.125, &[q2], &[p2]).unwrap();
        let (dq, dp) = initial_vectors::<2, 2>(Deviation::Axes);
        Phase { q, p, dq, dp }
    }

    fn dop853(y: Phase<f64, 2, 2>, delta: f64) -> Dop853Orbit<'static, HenonHeiles, 2, 2> {
        Dop853Orbit::new(
            &HenonHeiles,
            Dop853::new(&HenonHeiles, Dop853Config::with_delta(delta), 0.0, y),
        )
    }

    fn taylor(y: Phase<f64, 2, 2>, delta: f64) -> TaylorOrbit<'static, HenonHeiles, f64, 2, 2> {
        TaylorOrbit::new(&HenonHeiles, Taylor::new(&HenonHeiles, delta, 0.0, y))
    }

    /// The decay bound holds inside every step of a chaotic orbit, with the rate taken from
    /// the step's ends alone (without the factor 2 of [`sali_decay_rate`] for the path): a
    /// rate too small by that factor would already fail here.
    #[test]
    fn sali_never_falls_faster_than_the_decay_rate() {
        let mut integ = dop853(start(-0.25, 0.0), 1e-10);
        let mut checked = 0;
        let mut tightest = f64::INFINITY;
        // Down to SALI ~ 1e-11, where rounding (not the flow) starts to move it.
        let s = |y: &Phase<f64, 2, 2>| sali((&y.dq[0], &y.dp[0]), (&y.dq[1], &y.dp[1]));
        while s(&integ.state()) > 1e-11 {
            let y0 = integ.state();
            now(integ.step(600.0)).unwrap();
            integ.prepare_dense();
            let y1 = integ.state();
            let (t0, t1) = (integ.t_prev(), integ.t());
            let (s0, s1) = (s(&y0), s(&y1));
            let rate = sali_decay_rate(&HenonHeiles, &y0.q, &y1.q) / 2.0;
            for i in 1..16 {
                let t = t0 + (t1 - t0) * i as f64 / 16.0;
                let st = s(&integ.interpolate(t));
                let bound = (s0 * (-rate * (t - t0)).exp()).max(s1 * (-rate * (t1 - t)).exp());
                assert!(st >= bound, "t = {t}: SALI {st} below the bound {bound}");
                tightest = tightest.min(st / bound);
                checked += 1;
            }
            integ.renormalise();
        }
        assert!(checked > 1000, "{checked} points");
        // SALI fell from ~1 to below 1e-8 in those steps, so the points span the range.
        assert!(
            tightest < 3.0,
            "the bound was never within a factor 3: {tightest}"
        );
    }

    /// The factors' product is folded into the logarithm before it leaves f64's range, so
    /// the growth is Σ ln of the factors however large or small they are.
    #[test]
    fn growth_is_the_sum_of_the_logarithms_of_the_factors() {
        let mut tally = Tally::NEW;
        let mut sum = 0.0f64;
        for i in 0..2000 {
            // Runs of large factors, then of small ones, then near-unit ones.
            let factor = match i / 500 {
                0 => 1e40 * (1.0 + i as f64 * 1e-3),
                1 => 1e-37 / (1.0 + i as f64 * 1e-3),
                _ => 1.0 + ((i * 7919) % 13) as f64 * 1e-4,
            };
            tally.grew(factor);
            sum += factor.ln();
            assert!(tally.growth.is_finite() && tally.growth > 0.0, "{i}");
        }
        let total = tally.ln_growth + tally.growth.ln();
        assert!(
            (total - sum).abs() <= 1e-12 * sum.abs().max(1.0),
            "{total} vs {sum}"
        );
    }

    #[test]
    fn stop_window_brackets_where_the_bound_dips_below() {
        // From 1 at t = 0 and 1e-9 at t = 1 with rate 30: below 1e-8 from ln(1e8)/30 = 0.614.
        let (lo, hi) = stop_window((0.0, 1.0), (1.0, 1e-9), 30.0, 1e-8).unwrap();
        assert!((lo - 1e8f64.ln() / 30.0).abs() < 1e-12 && hi == 1.0);
        // Both ends far above: nothing to check.
        assert_eq!(stop_window((0.0, 1e-3), (0.5, 1e-3), 30.0, 1e-8), None);
        // Both ends close enough that the middle may dip below.
        let (lo, hi) = stop_window((0.0, 2e-8), (1.0, 2e-8), 30.0, 1e-8).unwrap();
        let d = 2f64.ln() / 30.0;
        assert!((lo - d).abs() < 1e-12 && (hi - (1.0 - d)).abs() < 1e-12);
    }

    fn free_run<I: AdaptiveIntegrator<2, 2>>(
        mut integ: I,
        config: &OrbitConfig,
        requests: &Requests,
        every_tau: bool,
    ) -> OrbitResult<2> {
        let (ham, free) = (&HenonHeiles, Protocol::Free);
        now(integrate(
            ham,
            &mut integ,
            free,
            config,
            requests,
            every_tau,
            &mut Unwatched,
        ))
        .unwrap()
    }

    /// Free-protocol runs on section points across the chaotic sea and the islands stop at the
    /// same multiple of τ, with the same bits, whether SALI is computed at every multiple or
    /// only inside the stop windows.
    #[test]
    fn stop_windows_do_not_change_free_runs() {
        let mut config = OrbitConfig::new(0.01, 1500.0);
        config.thresholds.early_stop = true;
        let requests = Requests {
            crossings: true,
            samples_per_decade: 3,
            ..Requests::default()
        };
        let mut early = 0;
        for i in 0..12 {
            let q2 = -0.4 + 0.09 * i as f64;
            let y = start(q2, 0.05);
            for method in 0..2 {
                let run = |every| {
                    if method == 0 {
                        free_run(dop853(y, 1e-5), &config, &requests, every)
                    } else {
                        free_run(taylor(y, 1e-5), &config, &requests, every)
                    }
                };
                let (a, b) = (run(false), run(true));
                assert_eq!(a.status, b.status, "q2 = {q2}");
                assert_eq!(a.t_reached.to_bits(), b.t_reached.to_bits(), "q2 = {q2}");
                assert_eq!(a.sali.to_bits(), b.sali.to_bits(), "q2 = {q2}");
                assert_eq!(a.series, b.series);
                assert_eq!(a.crossings.len(), b.crossings.len());
                early += (a.status == Status::ChaoticEarlyStop) as usize;
            }
        }
        assert!(early >= 6, "only {early} runs stopped early");
    }
}
