//! The tangent-map method: an orbit and `K` deviation vectors advanced together by the same
//! drift/kick/corrector sub-maps (Skokos & Gerlach 2010), each deviation vector by the Jacobian
//! of each sub-map evaluated where the orbit applies it.
//!
//! One stepping loop serves every [`Scheme`]: a step is the scheme's sub-maps applied in turn.
//! Consecutive steps share their end sub-map (the scheme is palindromic, so it both ends one step
//! and starts the next, at the same q for a kick, the same p for a drift): the loop evaluates it
//! once per step and applies the increment twice, once to close step n — which leaves the state
//! synchronised at t = nτ for indicators, crossings and output — and once to open step n + 1.

use crate::arith::real::Lanes;
use crate::arith::real::Real;
use crate::phase::Phase;
use crate::systems::hamiltonian::Hamiltonian;
use crate::tangent_map::scheme::{Op, Scheme};

/// A sub-map with its coefficients already multiplied by the step (aτ, bτ, γτ³).
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) enum SubMap {
    Drift(f64),
    Kick(f64),
    Corrector(f64),
    KickCorrector(f64, f64),
}

impl SubMap {
    #[inline(always)]
    fn scaled(op: Op, h: f64) -> SubMap {
        match op {
            Op::Drift(a) => SubMap::Drift(a * h),
            Op::Kick { b, gamma } => {
                let (b, c) = (b * h, gamma * h * h * h);
                match (b != 0.0, c != 0.0) {
                    (true, false) => SubMap::Kick(b),
                    (false, _) => SubMap::Corrector(c),
                    (true, true) => SubMap::KickCorrector(b, c),
                }
            }
        }
    }

    #[inline(always)]
    fn is_drift(self) -> bool {
        matches!(self, SubMap::Drift(_))
    }
}

/// A scaled coefficient as [`Hamiltonian::kick_terms`] takes it: `None` when it is zero.
#[inline(always)]
fn nonzero<T: Real>(v: f64) -> Option<T> {
    (v != 0.0).then(|| T::splat(v))
}

/// acc + M·u, accumulated with fused multiply-adds. Written as loops over a copy rather than
/// with `array::from_fn`, which the compiler outlines for wide lanes (8 and more), forcing
/// the whole step's state through memory.
#[inline(always)]
fn mat_vec_add<T: Real, const N: usize>(m: &[[T; N]; N], u: &[T; N], acc: &[T; N]) -> [T; N] {
    let mut s = *acc;
    for i in 0..N {
        for j in 0..N {
            s[i] = m[i][j].mul_add(u[j], s[i]);
        }
    }
    s
}

#[inline(always)]
fn apply<H: Hamiltonian<N>, T: Real, const N: usize, const K: usize>(
    ham: &H,
    x: &mut Phase<T, N, K>,
    op: SubMap,
) {
    match op {
        SubMap::Drift(a) => drift(x, a),
        SubMap::Kick(b) => kick(ham, x, nonzero(b), None),
        SubMap::Corrector(c) => kick(ham, x, None, nonzero(c)),
        SubMap::KickCorrector(b, c) => kick(ham, x, nonzero(b), nonzero(c)),
    }
}

#[inline(always)]
fn drift<T: Real, const N: usize, const K: usize>(x: &mut Phase<T, N, K>, a: f64) {
    let a = T::splat(a);
    for i in 0..N {
        x.q[i] = x.p[i].mul_add(a, x.q[i]);
    }
    for k in 0..K {
        for i in 0..N {
            x.dq[k][i] = x.dp[k][i].mul_add(a, x.dq[k][i]);
        }
    }
}

/// A kick by `b` with a corrector by `c` (`None`: a zero coefficient, see [`nonzero`]).
#[inline(always)]
fn kick<H: Hamiltonian<N>, T: Real, const N: usize, const K: usize>(
    ham: &H,
    x: &mut Phase<T, N, K>,
    b: Option<T>,
    c: Option<T>,
) {
    let t = ham.kick_terms(&x.q, b, c);
    for i in 0..N {
        x.p[i] += t.force[i];
    }
    for k in 0..K {
        x.dp[k] = mat_vec_add(&t.matrix, &x.dq[k], &x.dp[k]);
    }
}

