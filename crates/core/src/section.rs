//! The surface of section q1 = 0, p1 > 0: initial conditions on it and crossing location.

use crate::arith::real::Lanes;
use crate::phase::Phase;
use crate::systems::hamiltonian::Hamiltonian;
use crate::tangent_map::map::{StepPart, Stepping, TangentMap};

/// A point where the orbit crosses q1 = 0 upwards (p1 > 0).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Crossing<const N: usize> {
    /// Time of the crossing.
    pub t: f64,
    /// Coordinates at the crossing (q1 = 0).
    pub q: [f64; N],
    /// Momenta at the crossing (p1 > 0).
    pub p: [f64; N],
}

/// Why a point of the section cannot start an orbit.
#[derive(Clone, Debug, PartialEq)]
pub enum SectionError {
    /// 2(E − V) − |p_rest|² ≤ 0: the point is outside the energy surface's section.
    NotOnSection {
        /// The value of 2(E − V) − |p_rest|².
        radicand: f64,
    },
    /// A coordinate or the energy is NaN or infinite.
    NonFinite,
}

impl std::fmt::Display for SectionError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            SectionError::NotOnSection { radicand } => write!(
                f,
                "the point is not on the section at this energy (p1² = {radicand:.3e}, must be > 0)"
            ),
            SectionError::NonFinite => write!(f, "coordinates and energy must be finite"),
        }
    }
}

/// p1² = 2(E − V(q)) − Σ_{i≥2} p_i² for q = (0, q_rest), p = (·, p_rest).
pub fn p1_squared<H: Hamiltonian<N>, const N: usize>(
    ham: &H,
    energy: f64,
    q: &[f64; N],
    p: &[f64; N],
) -> f64 {
    let rest: f64 = p[1..].iter().map(|x| x * x).sum();
    2.0 * (energy - ham.potential(q)) - rest
}

/// The phase-space point on the section q1 = 0 with the given other coordinates and energy,
/// p1 > 0 from energy conservation.
pub fn on_section<H: Hamiltonian<N>, const N: usize>(
    ham: &H,
    energy: f64,
    q_rest: &[f64],
    p_rest: &[f64],
) -> Result<([f64; N], [f64; N]), SectionError> {
    let mut q = [0.0; N];
    let mut p = [0.0; N];
    q[1..].copy_from_slice(q_rest);
    p[1..].copy_from_slice(p_rest);
    if !energy.is_finite() || q.iter().chain(&p).any(|x| !x.is_finite()) {
        return Err(SectionError::NonFinite);
    }
    let r = p1_squared(ham, energy, &q, &p);
    if r.is_nan() || r <= 0.0 {
        return Err(SectionError::NotOnSection { radicand: r });
    }
    p[0] = r.sqrt();
    Ok((q, p))
}

/// A lattice of rectangular cells on the (q_2, p_2) plane of a 2-dof section: cell (i, j)
/// holds the points with ⌊(q_2 − q2_origin) / q2_width⌋ = i and ⌊(p_2 − p2_origin) /
/// p2_width⌋ = j (a grid's cells, and the indices beyond it).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct CellLattice {
    /// q_2 where cell column 0 starts.
    pub q2_origin: f64,
    /// p_2 where cell row 0 starts.
    pub p2_origin: f64,
    /// Width of a cell along q_2.
    pub q2_width: f64,
    /// Width of a cell along p_2.
    pub p2_width: f64,
}

impl CellLattice {
    /// Whether every point within `r` of (q2, p2) in each coordinate falls in the cell of
    /// (q2, p2). The index along each axis is a monotone function of the coordinate, rounding
    /// included, so equal indices at both ends of the interval hold for everything between.
    #[inline]
    pub fn same_cell_within(&self, q2: f64, p2: f64, r: f64) -> bool {
        // The floors at both corners over one array, so that the four divisions go as one
        // vector instruction (the operations, and so the bits, are the same).
        let x = [q2 - r, q2 + r, p2 - r, p2 + r];
        let lo = [
            self.q2_origin,
            self.q2_origin,
            self.p2_origin,
            self.p2_origin,
        ];
        let w = [self.q2_width, self.q2_width, self.p2_width, self.p2_width];
        let f: [f64; 4] = core::array::from_fn(|k| ((x[k] - lo[k]) / w[k]).floor());
        f[0] == f[1] && f[2] == f[3]
    }
}

