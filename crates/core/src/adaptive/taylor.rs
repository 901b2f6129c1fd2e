//! The Taylor-series method for the orbit and its deviation vectors.
//!
//! Along a solution, x(t + s) = Σ_k x_[k] s^k with x_[k+1] = f_[k]/(k + 1), f_[k] the k-th
//! coefficient of the right-hand side. For a polynomial ∇V those coefficients follow from
//! Cauchy products of the coefficients already known ([`TaylorSeries`]); the deviation vectors'
//! coefficients come from the same recursion applied to D²V·δq. Order and step follow Jorba &
//! Zou (Exp. Math. 14, 2005): p = ⌊1.5 − 1.16 log10 δ⌋ and h = min(ρ_{p−1}, ρ_p) e^{−2}
//! e^{−0.7/(p−1)} with ρ_j = ‖x_[j]‖^{−1/j}. No step is rejected; the polynomial is the dense
//! output. Generic over the number type, so the same code runs in f64 (`taylor`) and in
//! double-double (`taylor-dd`), one orbit at a time ([`Taylor`]) or several in SIMD lanes
//! ([`TaylorLanes`]).

use crate::adaptive::stepping::{
    phase_lane, set_phase_lane, LaneSteps, Lanewise, Scalar, StepFailure,
};
use crate::arith::real::Real;
use crate::phase::Phase;
use crate::systems::series::{Series, TaylorSeries, P_MAX};

/// The Taylor coefficients of a phase point and its deviation vectors.
#[derive(Clone, Debug)]
pub struct Jet<T: Real, const N: usize, const K: usize> {
    /// Coefficients of q.
    pub q: [Series<T>; N],
    /// Coefficients of p.
    pub p: [Series<T>; N],
    /// Coefficients of each deviation vector's δq.
    pub dq: [[Series<T>; N]; K],
    /// Coefficients of each deviation vector's δp.
    pub dp: [[Series<T>; N]; K],
    /// The highest order filled by the last [`Self::compute`].
    pub order: usize,
    /// 1/(k + 1) in `T`'s precision, computed once (a double-double division is dozens of
    /// operations, and the recursion needs one per order and step).
    inverse: Series<T>,
    /// Series of q that [`TaylorSeries::all_coeffs`] keeps across orders (as many as the
    /// system asks for, allocated at the first [`Jet::compute`]).
    derived: Vec<Series<T>>,
    /// The first order computed in `T::Lead` (see [`lead_order`]); beyond the order, none.
    lead_from: usize,
    /// The coefficients in `T::Lead` from order `lead_from − 1` on (below it, while
    /// `lead_from` is in use, the leading words of `T`'s), which the lead orders' sums read.
    lead: LeadSeries<T::Lead, N, K>,
}

/// The series a [`Jet`] keeps in its leading word's type.
#[derive(Clone, Debug)]
struct LeadSeries<B, const N: usize, const K: usize> {
    q: [Series<B>; N],
    p: [Series<B>; N],
    dq: [[Series<B>; N]; K],
    dp: [[Series<B>; N]; K],
    inverse: Series<B>,
    derived: Vec<Series<B>>,
}

/// How far below δ the rounding of the orders computed in f64 stays (see [`lead_order`]).
const LEAD_MARGIN: f64 = 1e-6;

/// The first order whose Taylor coefficients a double-double jet at tolerance δ computes in
/// f64 (from the leading words of the coefficients below it). Under the Jorba–Zou step the
/// terms of the series fall like ‖x_[k]‖ h^k ≈ e^{−2k} ‖x_0‖ (the rule takes ρ e^{−2} as the
/// step, and a step cut short to land on a multiple of τ only shrinks them), so computing
/// order k in f64 perturbs the step's result by about u e^{−2k} relative, u = 2⁻⁵³. From
/// order ½ ln(u / (m δ)) on, m = [`LEAD_MARGIN`], that is below m δ, a millionth of the
/// truncation error the order and step are chosen for (the low orders fall more slowly than
/// the model, and on random points the step moved by up to 1.5e-5 δ: test
/// `lead_orders_in_f64_keep_the_step_within_a_tiny_share_of_delta`). Order 0, the state
/// itself, is always kept in full. At the paper's δ = 1e-5 every order from 1 on qualifies:
/// the double-double recursion costs several times the f64 one (figures:
/// docs/performance.md) and is no more accurate (R1, τ = 0.01, t = 1e4: max |ΔH/H| 5.3e-14 in
/// double-double, 3.9e-14 in f64: the truncation either way), while the state summed in
/// double-double keeps a million steps' rounding out of it. At δ = 1e-28 (order 33) orders 21
/// and up qualify; max |ΔH/H| of R1 to t = 1e3 (free protocol) is 4.4e-30 with every order in
/// double-double and 4.1e-30 so.
pub fn lead_order(delta: f64) -> usize {
    let k = 0.5 * (0.5 * f64::EPSILON / (LEAD_MARGIN * delta)).ln();
    if k.is_nan() {
        return P_MAX + 1;
    }
    (k.ceil().max(1.0) as usize).min(P_MAX + 1)
}