/// The increment of the shared end sub-map: added to p and δp for a kick, to q and δq for a drift.
#[derive(Clone, Copy, Debug)]
pub(crate) struct EdgeIncrement<T, const N: usize, const K: usize> {
    pub orbit: [T; N],
    pub dev: [[T; N]; K],
}

/// A scheme compiled for one step size τ.
#[derive(Clone, Debug)]
pub struct TangentMap<'h, H> {
    ham: &'h H,
    tau: f64,
    /// All sub-maps of one step, for unmerged steps (crossing location, tests).
    ops: Vec<Op>,
    /// The end sub-map shared by consecutive steps, scaled by τ.
    edge: SubMap,
    /// The sub-maps strictly between the two ends, scaled by τ.
    body: Vec<SubMap>,
    /// The body as alternating drifts and plain kicks (every scheme here has this shape):
    /// whether it starts with a drift, and the scaled coefficients.
    alternating: Option<(bool, Vec<f64>)>,
}

/// The two parts of one orbit step that a crossing search takes separately.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum StepPart {
    /// Every sub-map up to the last one that moves q, so q is final (a root search on q1 needs
    /// nothing more).
    MovingQ,
    /// The rest: a final kick, if the scheme ends with one.
    Rest,
}

/// Whether `body` alternates drifts and plain kicks, and if so its coefficients.
fn alternating_shape(body: &[SubMap]) -> Option<(bool, Vec<f64>)> {
    let drift_first = body.first()?.is_drift();
    let mut coeffs = Vec::with_capacity(body.len());
    for (i, op) in body.iter().enumerate() {
        match (*op, (i % 2 == 0) == drift_first) {
            (SubMap::Drift(a), true) => coeffs.push(a),
            (SubMap::Kick(b), false) => coeffs.push(b),
            _ => return None,
        }
    }
    Some((drift_first, coeffs))
}

impl<'h, H> TangentMap<'h, H> {
    /// Compiles `scheme` for step size `tau` on `ham`.
    pub fn new(ham: &'h H, scheme: &Scheme, tau: f64) -> Self {
        let ops = scheme.ops();
        let scaled: Vec<SubMap> = ops.iter().map(|&o| SubMap::scaled(o, tau)).collect();
        let edge = scaled[0];
        let body = scaled[1..scaled.len() - 1].to_vec();
        let alternating = alternating_shape(&body);
        TangentMap {
            alternating,
            ham,
            tau,
            ops,
            edge,
            body,
        }
    }

    /// The step size τ.
    pub fn tau(&self) -> f64 {
        self.tau
    }

