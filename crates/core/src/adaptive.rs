//! The one-orbit driver for adaptive integrators (DOP853; Taylor to come), in the two protocols:
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

use crate::dop853::{Dense, Dop853, StepFailure};
use crate::hamiltonian::Hamiltonian;
use crate::indicators::{gali, in_band, norm2, sali};
use crate::orbit::{
    sample_steps, steps_to, Class, OrbitConfig, OrbitResult, Requests, Sample, Status,
};
use crate::real::dot;
use crate::section::{bracketed_root, Crossing};
use crate::tangent::Phase;
use crate::taylor::{Scalar, Taylor, TaylorSeries};

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
    pub fn as_str(self) -> &'static str {
        match self {
            Protocol::Restart => "restart",
            Protocol::Free => "free",
        }
    }
}

/// An adaptive integrator of the orbit and its deviation vectors.
pub trait AdaptiveIntegrator<const N: usize, const K: usize> {
    fn t(&self) -> f64;
    /// The current state, rounded to f64.
    fn state(&self) -> Phase<f64, N, K>;
    /// Scales every deviation vector to unit length (in the integrator's own precision) and
    /// returns ln of the factor removed from the first one.
    fn renormalise(&mut self) -> f64;
    /// One accepted step ending at or before `t_end` (exactly at it when within reach); with
    /// `dense`, the step's interpolant becomes available through [`Self::interpolate`].
    fn step(&mut self, t_end: f64, dense: bool) -> Result<(), StepFailure>;
    /// The state at `t` within the last step (only after a step taken with `dense`).
    fn interpolate(&self, t: f64) -> Phase<f64, N, K>;
    /// Start of the last step.
    fn t_prev(&self) -> f64;
    /// Accepted steps so far.
    fn steps(&self) -> u64;
    /// |H − H0|/|H0| in the integrator's own precision, now or (`Some(t)`) at a time within
    /// the last step.
    fn energy_error(&self, at: Option<f64>) -> f64;
}

/// |h − h0| relative to |h0| (absolute when h0 is ~0).
fn relative(dh: f64, h0: f64) -> f64 {
    dh.abs() / if h0.abs() > 1e-300 { h0.abs() } else { 1.0 }
}

/// DOP853 with the dense output of its last step.
pub struct Dop853Orbit<'h, H, const N: usize, const K: usize> {
    pub inner: Dop853<'h, H, N, K>,
    dense: Dense<N, K>,
    t_prev: f64,
    ham: &'h H,
    h0: f64,
}

impl<'h, H: Hamiltonian<N>, const N: usize, const K: usize> Dop853Orbit<'h, H, N, K> {
    pub fn new(ham: &'h H, inner: Dop853<'h, H, N, K>) -> Self {
        let t = inner.t;
        let h0 = ham.energy(&inner.y.q, &inner.y.p);
        Dop853Orbit {
            dense: Dense::empty(),
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
        let ln = unit_vectors(&mut self.inner.y);
        self.inner.state_changed();
        ln
    }
    fn step(&mut self, t_end: f64, dense: bool) -> Result<(), StepFailure> {
        self.t_prev = self.inner.t;
        self.inner
            .step(t_end, if dense { Some(&mut self.dense) } else { None })
    }
    fn interpolate(&self, t: f64) -> Phase<f64, N, K> {
        self.dense.at(t)
    }
    fn t_prev(&self) -> f64 {
        self.t_prev
    }
    fn steps(&self) -> u64 {
        self.inner.accepted
    }
    fn energy_error(&self, at: Option<f64>) -> f64 {
        let y = at.map_or(self.inner.y, |t| self.dense.at(t));
        relative(self.ham.energy(&y.q, &y.p) - self.h0, self.h0)
    }
}

/// Scales the deviation vectors of `y` to unit length (the factors rounded to f64, then applied
/// in `T`'s precision); returns ln of the factor removed from the first.
pub fn unit_vectors<T: Scalar, const N: usize, const K: usize>(y: &mut Phase<T, N, K>) -> f64 {
    let mut ln0 = 0.0;
    for k in 0..K {
        let n2: f64 = y.dq[k]
            .iter()
            .chain(&y.dp[k])
            .map(|x| x.to_f64() * x.to_f64())
            .sum();
        let s = 1.0 / n2.sqrt();
        if k == 0 {
            ln0 = -s.ln();
        }
        let st = T::splat(s);
        for i in 0..N {
            y.dq[k][i] = y.dq[k][i] * st;
            y.dp[k][i] = y.dp[k][i] * st;
        }
    }
    ln0
}

/// The Taylor method as an adaptive integrator; the step's polynomial is the dense output.
pub struct TaylorOrbit<'h, H, T, const N: usize, const K: usize> {
    pub inner: Taylor<'h, H, T, N, K>,
    ham: &'h H,
    h0: T,
}