impl<T: Real, const N: usize, const K: usize> Jet<T, N, K> {
    /// A jet for tolerance `delta` (which decides [`lead_order`] in extended precision).
    pub fn new(delta: f64) -> Self {
        let mut jet = Self::zero();
        if T::EXTENDED {
            jet.lead_from = lead_order(delta);
        }
        jet
    }

    /// A jet computed in `T`'s precision throughout.
    pub fn zero() -> Self {
        let z = [[T::splat(0.0); P_MAX + 1]; N];
        let zl = [[T::Lead::splat(0.0); P_MAX + 1]; N];
        Jet {
            q: z,
            p: z,
            dq: [z; K],
            dp: [z; K],
            order: 0,
            inverse: core::array::from_fn(|k| T::ratio(1.0, (k + 1) as f64)),
            derived: Vec::new(),
            lead_from: usize::MAX,
            lead: LeadSeries {
                q: zl,
                p: zl,
                dq: [zl; K],
                dp: [zl; K],
                inverse: core::array::from_fn(|k| T::Lead::ratio(1.0, (k + 1) as f64)),
                derived: Vec::new(),
            },
        }
    }

    /// The first order held in `T::Lead` for order `p` (p + 1: none).
    #[inline(always)]
    fn lead_split(&self, p: usize) -> usize {
        self.lead_from.min(p + 1)
    }

    /// Fills the coefficients of order 0..=p from the point `y`: those below
    /// [`lead_order`] in `T`, the others in `T::Lead` from the leading words of the lower
    /// ones (and stored in `T` too, exactly, for the step control and the dense output).
    #[inline(always)]
    pub fn compute<H: TaylorSeries<N>>(&mut self, ham: &H, y: &Phase<T, N, K>, p: usize) {
        assert!(p <= P_MAX);
        self.order = p;
        let derived = ham.derived_series();
        if self.derived.len() != derived {
            self.derived = vec![[T::splat(0.0); P_MAX + 1]; derived];
            self.lead.derived = vec![[T::Lead::splat(0.0); P_MAX + 1]; derived];
        }
        for i in 0..N {
            self.q[i][0] = y.q[i];
            self.p[i][0] = y.p[i];
            for k in 0..K {
                self.dq[k][i][0] = y.dq[k][i];
                self.dp[k][i][0] = y.dp[k][i];
            }
        }
        let split = self.lead_split(p);
        for k in 0..split - 1 {
            let inv = self.inverse[k];
            let (g, hvs) = ham.all_coeffs(&self.q, &self.dq, &mut self.derived, k);
            for i in 0..N {
                self.q[i][k + 1] = self.p[i][k] * inv;
                self.p[i][k + 1] = -(g[i] * inv);
            }
            for (v, hv) in hvs.iter().enumerate() {
                for i in 0..N {
                    self.dq[v][i][k + 1] = self.dp[v][i][k] * inv;
                    self.dp[v][i][k + 1] = -(hv[i] * inv);
                }
            }
        }
        if split > p {
            return;
        }
        // The lead orders' recursion is written out again rather than shared with the loop
        // above through a generic helper: such a helper would write each new coefficient once
        // and read it back for `T`, which slows taylor-dd runs (figures: docs/performance.md).
        let k0 = split - 1;
        let lead = &mut self.lead;
        for j in 0..=k0 {
            for i in 0..N {
                lead.q[i][j] = self.q[i][j].lead();
                lead.p[i][j] = self.p[i][j].lead();
                for v in 0..K {
                    lead.dq[v][i][j] = self.dq[v][i][j].lead();
                    lead.dp[v][i][j] = self.dp[v][i][j].lead();
                }
            }
        }
        for j in 0..k0 {
            for (lead, derived) in lead.derived.iter_mut().zip(&self.derived) {
                lead[j] = derived[j].lead();
            }
        }
        for k in k0..p {
            let inv = lead.inverse[k];
            let (g, hvs) = ham.all_coeffs(&lead.q, &lead.dq, &mut lead.derived, k);
            for i in 0..N {
                let (q, pk) = (lead.p[i][k] * inv, -(g[i] * inv));
                lead.q[i][k + 1] = q;
                lead.p[i][k + 1] = pk;
                self.q[i][k + 1] = T::from_lead(q);
                self.p[i][k + 1] = T::from_lead(pk);
            }
            for (v, hv) in hvs.iter().enumerate() {
                for i in 0..N {
                    let (dq, dp) = (lead.dp[v][i][k] * inv, -(hv[i] * inv));
                    lead.dq[v][i][k + 1] = dq;
                    lead.dp[v][i][k + 1] = dp;
                    self.dq[v][i][k + 1] = T::from_lead(dq);
                    self.dp[v][i][k + 1] = T::from_lead(dp);
                }
            }
        }
    }