    /// The Hamiltonian integrated.
    pub fn hamiltonian(&self) -> &'h H {
        self.ham
    }

    /// One unmerged step of size `h` (any h, not only τ) of the orbit and its deviation vectors.
    pub fn step<T: Real, const N: usize, const K: usize>(&self, x: &mut Phase<T, N, K>, h: f64)
    where
        H: Hamiltonian<N>,
    {
        self.step_ops(x, h, 0..self.ops.len());
    }

    /// Sub-maps `range` of one unmerged step of size `h`.
    fn step_ops<T: Real, const N: usize, const K: usize>(
        &self,
        x: &mut Phase<T, N, K>,
        h: f64,
        range: core::ops::Range<usize>,
    ) where
        H: Hamiltonian<N>,
    {
        for &op in &self.ops[range] {
            apply(self.ham, x, SubMap::scaled(op, h));
        }
    }

    /// One unmerged step of size `h` of the orbit alone.
    pub fn orbit_step<const N: usize>(&self, q: &mut [f64; N], p: &mut [f64; N], h: f64)
    where
        H: Hamiltonian<N>,
    {
        self.orbit_ops(q, p, h, 0..self.ops.len());
    }

    /// How many of one step's sub-maps move q: all but a final kick, which changes p only.
    fn ops_moving_q(&self) -> usize {
        match self.ops.last() {
            Some(Op::Kick { .. }) => self.ops.len() - 1,
            _ => self.ops.len(),
        }
    }

    /// The sub-maps of one step that make up `part`.
    #[inline(always)]
    fn part_range(&self, part: StepPart) -> core::ops::Range<usize> {
        match part {
            StepPart::MovingQ => 0..self.ops_moving_q(),
            StepPart::Rest => self.ops_moving_q()..self.ops.len(),
        }
    }

    /// `part` of [`TangentMap::orbit_step`]: the two parts in turn perform exactly the
    /// operations of the whole step.
    pub(crate) fn orbit_step_part<const N: usize>(
        &self,
        q: &mut [f64; N],
        p: &mut [f64; N],
        h: f64,
        part: StepPart,
    ) where
        H: Hamiltonian<N>,
    {
        self.orbit_ops(q, p, h, self.part_range(part));
    }

    /// [`TangentMap::orbit_step_part`] for `L` orbits with their own step sizes, one per SIMD
    /// lane, each lane performing exactly the scalar operations. Returns false, with `q` and
    /// `p` in an unspecified state, when the lanes would take different code paths (a scaled
    /// coefficient that is zero in some lanes only: h = 0 or underflow); the caller then steps
    /// the lanes one by one.
    #[inline(always)]
    pub(crate) fn orbit_step_part_lanes<const N: usize, const L: usize>(
        &self,
        q: &mut [Lanes<L>; N],
        p: &mut [Lanes<L>; N],
        h: &[f64; L],
        part: StepPart,
    ) -> bool
    where
        H: Hamiltonian<N>,
    {
        let same = |x: &Lanes<L>| x.0.iter().all(|&v| (v != 0.0) == (x.0[0] != 0.0));
        for &op in &self.ops[self.part_range(part)] {
            match op {
                Op::Drift(a) => {
                    let a = Lanes(h.map(|h| a * h));
                    for i in 0..N {
                        q[i] = p[i].mul_add(a, q[i]);
                    }
                }
                Op::Kick { b, gamma } => {
                    let (b, c) = (Lanes(h.map(|h| b * h)), Lanes(h.map(|h| gamma * h * h * h)));
                    if !same(&b) || !same(&c) {
                        return false;
                    }
                    let (kick, correct) = (b.0[0] != 0.0, c.0[0] != 0.0);
                    let t = self
                        .ham
                        .kick_terms(q, kick.then_some(b), correct.then_some(c));
                    for i in 0..N {
                        p[i] += t.force[i];
                    }
                }
            }
        }
        true
    }

    fn orbit_ops<const N: usize>(
        &self,
        q: &mut [f64; N],
        p: &mut [f64; N],
        h: f64,
        range: core::ops::Range<usize>,
    ) where
        H: Hamiltonian<N>,
    {
        let mut x: Phase<f64, N, 0> = Phase {
            q: *q,
            p: *p,
            dq: [],
            dp: [],
        };
        self.step_ops(&mut x, h, range);
        *q = x.q;
        *p = x.p;
    }

    #[inline(always)]
    pub(crate) fn edge_increment<T: Real, const N: usize, const K: usize>(
        &self,
        x: &Phase<T, N, K>,
    ) -> EdgeIncrement<T, N, K>
    where
        H: Hamiltonian<N>,
    {
        match self.edge {
            SubMap::Drift(a) => {
                let a = T::splat(a);
                EdgeIncrement {
                    orbit: core::array::from_fn(|i| a * x.p[i]),
                    dev: core::array::from_fn(|k| core::array::from_fn(|i| a * x.dp[k][i])),
                }
            }
            SubMap::Kick(b) => self.kick_increment(x, nonzero(b), None),
            SubMap::Corrector(c) => self.kick_increment(x, None, nonzero(c)),
            SubMap::KickCorrector(b, c) => self.kick_increment(x, nonzero(b), nonzero(c)),
        }
    }

    #[inline(always)]
    fn kick_increment<T: Real, const N: usize, const K: usize>(
        &self,
        x: &Phase<T, N, K>,
        b: Option<T>,
        c: Option<T>,
    ) -> EdgeIncrement<T, N, K>
    where
        H: Hamiltonian<N>,
    {
        let t = self.ham.kick_terms(&x.q, b, c);
        let zero = [T::splat(0.0); N];
        let mut dev = [zero; K];
        for k in 0..K {
            dev[k] = mat_vec_add(&t.matrix, &x.dq[k], &zero);
        }
        EdgeIncrement {
            orbit: t.force,
            dev,
        }
    }

    #[inline(always)]
    pub(crate) fn apply_edge<T: Real, const N: usize, const K: usize>(
        &self,
        x: &mut Phase<T, N, K>,
        inc: &EdgeIncrement<T, N, K>,
    ) {
        if self.edge.is_drift() {
            for i in 0..N {
                x.q[i] += inc.orbit[i];
            }
            for k in 0..K {
                for i in 0..N {
                    x.dq[k][i] += inc.dev[k][i];
                }
            }
        } else {
            add_kick_increment(x, inc);
        }
    }

    /// Advances a synchronised state by one step τ. `inc` must hold the end sub-map's increment
    /// at `x` (from [`TangentMap::edge_increment`]) and is updated to the new state's.
    #[inline(always)]
    pub(crate) fn advance<T: Real, const N: usize, const K: usize>(
        &self,
        x: &mut Phase<T, N, K>,
        inc: &mut EdgeIncrement<T, N, K>,
    ) where
        H: Hamiltonian<N>,
    {
        // Work on a local copy: with the body unrolled below, the whole step stays in
        // registers instead of loading and storing the state around every sub-map.
        let mut s = *x;
        self.apply_edge(&mut s, inc);
        match &self.alternating {
            Some((true, c)) => match c.len() {
                1 => self.body_unrolled::<T, N, K, 1, true>(&mut s, c),
                3 => self.body_unrolled::<T, N, K, 3, true>(&mut s, c),
                5 => self.body_unrolled::<T, N, K, 5, true>(&mut s, c),
                7 => self.body_unrolled::<T, N, K, 7, true>(&mut s, c),
                9 => self.body_unrolled::<T, N, K, 9, true>(&mut s, c),
                _ => self.body_in_turn(&mut s),
            },
            Some((false, c)) => match c.len() {
                1 => self.body_unrolled::<T, N, K, 1, false>(&mut s, c),
                3 => self.body_unrolled::<T, N, K, 3, false>(&mut s, c),
                5 => self.body_unrolled::<T, N, K, 5, false>(&mut s, c),
                7 => self.body_unrolled::<T, N, K, 7, false>(&mut s, c),
                _ => self.body_in_turn(&mut s),
            },
            None => self.body_in_turn(&mut s),
        }
        *inc = self.edge_increment(&s);
        self.apply_edge(&mut s, inc);
        *x = s;
    }

    #[inline(always)]
    fn body_in_turn<T: Real, const N: usize, const K: usize>(&self, x: &mut Phase<T, N, K>)
    where
        H: Hamiltonian<N>,
    {
        for &op in &self.body {
            apply(self.ham, x, op);
        }
    }

    /// The body with its length and drift/kick pattern known at compile time, so it unrolls
    /// into straight-line code (same operations as [`Self::body_in_turn`]).
    #[inline(always)]
    fn body_unrolled<
        T: Real,
        const N: usize,
        const K: usize,
        const M: usize,
        const DRIFT_FIRST: bool,
    >(
        &self,
        x: &mut Phase<T, N, K>,
        coeffs: &[f64],
    ) where
        H: Hamiltonian<N>,
    {
        let c: &[f64; M] = coeffs.try_into().expect("body length");
        for (i, &ci) in c.iter().enumerate() {
            if (i % 2 == 0) == DRIFT_FIRST {
                apply(self.ham, x, SubMap::Drift(ci));
            } else {
                apply(self.ham, x, SubMap::Kick(ci));
            }
        }
    }
}