/// A step of an orbit that crosses q1 = 0 upwards: it starts at (`q`, `p`) at time `t` with
/// q1 < 0 and ends one step τ later with q1 = `q1_end` ≥ 0.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct CrossingStep<const N: usize> {
    /// Coordinates at the step's start (q1 < 0).
    pub q: [f64; N],
    /// Momenta at the step's start.
    pub p: [f64; N],
    /// Time of the step's start.
    pub t: f64,
    /// q1 at the step's end (≥ 0).
    pub q1_end: f64,
}

impl<const N: usize> CrossingStep<N> {
    /// A placeholder for fixed-size queues.
    pub const ZERO: Self = CrossingStep {
        q: [0.0; N],
        p: [0.0; N],
        t: 0.0,
        q1_end: 0.0,
    };
}

/// The steps of the orbit from (`q`, `p`) (no deviation vectors) that cross q1 = 0 upwards
/// within its first `steps` steps of `map`, in time order: the input of the crossing searches
/// for tests and benchmarks that exercise them apart from a driver.
pub fn upward_crossing_steps<H: Hamiltonian<N>, const N: usize>(
    map: &TangentMap<'_, H>,
    q: [f64; N],
    p: [f64; N],
    steps: u64,
) -> Vec<CrossingStep<N>> {
    let x = Phase::<f64, N, 0> {
        q,
        p,
        dq: [],
        dp: [],
    };
    let mut s = Stepping::new(map, x);
    let mut found = Vec::new();
    for n in 0..steps {
        let (q0, p0) = (s.x.q, s.x.p);
        s.advance();
        if q0[0] < 0.0 && s.x.q[0] >= 0.0 {
            found.push(CrossingStep {
                q: q0,
                p: p0,
                t: n as f64 * map.tau(),
                q1_end: s.x.q[0],
            });
        }
    }
    found
}

/// Locates the upward crossing of q1 = 0 inside `step`.
///
/// Solves q1(Φ_h(x)) = 0 for h ∈ (0, τ], Φ_h being one step of the same splitting scheme with
/// step h, by Newton's method (dq1/dh from a polynomial model of q1(Φ_h), then secants) kept
/// inside a bisection bracket, so a crossing nearly tangent to the section (p1 → 0) never
/// divides by ~0. The partial steps run on a copy: the symplectic trajectory itself is
/// untouched. The error is the scheme's local error over h, O(h^(p+1)).
pub fn locate_upward<H: Hamiltonian<N>, const N: usize>(
    map: &TangentMap<'_, H>,
    step: &CrossingStep<N>,
) -> Crossing<N> {
    let [c] = locate_upward_lanes::<H, N, 1>(map, core::slice::from_ref(step));
    c
}

/// [`locate_upward`] for up to `L` crossings at once, the searches of all of them advanced
/// together in SIMD lanes: each lane performs the operations of a search alone, so a result
/// does not depend on its companions (and [`locate_upward`] is this with one lane).
#[inline]
pub fn locate_upward_lanes<H: Hamiltonian<N>, const N: usize, const L: usize>(
    map: &TangentMap<'_, H>,
    steps: &[CrossingStep<N>],
) -> [Crossing<N>; L] {
    locate_lanes(map, steps, None::<&fn(&Crossing<N>, f64) -> bool>)
}

/// [`locate_upward_lanes`] for a caller that needs only to know which region of the section
/// each crossing falls in (a cell of a grid), not the point itself. After each partial step
/// of a lane's search, `settles(c, r)` is asked whether every point within `r` of `c` in
/// each of the section's coordinates (q_i, p_i for i ≥ 2) is treated alike; when it says yes,
/// the lane's search ends there and `c` is its result: a point of the orbit near the crossing
/// (at τ = 0.5 within a few 1e-5 in time), with q1 ≈ 0 but not 0. The other lanes return
/// what [`locate_upward_lanes`] returns, bit for bit. So whenever `settles` answers by
/// the region of `c` alone, every crossing lands in the region of the exact one: `r` bounds
/// how far the orbit moves between `c` and the root.
///
/// Why this pays: a search takes three or four partial steps to reach the root to the last
/// bit, while the first one, at the guess of the crossing model, is 1e-6–1e-5 away in time
/// at τ = 0.5, well inside a cell of a 400×400 grid for all but a few per cent of the
/// crossings.
#[inline]
pub fn locate_upward_lanes_settling<H: Hamiltonian<N>, const N: usize, const L: usize>(
    map: &TangentMap<'_, H>,
    steps: &[CrossingStep<N>],
    settles: &impl Fn(&Crossing<N>, f64) -> bool,
) -> [Crossing<N>; L] {
    locate_lanes(map, steps, Some(settles))
}