    /// Σ_k x_[k] s^k by Horner's rule, every component's chain advanced one order at a time:
    /// the chains are independent, and interleaved they overlap in the pipeline (a
    /// double-double multiply-add is a long chain of dependent operations). The orders held
    /// in `T::Lead` are summed in it, the rest in `T`.
    #[inline(always)]
    pub fn eval(&self, s: T) -> Phase<T, N, K> {
        let p = self.order;
        let split = self.lead_split(p);
        let mine = Coefficients::of(&self.q, &self.p, &self.dq, &self.dp);
        let (mut y, below) = if split <= p {
            let c = &self.lead;
            let lead = Coefficients::of(&c.q, &c.p, &c.dq, &c.dp);
            let mut z = lead.phase(|x| x[p]);
            lead.horner(&mut z, s.lead(), split..p, |x, k| x[k]);
            (z.map(T::from_lead), split)
        } else {
            (mine.phase(|x| x[p]), p)
        };
        mine.horner(&mut y, s, 0..below, |x, k| x[k]);
        y
    }
}

/// The series of every component of a phase point (and its deviation vectors), seen together.
struct Coefficients<'a, S, const N: usize, const K: usize> {
    q: &'a [S; N],
    p: &'a [S; N],
    dq: &'a [[S; N]; K],
    dp: &'a [[S; N]; K],
}

impl<'a, S, const N: usize, const K: usize> Coefficients<'a, S, N, K> {
    #[inline(always)]
    fn of(q: &'a [S; N], p: &'a [S; N], dq: &'a [[S; N]; K], dp: &'a [[S; N]; K]) -> Self {
        Coefficients { q, p, dq, dp }
    }

    /// The phase point of `get` applied to every component's series.
    #[inline(always)]
    fn phase<U>(&self, get: impl Fn(&S) -> U) -> Phase<U, N, K> {
        Phase {
            q: core::array::from_fn(|i| get(&self.q[i])),
            p: core::array::from_fn(|i| get(&self.p[i])),
            dq: core::array::from_fn(|v| core::array::from_fn(|i| get(&self.dq[v][i]))),
            dp: core::array::from_fn(|v| core::array::from_fn(|i| get(&self.dp[v][i]))),
        }
    }

    /// Horner's rule over the orders `orders` from the top down: y ← y·s + get(series, k),
    /// every component's chain advanced one order at a time.
    #[inline(always)]
    fn horner<U: Real>(
        &self,
        y: &mut Phase<U, N, K>,
        s: U,
        orders: core::ops::Range<usize>,
        get: impl Fn(&S, usize) -> U,
    ) {
        for k in orders.rev() {
            for i in 0..N {
                y.q[i] = y.q[i].mul_add(s, get(&self.q[i], k));
                y.p[i] = y.p[i].mul_add(s, get(&self.p[i], k));
                for v in 0..K {
                    y.dq[v][i] = y.dq[v][i].mul_add(s, get(&self.dq[v][i], k));
                    y.dp[v][i] = y.dp[v][i].mul_add(s, get(&self.dp[v][i], k));
                }
            }
        }
    }
}

impl<T: Lanewise, const N: usize, const K: usize> Jet<T, N, K> {
    /// ‖x_[j]‖∞ over every component of lane `l`.
    pub fn norm_inf(&self, j: usize, l: usize) -> f64 {
        let at = |x: &Series<T>| x[j].lane(l).to_f64().abs();
        let mut m = 0.0f64;
        for i in 0..N {
            m = m.max(at(&self.q[i])).max(at(&self.p[i]));
            for k in 0..K {
                m = m.max(at(&self.dq[k][i])).max(at(&self.dp[k][i]));
            }
        }
        m
    }

    /// ‖x_[j]‖∞ of lane `l` for j = 0, p − 1 and p: what the step control reads.
    fn step_norms(&self, l: usize) -> [f64; 3] {
        let p = self.order;
        [0, p - 1, p].map(|j| self.norm_inf(j, l))
    }

    /// [`Self::step_norms`] of every lane in one pass (each lane's maxima taken in
    /// [`Self::norm_inf`]'s order).
    #[inline(always)]
    fn step_norms_lanes<const L: usize>(&self) -> [[f64; 3]; L] {
        let p = self.order;
        let mut m = [[0.0f64; L]; 3];
        for (slot, j) in [0, p - 1, p].into_iter().enumerate() {
            let m = &mut m[slot];
            for i in 0..N {
                fold_abs_max(m, self.q[i][j]);
                fold_abs_max(m, self.p[i][j]);
                for k in 0..K {
                    fold_abs_max(m, self.dq[k][i][j]);
                    fold_abs_max(m, self.dp[k][i][j]);
                }
            }
        }
        core::array::from_fn(|l| [m[0][l], m[1][l], m[2][l]])
    }