/// Adds a kick's increment (to p and δp).
#[inline(always)]
fn add_kick_increment<T: Real, const N: usize, const K: usize>(
    x: &mut Phase<T, N, K>,
    inc: &EdgeIncrement<T, N, K>,
) {
    for i in 0..N {
        x.p[i] += inc.orbit[i];
    }
    for k in 0..K {
        for i in 0..N {
            x.dp[k][i] += inc.dev[k][i];
        }
    }
}

/// How a batched loop takes its steps, chosen once per loop rather than at every step.
/// [`TangentMap::advance`] finds the map's shape at every step (an indirect jump on the body's
/// length, tests of the edge's kind and of each coefficient against zero); a loop compiled for
/// one shape, its coefficients read once, has none of that, which speeds up 4-lane loops
/// (`batch_profile` figures: docs/performance.md).
pub(crate) trait StepShape: Copy {
    /// [`TangentMap::advance`] for the map the shape was read from: the same operations.
    fn advance<H: Hamiltonian<N>, T: Real, const N: usize, const K: usize>(
        self,
        map: &TangentMap<'_, H>,
        x: &mut Phase<T, N, K>,
        inc: &mut EdgeIncrement<T, N, K>,
    );

    /// A bound on the norm of the tangent map of `steps` consecutive steps, which bounds the
    /// norm of its inverse too, for an orbit whose positions at the steps' ends stay within
    /// |q| ≤ `r` and whose momentum starts within |p| ≤ `p`; `None` where the shape or the
    /// system gives none.
    fn stretch_bound<H: Hamiltonian<N>, const N: usize>(
        self,
        _map: &TangentMap<'_, H>,
        _r: f64,
        _p: f64,
        _steps: u64,
    ) -> Option<f64> {
        None
    }
}