impl<'h, H: TaylorSeries<N>, T: Scalar, const N: usize, const K: usize>
    TaylorOrbit<'h, H, T, N, K>
{
    pub fn new(ham: &'h H, inner: Taylor<'h, H, T, N, K>) -> Self {
        let h0 = ham.energy(&inner.y.q, &inner.y.p);
        TaylorOrbit { inner, ham, h0 }
    }
}

impl<H: TaylorSeries<N>, T: Scalar, const N: usize, const K: usize> AdaptiveIntegrator<N, K>
    for TaylorOrbit<'_, H, T, N, K>
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
    fn step(&mut self, t_end: f64, _dense: bool) -> Result<(), StepFailure> {
        self.inner.step(t_end)
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

/// A phase point rounded to f64.
pub fn to_f64_phase<T: Scalar, const N: usize, const K: usize>(
    y: &Phase<T, N, K>,
) -> Phase<f64, N, K> {
    Phase {
        q: y.q.map(Scalar::to_f64),
        p: y.p.map(Scalar::to_f64),
        dq: y.dq.map(|v| v.map(Scalar::to_f64)),
        dp: y.dp.map(|v| v.map(Scalar::to_f64)),
    }
}

/// Bookkeeping at the multiples of τ and at step ends.
struct Books<'a, const K: usize> {
    config: &'a OrbitConfig,
    requests: &'a Requests,
    r2_max: f64,
    /// Σ ln of the renormalisation factors of the first vector.
    ln_growth: f64,
    energy_max: f64,
    samples: Vec<u64>,
    next_sample: usize,
}

impl<const K: usize> Books<'_, K> {
    fn mle<const N: usize>(&self, y: &Phase<f64, N, K>, t: f64) -> f64 {
        if t > 0.0 {
            (self.ln_growth + 0.5 * norm2(&y.dq[0], &y.dp[0]).ln()) / t
        } else {
            0.0
        }
    }

    /// At t = nτ: samples and the early stop. Returns true when the orbit stops.
    fn at_tau<const N: usize>(
        &mut self,
        n: u64,
        y: &Phase<f64, N, K>,
        energy_error: impl FnOnce() -> f64,
        out: &mut OrbitResult<N>,
    ) -> bool {
        let t = n as f64 * self.config.tau;
        if self.next_sample < self.samples.len() && self.samples[self.next_sample] == n {
            self.next_sample += 1;
            out.series.push(Sample {
                t,
                sali: sali((&y.dq[0], &y.dp[0]), (&y.dq[1], &y.dp[1])),
                gali: if self.requests.gali {
                    gali(&y.dq, &y.dp)
                } else {
                    Vec::new()
                },
                mle: self.mle(y, t),
                energy_error: energy_error(),
            });
        }
        let th = self.config.thresholds;
        th.early_stop && sali((&y.dq[0], &y.dp[0]), (&y.dq[1], &y.dp[1])) < th.chaotic
    }

    /// At a step end: escape, non-finite, energy. Returns the status that stops the orbit.
    fn at_step_end<const N: usize>(
        &mut self,
        y: &Phase<f64, N, K>,
        energy_error: impl FnOnce() -> f64,
    ) -> Option<Status> {
        let r2 = dot(&y.q, &y.q);
        if r2.is_nan()
            || (0..K).any(|k| !norm2(&y.dq[k], &y.dp[k]).is_finite())
            || !dot(&y.p, &y.p).is_finite()
        {
            return Some(Status::NonFinite);
        }
        // Every step end: an adaptive step costs far more than an energy evaluation.
        let e = energy_error();
        if r2 > self.r2_max {
            // Left the well by gaining energy: the integration blew up, nothing escaped.
            #[allow(clippy::neg_cmp_op_on_partial_ord)]
            return Some(if !(e <= self.config.thresholds.energy_drift) {
                Status::EnergyDrift
            } else {
                Status::Escaped
            });
        }
        self.energy_max = self.energy_max.max(e);
        if e > self.config.thresholds.energy_drift {
            return Some(Status::EnergyDrift);
        }
        None
    }
}