    /// Lane `l`'s polynomial at `s`, by [`Jet::eval`]'s operations on that lane alone (the
    /// lead orders read from `T`'s series, which hold them exactly).
    pub fn eval_lane(&self, l: usize, s: T::Lane) -> Phase<T::Lane, N, K> {
        let p = self.order;
        let split = self.lead_split(p);
        let mine = Coefficients::of(&self.q, &self.p, &self.dq, &self.dp);
        let (mut y, below) = if split <= p {
            let lead = |x: &Series<T>, k: usize| x[k].lane(l).lead();
            let mut z = mine.phase(|x| lead(x, p));
            mine.horner(&mut z, s.lead(), split..p, lead);
            (z.map(<T::Lane as Real>::from_lead), split)
        } else {
            (mine.phase(|x| x[p].lane(l)), p)
        };
        mine.horner(&mut y, s, 0..below, |x, k| x[k].lane(l));
        y
    }
}

/// m_l ← max(m_l, |x_l|) in every lane.
#[inline(always)]
fn fold_abs_max<T: Lanewise, const L: usize>(m: &mut [f64; L], x: T) {
    for l in 0..L {
        m[l] = m[l].max(x.lane(l).to_f64().abs());
    }
}

/// Whether every component of lane `l` is finite.
fn lane_finite<T: Lanewise, const N: usize, const K: usize>(y: &Phase<T, N, K>, l: usize) -> bool {
    let finite = |v: &[T; N]| v.iter().all(|x| x.lane(l).to_f64().is_finite());
    finite(&y.q) && finite(&y.p) && y.dq.iter().chain(&y.dp).all(finite)
}

/// [`lane_finite`] of every lane at once: the same test of each number, without a branch per
/// number (lane by lane it is a visible share of a taylor-dd run; figures:
/// docs/performance.md).
#[inline(always)]
fn lanes_finite<T: Lanewise, const N: usize, const K: usize, const L: usize>(
    y: &Phase<T, N, K>,
) -> [bool; L] {
    let mut bad = [false; L];
    let mut scan = |v: &[T; N]| {
        for x in v {
            for (l, b) in bad.iter_mut().enumerate() {
                *b |= !x.lane(l).to_f64().is_finite();
            }
        }
    };
    scan(&y.q);
    scan(&y.p);
    for k in 0..K {
        scan(&y.dq[k]);
        scan(&y.dp[k]);
    }
    bad.map(|b| !b)
}

/// Bounds on the norms under which the natural step surely exceeds any reach up to `reach`.
#[derive(Clone, Copy, Debug)]
struct ReachTest {
    reach: f64,
    bound: [f64; 2],
}

impl ReachTest {
    /// Passes nothing (negative bounds) and is recomputed at the next step.
    const NONE: ReachTest = ReachTest {
        reach: f64::NEG_INFINITY,
        bound: [-1.0; 2],
    };
}

/// The Jorba–Zou order and its step factors.
#[derive(Clone, Copy, Debug)]
struct StepRule {
    order: usize,
    /// The factors e^{−2} and e^{−0.7/(p−1)} of the natural step, for this order (applied one
    /// after the other, as the rule is written: their product would round differently).
    factors: (f64, f64),
}

impl StepRule {
    fn new(delta: f64) -> Self {
        let order = order_for(delta);
        StepRule {
            order,
            factors: ((-2.0f64).exp(), (-0.7 / (order as f64 - 1.0)).exp()),
        }
    }

    /// The Jorba–Zou step for a jet with the norms `n` of [`Jet::step_norms`] (absolute error
    /// control unless ‖x_0‖∞ > 1), or infinity when it surely exceeds `reach` (> 0). That is
    /// decided without the roots: ‖x_[j]‖ ≤ ½ (c/r)^j for j = p − 1, p and some r ≥ `reach`
    /// puts ρ_j c at least 2^{1/j} ≥ 1.4 % above `reach`, far beyond the rounding of either
    /// test, so the step the roots would give lands on t_end just the same: the test changes
    /// the cost, never the step. In the restart protocol at small τ nearly every step is cut to
    /// τ and needs no more. The bounds for r are kept in `test` and reused while the reach
    /// stays just below it.
    #[inline(always)]
    fn natural_step(&self, n: [f64; 3], reach: f64, test: &mut ReachTest) -> f64 {
        let p = self.order;
        let scale = n[0].max(1.0);
        // Bounds for a much larger reach would be needlessly strict (more roots), so they are
        // reused only within a hair below it.
        if !(reach > 0.0 && reach <= test.reach && reach >= test.reach * (1.0 - 1e-5)) {
            // Slack above this reach, so that the restart protocol's reaches (τ up to the
            // rounding of the multiples of τ) share one computation.
            let r = reach * (1.0 + 1e-6);
            let x = self.factors.0 * self.factors.1 / r;
            // ½ x^(p−1) and ½ x^p (one power: how they round is far inside the margin).
            let low = 0.5 * x.powi((p - 1) as i32);
            let bound = [low, low * x];
            // An infinite bound would pass norms too large for the argument above.
            *test = if bound.iter().all(|b| b.is_finite()) && r > 0.0 {
                ReachTest { reach: r, bound }
            } else {
                ReachTest::NONE
            };
        }
        // ‖x_[j]‖/scale ≤ bound, multiplied out: no division on the common path (the roots
        // below divide as the rule is written; the test only decides whether they are needed).
        let surely_reaches =
            (0..2).all(|i| n[1 + i].is_finite() && n[1 + i] <= test.bound[i] * scale);
        if surely_reaches {
            return f64::INFINITY;
        }
        self.step_from_roots(n)
    }