// Inline: copied into the caller's codegen unit, where `settles` inlines into the search.
#[inline]
fn locate_lanes<H: Hamiltonian<N>, S, const N: usize, const L: usize>(
    map: &TangentMap<'_, H>,
    steps: &[CrossingStep<N>],
    settles: Option<&S>,
) -> [Crossing<N>; L]
where
    S: Fn(&Crossing<N>, f64) -> bool,
{
    assert!(!steps.is_empty() && steps.len() <= L);
    let count = steps.len();
    let pick = |l: usize| &steps[l.min(count - 1)];
    let tau = map.tau();
    let q0: [Lanes<L>; N] = core::array::from_fn(|i| Lanes::from_fn(|l| pick(l).q[i]));
    let p0: [Lanes<L>; N] = core::array::from_fn(|i| Lanes::from_fn(|l| pick(l).p[i]));
    let model = CrossingModel::new(
        map.hamiltonian(),
        tau,
        &q0,
        &p0,
        core::array::from_fn(|l| pick(l).q1_end),
    );
    let mut search = RootSearch::new(0.0, tau, model.h0, 4.0 * f64::EPSILON * tau);
    // The state at each lane's last evaluated point: its root once the search is over.
    let (mut q_root, mut p_root) = (q0, p0);
    let mut settled: [Option<Crossing<N>>; L] = [None; L];
    loop {
        // Lanes whose search is over re-evaluate their root; the result is ignored.
        let h = search.s.0;
        let (mut q, mut p) = (q0, p0);
        step_lanes(map, StepPart::MovingQ, &mut q, &mut p, &h);
        let dg = model.slope(Lanes(h));
        if let Some(settles) = settles {
            let now = settle_lanes(map, &q, &p, &h, &dg, &search.live, |l, c, r| {
                settles(
                    &Crossing {
                        t: pick(l).t + c.t,
                        ..*c
                    },
                    r,
                )
            });
            for l in 0..L {
                if now[l].is_some() {
                    settled[l] = now[l];
                    search.live[l] = false;
                }
            }
            if !search.live.iter().any(|&l| l) {
                break;
            }
        }
        for l in 0..L {
            if search.live[l] {
                for i in 0..N {
                    q_root[i].0[l] = q[i].0[l];
                    p_root[i].0[l] = p[i].0[l];
                }
            }
        }
        if !search.evaluated(q[0], dg) {
            break;
        }
    }
    let h = search.s.0;
    if settled.iter().any(Option::is_none) {
        step_lanes(map, StepPart::Rest, &mut q_root, &mut p_root, &h);
    }
    core::array::from_fn(|l| match settled[l] {
        Some(c) => Crossing {
            t: pick(l).t + c.t,
            ..c
        },
        None => Crossing {
            t: pick(l).t + h[l],
            q: core::array::from_fn(|i| q_root[i].0[l]),
            p: core::array::from_fn(|i| p_root[i].0[l]),
        },
    })
}