/// Locates an upward crossing of q1 = 0 inside the last step from its dense output (Newton
/// with dq1/dt = p1 inside a bisection bracket).
fn locate_dense<I: AdaptiveIntegrator<N, K>, const N: usize, const K: usize>(
    integ: &I,
) -> Crossing<N> {
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
    assert!(K >= 2, "SALI needs two deviation vectors");
    let y0 = integ.state();
    let tau = config.tau;
    let n_final = steps_to(config.t_final, tau);
    let radius = config.escape_radius.unwrap_or_else(|| ham.escape_radius());
    let mut books: Books<'_, K> = Books {
        config,
        requests,
        r2_max: radius * radius,
        ln_growth: 0.0,
        energy_max: 0.0,
        samples: sample_steps(requests.samples_per_decade, n_final),
        next_sample: 0,
    };
    let mut out = OrbitResult::empty();
    let mut status = Status::Ok;
    let mut n = 0u64;
    // The time the indicators refer to at the end.
    let mut t_end_state = 0.0;
    let mut end_state = y0;
    let want_dense = requests.crossings || protocol == Protocol::Free;

    'outer: while n < n_final {
        let target = match protocol {
            Protocol::Restart => (n + 1) as f64 * tau,
            Protocol::Free => n_final as f64 * tau,
        };
        let q1_before = integ.state().q[0];
        if let Err(e) = integ.step(target, want_dense) {
            status = match e {
                StepFailure::StepTooSmall { .. } => Status::StepLimit,
                StepFailure::NonFinite { .. } => Status::NonFinite,
            };
            break;
        }
        if let Some(s) = books.at_step_end(&integ.state(), || integ.energy_error(None)) {
            status = s;
            break;
        }
        if requests.crossings && q1_before < 0.0 && integ.state().q[0] >= 0.0 {
            out.crossings.push(locate_dense(integ));
        }
        match protocol {
            Protocol::Restart => {
                if integ.t() < target {
                    // Within a long interval the vectors may grow past f64's range (C1 at
                    // τ = 1e4: e^(λτ) ≈ 1e195 per vector, squared past 1e308): renormalise
                    // early, but only when a squared norm leaves the band, so short intervals
                    // (the paper's τ ≤ 0.5) keep the protocol bit for bit; the step control
                    // sees the vectors' scale, so where it triggers the steps change.
                    let y = integ.state();
                    if (0..K).any(|k| !in_band(norm2(&y.dq[k], &y.dp[k]))) {
                        books.ln_growth += integ.renormalise();
                    }
                    continue;
                }
                n += 1;
                let y = integ.state();
                t_end_state = n as f64 * tau;
                end_state = y;
                if books.at_tau(n, &y, || integ.energy_error(None), &mut out) {
                    status = Status::ChaoticEarlyStop;
                    break;
                }
            }
            Protocol::Free => {
                // Every multiple of τ inside this step, through the dense output.
                while n < n_final && (n + 1) as f64 * tau <= integ.t() {
                    n += 1;
                    let t = n as f64 * tau;
                    let at = (t != integ.t()).then_some(t);
                    let y = at.map_or_else(|| integ.state(), |t| integ.interpolate(t));
                    t_end_state = t;
                    end_state = y;
                    if books.at_tau(n, &y, || integ.energy_error(at), &mut out) {
                        status = Status::ChaoticEarlyStop;
                        break 'outer;
                    }
                }
            }
        }
        if n < n_final {
            books.ln_growth += integ.renormalise();
        }
    }

    out.status = status;
    out.steps = integ.steps();
    out.energy_error_max = requests.energy.then_some(books.energy_max);
    if matches!(status, Status::Ok | Status::ChaoticEarlyStop) {
        // The end state was taken before any later renormalisation (none happens once n
        // reaches n_final or the orbit stops), so its scale matches `ln_growth`.
        let y = end_state;
        out.t_reached = t_end_state;
        out.q_end = y.q;
        out.p_end = y.p;
        out.sali = sali((&y.dq[0], &y.dp[0]), (&y.dq[1], &y.dp[1]));
        out.mle = books.mle(&y, t_end_state);
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
        out.class = None;
    }
    out
}