    /// The Jorba–Zou step itself: min(ρ_{p−1}, ρ_p) e^{−2} e^{−0.7/(p−1)}.
    fn step_from_roots(&self, n: [f64; 3]) -> f64 {
        let p = self.order;
        let scale = n[0].max(1.0);
        let rho = |i: usize| {
            let norm = n[1 + i] / scale;
            if norm > 0.0 {
                norm.powf(-1.0 / (p - 1 + i) as f64)
            } else {
                f64::INFINITY
            }
        };
        rho(0).min(rho(1)) * self.factors.0 * self.factors.1
    }

    /// The step of lane `l`, at time `t`, toward `t_end` (the jet computed): its size and
    /// whether it lands on `t_end`.
    fn plan<S: Scalar>(
        &self,
        norms: [f64; 3],
        test: &mut ReachTest,
        t: S,
        t_end: f64,
    ) -> Result<(S, bool), StepFailure> {
        let t64 = t.to_f64();
        let remaining = S::splat(t_end) - t;
        // Infinite when the series terminates (a polynomial solution): then any step is exact.
        // The reach in f64, as the test below sees it (`remaining` may differ in extended
        // precision).
        let h_nat = self.natural_step(norms, t_end - t64, test);
        if h_nat.is_nan() {
            return Err(StepFailure::NonFinite { t: t64 });
        }
        let (h, last) = if t64 + h_nat >= t_end {
            (remaining, true)
        } else {
            (S::splat(h_nat), false)
        };
        if h.to_f64() <= t64.abs() * f64::EPSILON * 0.1 && !last {
            return Err(StepFailure::StepTooSmall { t: t64 });
        }
        Ok((h, last))
    }
}

/// Jorba–Zou order for a tolerance: ⌊1.5 − 1.16 log10 δ⌋, at least 2.
pub fn order_for(delta: f64) -> usize {
    ((1.5 - 1.16 * delta.log10()).floor() as usize).clamp(2, P_MAX)
}

/// A Taylor integration in progress, in number type `T`.
#[derive(Clone, Debug)]
pub struct Taylor<'h, H, T: Real, const N: usize, const K: usize> {
    ham: &'h H,
    /// Tolerance δ (which decides the order).
    pub delta: f64,
    rule: StepRule,
    test: ReachTest,
    /// Time, in `T` so that steps landing on t_end are exact in extended precision too.
    t: T,
    t_prev: T,
    /// Current state.
    pub y: Phase<T, N, K>,
    jet: Box<Jet<T, N, K>>,
    /// Steps taken so far.
    pub steps: u64,
}

impl<'h, H: TaylorSeries<N>, T: Scalar + Lanewise<Lane = T>, const N: usize, const K: usize>
    Taylor<'h, H, T, N, K>
{
    /// An integration from `y` at time `t0` with tolerance `delta`.
    pub fn new(ham: &'h H, delta: f64, t0: f64, y: Phase<T, N, K>) -> Self {
        Taylor {
            ham,
            delta,
            rule: StepRule::new(delta),
            test: ReachTest::NONE,
            t: T::splat(t0),
            t_prev: T::splat(t0),
            y,
            jet: Box::new(Jet::new(delta)),
            steps: 0,
        }
    }

    /// Current time, rounded to f64.
    pub fn t(&self) -> f64 {
        self.t.to_f64()
    }

    /// The Jorba–Zou order in use.
    pub fn order(&self) -> usize {
        self.rule.order
    }

    /// Where the last step started, rounded to f64.
    pub fn t_prev(&self) -> f64 {
        self.t_prev.to_f64()
    }

    /// One step ending at or before `t_end`, exactly at it when within reach.
    pub fn step(&mut self, t_end: f64) -> Result<(), StepFailure> {
        if !lane_finite(&self.y, 0) {
            return Err(StepFailure::NonFinite { t: self.t() });
        }
        self.jet.compute(self.ham, &self.y, self.rule.order);
        let norms = self.jet.step_norms(0);
        let (h, last) = self.rule.plan(norms, &mut self.test, self.t, t_end)?;
        self.y = self.jet.eval(h);
        self.t_prev = self.t;
        self.t = if last { T::splat(t_end) } else { self.t + h };
        self.steps += 1;
        Ok(())
    }

    /// The state at time t within the last step, from its Taylor polynomial.
    pub fn interpolate(&self, t: f64) -> Phase<T, N, K> {
        self.jet.eval_lane(0, T::splat(t) - self.t_prev)
    }
}