/// Any map: its own dispatch at every step.
#[derive(Clone, Copy)]
pub(crate) struct AnyShape;

impl StepShape for AnyShape {
    #[inline(always)]
    fn advance<H: Hamiltonian<N>, T: Real, const N: usize, const K: usize>(
        self,
        map: &TangentMap<'_, H>,
        x: &mut Phase<T, N, K>,
        inc: &mut EdgeIncrement<T, N, K>,
    ) {
        map.advance(x, inc)
    }
}

/// A corrected kick at both ends and drift–kick–drift between, no coefficient zero: the shape
/// of SBAB2C, the paper's scheme and every tangent-map row of its Table 2. Holds the scaled
/// coefficients: the edge's kick and corrector, then the body's drift, kick and drift.
#[derive(Clone, Copy)]
pub(crate) struct CorrectedDkd {
    edge: (f64, f64),
    body: [f64; 3],
}

impl CorrectedDkd {
    /// The shape of `map`'s steps, if it is this one.
    pub(crate) fn of<H>(map: &TangentMap<'_, H>) -> Option<Self> {
        let SubMap::KickCorrector(b, c) = map.edge else {
            return None;
        };
        let Some((true, body)) = &map.alternating else {
            return None;
        };
        let body: [f64; 3] = body.as_slice().try_into().ok()?;
        // `nonzero` would drop a zero coefficient's terms; this shape always keeps them.
        let nonzero = [b, c, body[1]].iter().all(|&v| v != 0.0);
        nonzero.then_some(CorrectedDkd { edge: (b, c), body })
    }
}

impl StepShape for CorrectedDkd {
    #[inline(always)]
    fn advance<H: Hamiltonian<N>, T: Real, const N: usize, const K: usize>(
        self,
        map: &TangentMap<'_, H>,
        x: &mut Phase<T, N, K>,
        inc: &mut EdgeIncrement<T, N, K>,
    ) {
        let ((b, c), [a1, b1, a2]) = (self.edge, self.body);
        let mut s = *x;
        add_kick_increment(&mut s, inc);
        drift(&mut s, a1);
        kick(map.ham, &mut s, Some(T::splat(b1)), None);
        drift(&mut s, a2);
        *inc = map.kick_increment(&s, Some(T::splat(b)), Some(T::splat(c)));
        add_kick_increment(&mut s, inc);
        *x = s;
    }

    /// A step acts on deviation vectors as five maps in turn: the edge's shear δp += S δq
    /// (S = −b D²V + c D²K at the step's start), the drift δq += a1 δp, the body's shear
    /// (−b1 D²V at the middle position), the drift by a2, and the edge's shear at the end.
    /// A shear [[I, 0], [S, I]] has norm at most 1 + ‖S‖ and a drift at most 1 + |a|; the
    /// inverse of each is the same map with −S or −a, so the same bound holds for the
    /// inverse. The middle position lies within |a1|·|p| of the start (p after the first
    /// kick), and every kick adds at most its force's bound to |p|.
    fn stretch_bound<H: Hamiltonian<N>, const N: usize>(
        self,
        map: &TangentMap<'_, H>,
        r: f64,
        p: f64,
        steps: u64,
    ) -> Option<f64> {
        let ((b, c), [a1, b1, a2]) = (self.edge, self.body);
        let ham = map.hamiltonian();
        let ends = ham.derivative_bounds(r)?;
        let edge_force = b.abs() * ends.grad + c.abs() * ends.corrector_grad;
        let edge_shear = 1.0 + b.abs() * ends.hessian + c.abs() * ends.corrector_hessian;
        let drifts = (1.0 + a1.abs()) * (1.0 + a2.abs());
        let (mut p, mut stretch) = (p, 1.0);
        for _ in 0..steps {
            p += edge_force;
            let middle = ham.derivative_bounds(r + a1.abs() * p)?;
            p += b1.abs() * middle.grad + edge_force;
            stretch *= edge_shear * edge_shear * drifts * (1.0 + b1.abs() * middle.hessian);
        }
        // Room for the rounding of the products above.
        let stretch = stretch * (1.0 + 1e-9);
        stretch.is_finite().then_some(stretch)
    }
}