/// Completes the partial steps of size `h` that end at (`q`, `p`) (positions final, momenta
/// not yet) and returns, for each `live` lane whose point `accept` takes, that point (time
/// within the step): its crossing.
///
/// The bound handed to `accept`: with g(s) = q1 after a partial step of size s, g(h) = g0 and
/// g'(h) ≈ p1, Newton's correction is δ = −g0/p1. While |g''| ≈ |∂V/∂q1| stays below p1/(4|δ|)
/// and g' is within a quarter of p1, the root lies within 2|δ| of h, and in that time no
/// other coordinate moves by more than 2|δ| times its rate (|p_i| for q_i, |∂V/∂q_i| for
/// p_i). The bound doubles that again, plus 1e-12 for the rounding of the points themselves.
/// A splitting step's dq1/ds is p1 (and its other rates the field's) only up to the scheme's
/// error, a series in powers of τ·ω with ω² the size of D²V over the step: a lane settles
/// only where τ²·(‖D²V‖∞ + τ‖D³V(p, ·, ·)‖∞) ≤ 4 (the second term: how much D²V changes
/// while the orbit moves by τ·p) and the crossing model's slope `dg`, which fits the step's
/// own end point, agrees with p1 to 5 %. (The first condition keeps out orbits far out on
/// their way to escape, with q ~ 1e8 or beyond: their partial steps leave the field's path,
/// and may cross the section more than once.)
fn settle_lanes<H: Hamiltonian<N>, const N: usize, const L: usize>(
    map: &TangentMap<'_, H>,
    q: &[Lanes<L>; N],
    p: &[Lanes<L>; N],
    h: &[f64; L],
    dg: &Lanes<L>,
    live: &[bool; L],
    accept: impl Fn(usize, &Crossing<N>, f64) -> bool,
) -> [Option<Crossing<N>>; L] {
    let (mut q, mut p) = (*q, *p);
    step_lanes(map, StepPart::Rest, &mut q, &mut p, h);
    let ham = map.hamiltonian();
    let grad = ham.grad(&q);
    let hessian = ham.hessian(&q);
    let sweep: [[Lanes<L>; N]; N] = core::array::from_fn(|j| {
        let e = core::array::from_fn(|i| Lanes([if i == j { 1.0 } else { 0.0 }; L]));
        ham.third_vec(&q, &p, &e)
    });
    let tau = map.tau();
    // Lane-wise over whole arrays (so it vectorises); only candidates reach `accept`.
    let row_sums = |m: &[[Lanes<L>; N]; N]| -> [f64; L] {
        core::array::from_fn(|l| {
            (0..N).fold(0.0, |x: f64, i| {
                x.max((0..N).map(|j| m[i][j].0[l].abs()).sum())
            })
        })
    };
    let (stiff, sweeping) = (row_sums(&hessian), row_sums(&sweep));
    let d: [f64; L] = core::array::from_fn(|l| (q[0].0[l] / p[0].0[l]).abs());
    let rate: [f64; L] = core::array::from_fn(|l| {
        (1..N).fold(0.0, |m: f64, i| {
            m.max(p[i].0[l].abs()).max(grad[i].0[l].abs())
        })
    });
    let candidate: [bool; L] = core::array::from_fn(|l| {
        let (p1, d) = (p[0].0[l], d[l]);
        let inside = (h[l] - 2.0 * d > 0.0) & (h[l] + 2.0 * d <= tau);
        let resolved = (tau * tau * (stiff[l] + tau * sweeping[l]) <= 4.0)
            & ((dg.0[l] - p1).abs() <= 0.05 * p1);
        let gentle = 4.0 * d * grad[0].0[l].abs() <= p1;
        live[l] & (p1 > 0.0) & inside & resolved & gentle
    });
    core::array::from_fn(|l| {
        let radius = 4.0 * d[l] * rate[l] + 1e-12;
        if !(candidate[l] && radius.is_finite()) {
            return None;
        }
        let c = Crossing {
            t: h[l],
            q: core::array::from_fn(|i| q[i].0[l]),
            p: core::array::from_fn(|i| p[i].0[l]),
        };
        accept(l, &c, radius).then_some(c)
    })
}

/// Takes `part` of a step of size `h[l]` in every lane: all lanes together, or (when the
/// lanes' scaled coefficients are zero in some only) one by one, with the same operations.
#[inline(always)]
fn step_lanes<H: Hamiltonian<N>, const N: usize, const L: usize>(
    map: &TangentMap<'_, H>,
    part: StepPart,
    q: &mut [Lanes<L>; N],
    p: &mut [Lanes<L>; N],
    h: &[f64; L],
) {
    let (q_in, p_in) = (*q, *p);
    if map.orbit_step_part_lanes(q, p, h, part) {
        return;
    }
    for l in 0..L {
        let mut ql: [f64; N] = core::array::from_fn(|i| q_in[i].0[l]);
        let mut pl: [f64; N] = core::array::from_fn(|i| p_in[i].0[l]);
        map.orbit_step_part(&mut ql, &mut pl, h[l], part);
        for i in 0..N {
            q[i].0[l] = ql[i];
            p[i].0[l] = pl[i];
        }
    }
}