/// `L` Taylor integrations side by side, one per lane of `T` (`T::LANES == L`): the
/// recursion and the evaluation run on all lanes at once, the step control lane by lane with
/// [`Taylor`]'s own functions, so each lane computes exactly what [`Taylor`] computes for its
/// orbit alone. A lane steps only when asked; the others keep their state.
pub struct TaylorLanes<'h, H, T: Lanewise, const N: usize, const K: usize, const L: usize> {
    ham: &'h H,
    rule: StepRule,
    tests: [ReachTest; L],
    y: Phase<T, N, K>,
    t: [T::Lane; L],
    t_prev: [T::Lane; L],
    steps: [u64; L],
    /// The energy of each lane's current state, computed for all lanes at once after a step
    /// (the driver checks it after every step, and lane by lane, gathering the state first,
    /// it is a visible share of a taylor-dd run; figures: docs/performance.md).
    energy: [T::Lane; L],
    /// With [`Self::screen_energy`]: the energy of each lane's state rounded to f64, formed
    /// after every step instead of `energy` (which is then computed when asked).
    energy_f64: Option<[f64; L]>,
    /// The driver's sums over each lane's state after its last step, rounded to f64.
    sums: crate::adaptive::stepping::StepEnd<crate::arith::real::Lanes<L>, K>,
    jet: Box<Jet<T, N, K>>,
}