/// A scalar orbit being advanced in steps of τ, its end-sub-map increment kept alongside.
pub struct Stepping<'m, 'h, H, const N: usize, const K: usize> {
    map: &'m TangentMap<'h, H>,
    /// The current state.
    pub x: Phase<f64, N, K>,
    inc: EdgeIncrement<f64, N, K>,
}

impl<'m, 'h, H: Hamiltonian<N>, const N: usize, const K: usize> Stepping<'m, 'h, H, N, K> {
    /// Starts stepping from `x`.
    pub fn new(map: &'m TangentMap<'h, H>, x: Phase<f64, N, K>) -> Self {
        let inc = map.edge_increment(&x);
        Stepping { map, x, inc }
    }

    /// One step τ; afterwards `x` is the synchronised state at the next multiple of τ.
    #[inline(always)]
    pub fn advance(&mut self) {
        self.map.advance(&mut self.x, &mut self.inc);
    }

    pub(crate) fn parts_mut(&mut self) -> (&mut Phase<f64, N, K>, &mut EdgeIncrement<f64, N, K>) {
        (&mut self.x, &mut self.inc)
    }

    /// Multiplies deviation vector `k` by `s`, which must be a power of two so that scaling is
    /// exact and commutes bit for bit with every later operation.
    #[inline]
    pub fn scale_vector(&mut self, k: usize, s: f64) {
        for i in 0..N {
            self.x.dq[k][i] *= s;
            self.x.dp[k][i] *= s;
            self.inc.dev[k][i] *= s;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::arith::real::dot;
    use crate::indicators::norm2;
    use crate::systems::hamiltonian::HenonHeiles;

    fn r1() -> ([f64; 2], [f64; 2]) {
        let (q2, p2) = (0.558f64, 0.0f64);
        let p1 = (0.25 - p2 * p2 - q2 * q2 + 2.0 * q2 * q2 * q2 / 3.0).sqrt();
        ([0.0, q2], [p1, p2])
    }

    /// The stretch bound of SBAB2C's shape holds on real orbits: over windows of `steps`
    /// steps along a chaotic and a regular orbit, no deviation vector (the two axes and two
    /// tilted ones) grows or shrinks by more than the bound for the window's largest |q| and
    /// its first |p|, and the sine of the angle between two vectors shrinks by at most its
    /// fourth power. At τ = 0.01 the bound over 16 steps stays below 2.5, so the quiet
    /// windows it serves are possible where they matter.
    #[test]
    fn stretch_bound_holds_along_orbits() {
        let ham = HenonHeiles;
        let scheme = Scheme::by_name("sbab2c").unwrap();
        let c1 = {
            let (q2, p2) = (-0.25f64, 0.0f64);
            let p1 = (0.25 - p2 * p2 - q2 * q2 + 2.0 * q2 * q2 * q2 / 3.0).sqrt();
            ([0.0, q2], [p1, p2])
        };
        let norm = |x: &Phase<f64, 2, 4>, k: usize| norm2(&x.dq[k], &x.dp[k]).sqrt();
        // The windows' vectors start far from aligned, where 1 − cos² loses nothing.
        let sine = |x: &Phase<f64, 2, 4>, a: usize, b: usize| {
            let c = dot(&x.dq[a], &x.dq[b]) + dot(&x.dp[a], &x.dp[b]);
            let cos = c / (norm(x, a) * norm(x, b));
            (1.0 - cos * cos).max(0.0).sqrt()
        };
        let mut windows = 0;
        for (tau, steps) in [(0.01, 16u64), (0.05, 8), (0.5, 2)] {
            let map = TangentMap::new(&ham, &scheme, tau);
            let shape = CorrectedDkd::of(&map).unwrap();
            if tau == 0.01 {
                assert!(shape.stretch_bound(&map, 1.0, 1.0, 16).unwrap() < 2.5);
            }
            for (q, p) in [c1, r1()] {
                let mut x: Phase<f64, 2, 4> = Phase::zero();
                (x.q, x.p) = (q, p);
                for w in 0..400 {
                    // Fresh vectors at each window's start: the axes and two tilted ones.
                    x.dq = [[1.0, 0.0], [0.0, 1.0], [0.6, -0.3], [0.0, 0.0]];
                    x.dp = [[0.0, 0.0], [0.0, 0.0], [0.2, 0.7], [1.0, 1e-3]];
                    let mut inc = map.edge_increment(&x);
                    let p0 = x.p[0].hypot(x.p[1]);
                    let sine0 = [sine(&x, 0, 1), sine(&x, 2, 3), sine(&x, 0, 3)];
                    let mut r: f64 = x.q[0].hypot(x.q[1]);
                    for _ in 0..steps {
                        shape.advance(&map, &mut x, &mut inc);
                        r = r.max(x.q[0].hypot(x.q[1]));
                    }
                    let bound = shape.stretch_bound(&map, r, p0, steps).unwrap();
                    for k in 0..4 {
                        let n = norm(&x, k);
                        assert!(
                            n <= bound && n >= 1.0 / bound,
                            "τ {tau} window {w}: {n} {bound}"
                        );
                    }
                    let now = [sine(&x, 0, 1), sine(&x, 2, 3), sine(&x, 0, 3)];
                    for (s0, s) in sine0.iter().zip(now) {
                        assert!(s >= s0 / bound.powi(4), "τ {tau} window {w}");
                    }
                    windows += 1;
                }
            }
        }
        assert_eq!(windows, 2400);
        assert!(AnyShape
            .stretch_bound(&TangentMap::new(&ham, &scheme, 0.01), 1.0, 1.0, 16)
            .is_none());
    }

    /// Of every scheme only SBAB2C has the corrected drift–kick–drift shape, and its steps
    /// taken through that shape are the map's own, bit for bit.
    #[test]
    fn the_fixed_shape_is_sbab2c_and_steps_as_the_map_does() {
        let ham = HenonHeiles;
        for scheme in Scheme::all() {
            let map = TangentMap::new(&ham, &scheme, 0.3);
            let shape = CorrectedDkd::of(&map);
            assert_eq!(shape.is_some(), scheme.name == "sbab2c", "{}", scheme.name);
            let Some(shape) = shape else { continue };
            let (q, p) = r1();
            let mut a: Phase<f64, 2, 2> = Phase::zero();
            (a.q, a.p) = (q, p);
            a.dq[0][0] = 1.0;
            a.dp[1][1] = 1.0;
            let (mut b, mut inc_a) = (a, map.edge_increment(&a));
            let mut inc_b = inc_a;
            for _ in 0..500 {
                map.advance(&mut a, &mut inc_a);
                shape.advance(&map, &mut b, &mut inc_b);
            }
            let bits = |x: &Phase<f64, 2, 2>| {
                let all = [x.q, x.p, x.dq[0], x.dq[1], x.dp[0], x.dp[1]];
                all.map(|v| v.map(f64::to_bits))
            };
            assert_eq!(bits(&a), bits(&b));
        }
    }

    #[test]
    fn merged_steps_equal_unmerged_steps_to_rounding() {
        let ham = HenonHeiles;
        for scheme in Scheme::all() {
            let map = TangentMap::new(&ham, &scheme, 0.05);
            let (q, p) = r1();
            let mut a: Phase<f64, 2, 2> = Phase::zero();
            a.q = q;
            a.p = p;
            a.dq[0][0] = 1.0;
            a.dq[1][1] = 1.0;
            let mut b = a;
            let mut s = Stepping::new(&map, a);
            for _ in 0..200 {
                s.advance();
                map.step(&mut b, 0.05);
            }
            let a = s.x;
            for i in 0..2 {
                assert!((a.q[i] - b.q[i]).abs() < 1e-12, "{}", scheme.name);
                assert!((a.p[i] - b.p[i]).abs() < 1e-12, "{}", scheme.name);
                for k in 0..2 {
                    let scale = 1.0 + b.dq[k][i].abs() + b.dp[k][i].abs();
                    assert!(
                        (a.dq[k][i] - b.dq[k][i]).abs() < 1e-10 * scale,
                        "{}",
                        scheme.name
                    );
                    assert!(
                        (a.dp[k][i] - b.dp[k][i]).abs() < 1e-10 * scale,
                        "{}",
                        scheme.name
                    );
                }
            }
        }
    }
}