/// Where the search for a crossing starts: the root of a quartic model of q1(Φ_h), whose slope
/// also serves the first step. The model is the exact flow's Taylor polynomial to third order,
/// q1 + p1 h + a h²/2 + j h³/6 (a splitting step agrees with the flow that far only up to its
/// error constants), plus the h⁴ term that makes it pass through the step's own end,
/// q1(Φ_τ). At τ = 0.5 the end point cuts the first guess's error from 1e-4–1e-3 to
/// 1e-6–1e-5, and the search's partial steps from 3.6 to 2.9 per crossing (`crossing_cost`).
struct CrossingModel<const L: usize> {
    p1: Lanes<L>,
    a: Lanes<L>,
    j: Lanes<L>,
    c4: Lanes<L>,
    h0: [f64; L],
}

impl<const L: usize> CrossingModel<L> {
    fn new<H: Hamiltonian<N>, const N: usize>(
        ham: &H,
        tau: f64,
        q: &[Lanes<L>; N],
        p: &[Lanes<L>; N],
        q1_end: [f64; L],
    ) -> Self {
        let (a, j) = (-ham.grad(q)[0], -ham.hess_vec(q, p)[0]);
        let (q1, p1) = (q[0], p[0]);
        let j6 = div(j, Lanes([6.0; L]));
        let cubic = |h: Lanes<L>| q1 + h * (p1 + h * (Lanes([0.5; L]) * a + h * j6));
        let tau2 = tau * tau;
        let c4 = div(
            Lanes(q1_end) - cubic(Lanes([tau; L])),
            Lanes([tau2 * tau2; L]),
        );
        let mut m = CrossingModel {
            p1,
            a,
            j,
            // τ⁴ underflows for absurdly small steps: the cubic alone then.
            c4: Lanes(c4.0.map(|c| if c.is_finite() { c } else { 0.0 })),
            h0: [0.5 * tau; L],
        };
        // Two Newton steps from the linear guess reach the quartic's root to well below the
        // model's own error.
        let mut h = div(-q1, p1);
        for _ in 0..2 {
            let h2 = h * h;
            let f = cubic(h) + m.c4 * h2 * h2;
            let df = m.slope(h);
            let step = h - div(f, df);
            h = Lanes(core::array::from_fn(|l| {
                if df.0[l] > 0.0 {
                    step.0[l]
                } else {
                    h.0[l]
                }
            }));
        }
        m.h0 = core::array::from_fn(|l| if p1.0[l] > 0.0 { h.0[l] } else { m.h0[l] });
        m
    }

    fn slope(&self, h: Lanes<L>) -> Lanes<L> {
        let four = Lanes([4.0; L]);
        self.p1 + h * (self.a + h * (Lanes([0.5; L]) * self.j + h * (four * self.c4)))
    }
}

/// A mask from a lane-wise condition.
fn mask<const L: usize>(f: impl Fn(usize) -> bool) -> [bool; L] {
    core::array::from_fn(f)
}

/// Lane-wise division.
fn div<const L: usize>(a: Lanes<L>, b: Lanes<L>) -> Lanes<L> {
    Lanes(core::array::from_fn(|l| a.0[l] / b.0[l]))
}

/// Lane-wise `if m { a } else { b }`.
fn select<const L: usize>(m: [bool; L], a: Lanes<L>, b: Lanes<L>) -> Lanes<L> {
    Lanes(core::array::from_fn(|l| if m[l] { a.0[l] } else { b.0[l] }))
}

/// Finds s in [lo, hi] with g(s) = 0, given g(lo) < 0 ≤ g(hi). `eval(s)` returns g(s), g'(s)
/// and whatever state the caller wants at s; g' may only approximate the derivative, so it
/// serves the first step and the secant through the last two evaluations serves the rest,
/// converging superlinearly to the root of g itself. Returns s and the state there; see
/// [`RootSearch`] for the rules.
pub(crate) fn bracketed_root<S>(
    lo: f64,
    hi: f64,
    start: f64,
    tol: f64,
    eval: impl Fn(f64) -> (f64, f64, S),
) -> (f64, S) {
    let mut search = RootSearch::<1>::new(lo, hi, [start], tol);
    loop {
        let (g, dg, state) = eval(search.s.0[0]);
        if !search.evaluated(Lanes([g]), Lanes([dg])) {
            return (search.s.0[0], state);
        }
    }
}