impl<'h, H: TaylorSeries<N>, T: Lanewise, const N: usize, const K: usize, const L: usize>
    TaylorLanes<'h, H, T, N, K, L>
{
    /// `L` idle lanes with tolerance `delta`; [`Self::start`] starts each.
    pub fn new(ham: &'h H, delta: f64) -> Self {
        assert_eq!(T::LANES, L, "one lane of T per integration");
        let zero = T::Lane::splat(0.0);
        TaylorLanes {
            ham,
            rule: StepRule::new(delta),
            tests: [ReachTest::NONE; L],
            y: Phase::zero(),
            t: [zero; L],
            t_prev: [zero; L],
            steps: [0; L],
            energy: [zero; L],
            energy_f64: None,
            sums: crate::adaptive::stepping::StepEnd::of(&Phase::<_, N, K>::zero()),
            jet: Box::new(Jet::new(delta)),
        }
    }

    /// Starts lane `l` afresh from `y` at time `t0`.
    pub fn start(&mut self, l: usize, t0: f64, y: &Phase<T::Lane, N, K>) {
        set_phase_lane(&mut self.y, l, y);
        self.t[l] = T::Lane::splat(t0);
        self.t_prev[l] = self.t[l];
        self.steps[l] = 0;
        self.energy[l] = self.ham.energy(&y.q, &y.p);
        // As a new `Taylor` starts (the bounds never change a step, but a lane should not
        // depend on the orbit before it even in cost).
        self.tests[l] = ReachTest::NONE;
    }

    /// The Hamiltonian integrated.
    pub fn hamiltonian(&self) -> &'h H {
        self.ham
    }

    /// The energy of lane `l`'s current state (its orbit, not its deviation vectors, so
    /// renormalising leaves it alone).
    pub fn energy(&self, l: usize) -> T::Lane {
        if self.energy_f64.is_some() {
            let y = self.state(l);
            return self.ham.energy(&y.q, &y.p);
        }
        self.energy[l]
    }

    /// Forms each lane's energy after a step from its state rounded to f64 only
    /// ([`Self::energy_f64`]), and the energy in `T`'s precision when asked: in double-double
    /// the energy at every step is a large share of a taylor-dd step (figures:
    /// docs/performance.md).
    pub fn screen_energy(&mut self) {
        self.energy_f64 = Some([0.0; L]);
    }

    /// The energy of lane `l`'s state rounded to f64, with [`Self::screen_energy`].
    pub fn energy_f64(&self, l: usize) -> Option<f64> {
        self.energy_f64.map(|e| e[l])
    }

    /// The state of lane `l`.
    pub fn state(&self, l: usize) -> Phase<T::Lane, N, K> {
        phase_lane(&self.y, l)
    }

    /// The driver's sums over lane `l`'s state after its last step.
    pub fn step_end(&self, l: usize) -> crate::adaptive::stepping::StepEnd<f64, K> {
        self.sums.lane(l)
    }

    /// The state of lane `l` rounded to f64 (as [`crate::adaptive::stepping::to_f64_phase`] of
    /// [`Self::state`], read straight from the lanes).
    #[inline(always)]
    pub fn state_f64(&self, l: usize) -> Phase<f64, N, K> {
        let at = |x: &T| x.lane(l).to_f64();
        Phase {
            q: self.y.q.each_ref().map(at),
            p: self.y.p.each_ref().map(at),
            dq: self.y.dq.each_ref().map(|v| v.each_ref().map(at)),
            dp: self.y.dp.each_ref().map(|v| v.each_ref().map(at)),
        }
    }

    /// Scales the deviation vectors of every lane of `mask` to unit length in place, all at
    /// once, each lane by [`crate::adaptive::stepping::unit_vectors`]' operations; returns what it
    /// returns for each such lane. (Lane by lane, gathering and scattering, it is a large
    /// share of a run; figures: docs/performance.md.)
    #[inline(always)]
    pub fn unit_vectors(&mut self, mask: &[bool; L]) -> [f64; L]
    where
        T: Real<Lead = crate::arith::real::Lanes<L>>,
    {
        crate::adaptive::stepping::unit_deviations_lanes(&mut self.y.dq, &mut self.y.dp, mask)
    }

    /// [`Self::unit_vectors`] of the lanes of `renormalise`, then [`Self::step`].
    #[inline(always)]
    pub fn renormalise_and_step(
        &mut self,
        renormalise: &[bool; L],
        t_end: &[Option<f64>; L],
    ) -> LaneSteps<L>
    where
        T: Real<Lead = crate::arith::real::Lanes<L>>,
    {
        let factors = self.unit_vectors(renormalise);
        (self.step(t_end), factors)
    }

    /// Lane `l`'s current time, rounded to f64.
    pub fn t(&self, l: usize) -> f64 {
        self.t[l].to_f64()
    }

    /// Where lane `l`'s last step started, rounded to f64.
    pub fn t_prev(&self, l: usize) -> f64 {
        self.t_prev[l].to_f64()
    }

    /// Lane `l`'s steps so far.
    pub fn steps(&self, l: usize) -> u64 {
        self.steps[l]
    }

    /// One step of every lane `l` with `t_end[l]` set, as [`Taylor::step`] takes it; the
    /// outcome of each such lane (`None` for the others). Inlined, so that a caller compiled
    /// for a wider instruction set runs the recursion in it.
    #[inline(always)]
    pub fn step(&mut self, t_end: &[Option<f64>; L]) -> [Option<Result<(), StepFailure>>; L] {
        let mut out = [None; L];
        let mut go = [false; L];
        // In f64 lane by lane is faster (the test is cheap there, and the branch-free form
        // changes how the step around it compiles; figures: docs/performance.md).
        let finite: [bool; L] = if T::EXTENDED {
            lanes_finite::<T, N, K, L>(&self.y)
        } else {
            core::array::from_fn(|l| lane_finite(&self.y, l))
        };
        for l in 0..L {
            if t_end[l].is_some() {
                if finite[l] {
                    go[l] = true;
                } else {
                    out[l] = Some(Err(StepFailure::NonFinite { t: self.t(l) }));
                }
            }
        }
        if !go.contains(&true) {
            return out;
        }
        self.jet.compute(self.ham, &self.y, self.rule.order);
        let norms = self.jet.step_norms_lanes::<L>();
        let mut h = T::splat(0.0);
        let mut last = [false; L];
        for l in 0..L {
            if !go[l] {
                continue;
            }
            let t_end = t_end[l].expect("asked");
            match self
                .rule
                .plan(norms[l], &mut self.tests[l], self.t[l], t_end)
            {
                Ok((hl, landed)) => {
                    h.set_lane(l, hl);
                    last[l] = landed;
                }
                Err(e) => {
                    out[l] = Some(Err(e));
                    go[l] = false;
                }
            }
        }
        let y = self.jet.eval(h);
        // With the screen, the exact energy is formed only when asked (`Self::energy`).
        let energy = self
            .energy_f64
            .is_none()
            .then(|| self.ham.energy(&y.q, &y.p));
        if go.iter().all(|&g| g) {
            self.y = y;
        } else {
            self.y.zip_mut(&y, |d, s| {
                for l in (0..L).filter(|&l| go[l]) {
                    d.set_lane(l, s.lane(l));
                }
            });
        }
        let rounded = |x: T| crate::arith::real::Lanes::<L>::from_fn(|l| x.lane(l).to_f64());
        let y64 = self.y.map(rounded);
        self.sums = crate::adaptive::stepping::StepEnd::of(&y64);
        if let Some(e) = &mut self.energy_f64 {
            *e = self.ham.energy(&y64.q, &y64.p).0;
        }
        for l in (0..L).filter(|&l| go[l]) {
            if let Some(e) = energy {
                self.energy[l] = e.lane(l);
            }
            self.t_prev[l] = self.t[l];
            self.t[l] = if last[l] {
                T::Lane::splat(t_end[l].expect("asked"))
            } else {
                self.t[l] + h.lane(l)
            };
            self.steps[l] += 1;
            out[l] = Some(Ok(()));
        }
        out
    }

    /// The state of lane `l` at time t within its last step, from its Taylor polynomial.
    pub fn interpolate(&self, l: usize, t: f64) -> Phase<T::Lane, N, K> {
        self.jet.eval_lane(l, T::Lane::splat(t) - self.t_prev[l])
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::arith::dd::DoubleDouble;
    use crate::HenonHeiles;

    #[test]
    fn jorba_zou_orders_match_the_papers_table_1() {
        assert_eq!(order_for(1e-5), 7);
        assert_eq!(order_for(1e-16), 20);
        assert_eq!(order_for(1e-15), 18);
        assert_eq!(order_for(1e-28), 33);
    }

    #[test]
    fn lead_orders_follow_the_tolerance() {
        assert_eq!(lead_order(1e-5), 1);
        assert_eq!(lead_order(1e-16), 7);
        assert_eq!(lead_order(1e-28), 21);
        assert_eq!(lead_order(1e-60), P_MAX + 1);
        assert_eq!(lead_order(f64::NAN), P_MAX + 1);
    }

    /// A double-double jet with its high orders in f64 gives the step of one computed in
    /// double-double throughout to within 1e-4 δ (at the Jorba–Zou step and half of it, on
    /// random points and vectors), and the polynomial of one lane reads as the batch's.
    #[test]
    fn lead_orders_in_f64_keep_the_step_within_a_tiny_share_of_delta() {
        let mut seed = 0.41f64;
        let mut next = move || {
            seed = (seed * 3.7 + 0.19).fract();
            2.0 * seed - 1.0
        };
        let dd = |x: f64| DoubleDouble::from_f64(x) * DoubleDouble::from_f64(1.0 + x * 1e-9);
        let flat = |y: &Phase<DoubleDouble, 2, 2>| {
            let mut v = y.q.to_vec();
            v.extend(y.p);
            y.dq.iter().chain(&y.dp).for_each(|w| v.extend(w));
            v
        };
        for delta in [1e-5, 1e-10, 1e-16, 1e-22, 1e-28] {
            let p = order_for(delta);
            assert!(lead_order(delta) <= p, "δ = {delta:e}: some orders in f64");
            let mut worst = 0.0f64;
            for _ in 0..20 {
                // Points of the bounded region at H ≤ 1/8 or so, unit-scale vectors.
                let mut r = || dd(0.45 * next());
                let y = Phase {
                    q: [r(), r()],
                    p: [r(), r()],
                    dq: [[r(), r()], [r(), r()]]
                        .map(|v| v.map(|x| x * DoubleDouble::from_f64(2.0))),
                    dp: [[r(), r()], [r(), r()]]
                        .map(|v| v.map(|x| x * DoubleDouble::from_f64(2.0))),
                };
                let mut full = Jet::<DoubleDouble, 2, 2>::zero();
                let mut mixed = Jet::<DoubleDouble, 2, 2>::new(delta);
                full.compute(&HenonHeiles, &y, p);
                mixed.compute(&HenonHeiles, &y, p);
                let h = StepRule::new(delta).step_from_roots(full.step_norms(0));
                for s in [h, 0.5 * h] {
                    let a = flat(&full.eval(DoubleDouble::from_f64(s)));
                    let b = flat(&mixed.eval(DoubleDouble::from_f64(s)));
                    let c = flat(&mixed.eval_lane(0, DoubleDouble::from_f64(s)));
                    for i in 0..a.len() {
                        assert_eq!(b[i], c[i], "eval_lane = eval, δ = {delta:e}");
                        worst = worst.max((a[i] - b[i]).to_f64().abs());
                    }
                }
            }
            // The model puts it below LEAD_MARGIN δ; the low orders' terms fall more slowly
            // than the model's e^{−2k}, and the sums' own rounding adds: measured 1.4–1.5e-5 δ
            // for δ = 1e-16 to 1e-28, 6e-7 δ at 1e-10 (and 6e-12 δ at 1e-5, where the
            // recursion's rounding, not the margin, sets it).
            assert!(
                worst <= 100.0 * LEAD_MARGIN * delta,
                "δ = {delta:e}: {worst:e} = {:e} δ",
                worst / delta
            );
        }
    }

    /// The root-free test (fresh, or with bounds kept from a larger reach) skips the roots
    /// only where the step from the roots exceeds the reach by more than its 1.4 % margin, so
    /// it never changes a step; and it does skip most of them at reaches like the restart
    /// protocol's.
    #[test]
    fn the_reach_test_skips_only_roots_that_reach() {
        let mut x = 0.37f64;
        let mut next = move || {
            x = (x * 3.7 + 0.19).fract();
            x
        };
        for delta in [1e-5, 1e-16, 1e-28] {
            let rule = StepRule::new(delta);
            let (mut skipped, mut computed) = (0, 0);
            for _ in 0..20_000 {
                let e = |u: f64, lo: f64, hi: f64| 10f64.powf(lo + (hi - lo) * u);
                let n = [
                    e(next(), -2.0, 2.0),
                    e(next(), -12.0, 6.0),
                    e(next(), -12.0, 6.0),
                ];
                let reach = e(next(), -3.0, 0.5);
                let mut kept = ReachTest::NONE;
                rule.natural_step(n, reach * (1.0 + next()), &mut kept);
                let mut fresh = ReachTest::NONE;
                for test in [&mut fresh, &mut kept] {
                    let h = rule.natural_step(n, reach, test);
                    if h == f64::INFINITY {
                        skipped += 1;
                        let roots = rule.step_from_roots(n);
                        assert!(roots >= 1.01 * reach, "δ = {delta}: {n:?} {reach} {roots}");
                    } else {
                        computed += 1;
                        assert_eq!(h, rule.step_from_roots(n));
                    }
                }
            }
            assert!(skipped > 5_000 && computed > 5_000, "{skipped} {computed}");
        }
    }
}