/// The safeguarded Newton/secant search of [`bracketed_root`] for `L` roots at once, one per
/// lane, each lane taking exactly the steps it would take alone (selects, no branches, so
/// the lanes run as SIMD). Every step stays inside a shrinking bisection bracket, so a small
/// or wrong-signed slope (a crossing nearly tangent to the section) never sends it astray. It
/// stops when |g| is a few ulps (g is q1, of order one), when the correction is below `tol`,
/// or when the bracket is exhausted.
struct RootSearch<const L: usize> {
    lo: Lanes<L>,
    hi: Lanes<L>,
    tol: f64,
    /// The point to evaluate next, or (once the lane's search is over) the root.
    s: Lanes<L>,
    /// The previous evaluation (s, g), once there is one.
    prev_s: Lanes<L>,
    prev_g: Lanes<L>,
    has_prev: [bool; L],
    /// The evaluation at `s` is the last one.
    last: [bool; L],
    steps: [u32; L],
    /// The lane's search goes on.
    live: [bool; L],
}

impl<const L: usize> RootSearch<L> {
    fn new(lo: f64, hi: f64, start: [f64; L], tol: f64) -> Self {
        RootSearch {
            lo: Lanes([lo; L]),
            hi: Lanes([hi; L]),
            tol,
            s: Lanes(start.map(|s| s.clamp(lo, hi))),
            prev_s: Lanes([0.0; L]),
            prev_g: Lanes([0.0; L]),
            has_prev: [false; L],
            last: [false; L],
            steps: [0; L],
            live: [true; L],
        }
    }

    /// Takes g(s) and g'(s) of every lane (ignored where the search is over) and moves each
    /// live lane's `s` to its next point; returns whether any lane goes on.
    fn evaluated(&mut self, g: Lanes<L>, dg: Lanes<L>) -> bool {
        let s = self.s;
        // q1 is O(1): a residual of a few ulps is as close to the section as f64 gets.
        let live: [bool; L] = mask(|l| {
            self.live[l]
                & !(self.last[l] | (self.steps[l] == 100) | (g.0[l].abs() <= 4.0 * f64::EPSILON))
        });
        let below: [bool; L] = mask(|l| g.0[l] < 0.0);
        let lo = select(mask(|l| live[l] & below[l]), s, self.lo);
        let hi = select(mask(|l| live[l] & !below[l]), s, self.hi);
        // After the first step, the secant slope through the last two evaluations: it is the
        // slope of g itself, whereas the supplied derivative may only approximate it.
        let secant = mask(|l| {
            self.has_prev[l] & (self.prev_s.0[l] != s.0[l]) & (self.prev_g.0[l] != g.0[l])
        });
        let slope = select(secant, div(g - self.prev_g, s - self.prev_s), dg);
        let newton = s - div(g, slope);
        let inside =
            mask(|l| (slope.0[l] > 0.0) & (newton.0[l] > lo.0[l]) & (newton.0[l] < hi.0[l]));
        let next = select(inside, newton, Lanes([0.5; L]) * (lo + hi));
        let last: [bool; L] = mask(|l| {
            let (lo, hi) = (lo.0[l], hi.0[l]);
            ((next.0[l] - s.0[l]).abs() <= self.tol)
                | (hi - lo <= 4.0 * f64::EPSILON * hi.abs().max(lo.abs()))
        });
        self.lo = lo;
        self.hi = hi;
        self.last = mask(|l| if live[l] { last[l] } else { self.last[l] });
        self.prev_s = select(live, s, self.prev_s);
        self.prev_g = select(live, g, self.prev_g);
        for l in 0..L {
            self.has_prev[l] |= live[l];
            self.steps[l] += live[l] as u32;
        }
        self.s = select(live, next, s);
        self.live = live;
        live.iter().any(|&l| l)
    }
}
