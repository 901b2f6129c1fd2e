//! What every adaptive integrator (DOP853, Taylor) and their drivers share, below all of them:
//! numbers in SIMD lanes ([`Lanewise`]) and their f64 rounding ([`Scalar`]), a step's failure
//! and a batch's step results, the sums tested after every step ([`StepEnd`]), and deviation
//! vectors scaled to unit length. `dop853` and `taylor` build on this module alone, and
//! `adaptive` on the three, so no two of them import each other.

use crate::arith::dd::DoubleDouble;
use crate::arith::real::{dot, Lanes, Real};
use crate::phase::Phase;

/// A number the Taylor integrator can run in: it must convert to f64 for step control.
pub trait Scalar: Real {
    /// The nearest f64.
    fn to_f64(self) -> f64;
}

impl Scalar for f64 {
    #[inline(always)]
    fn to_f64(self) -> f64 {
        self
    }
}

impl Scalar for DoubleDouble {
    #[inline(always)]
    fn to_f64(self) -> f64 {
        DoubleDouble::to_f64(self)
    }
}

/// A number type holding [`Lanewise::LANES`] independent numbers of type [`Lanewise::Lane`]:
/// one for `f64` and `DoubleDouble`, several for their SIMD forms. Step control is per lane;
/// the recursion and the evaluation run on every lane at once.
pub trait Lanewise: Real {
    /// Numbers held (1 for `f64` and `DoubleDouble`).
    const LANES: usize;
    /// The type of one lane's number.
    type Lane: Scalar;
    /// Lane `i`'s number.
    fn lane(self, i: usize) -> Self::Lane;
    /// Sets lane `i`'s number to `x`.
    fn set_lane(&mut self, i: usize, x: Self::Lane);
}

impl Lanewise for f64 {
    const LANES: usize = 1;
    type Lane = f64;
    #[inline(always)]
    fn lane(self, _: usize) -> f64 {
        self
    }
    #[inline(always)]
    fn set_lane(&mut self, _: usize, x: f64) {
        *self = x;
    }
}

impl Lanewise for DoubleDouble {
    const LANES: usize = 1;
    type Lane = DoubleDouble;
    #[inline(always)]
    fn lane(self, _: usize) -> DoubleDouble {
        self
    }
    #[inline(always)]
    fn set_lane(&mut self, _: usize, x: DoubleDouble) {
        *self = x;
    }
}

impl<const L: usize> Lanewise for Lanes<L> {
    const LANES: usize = L;
    type Lane = f64;
    #[inline(always)]
    fn lane(self, i: usize) -> f64 {
        self.0[i]
    }
    #[inline(always)]
    fn set_lane(&mut self, i: usize, x: f64) {
        self.0[i] = x;
    }
}

impl<const L: usize> Lanewise for DoubleDouble<Lanes<L>> {
    const LANES: usize = L;
    type Lane = DoubleDouble;
    #[inline(always)]
    fn lane(self, i: usize) -> DoubleDouble {
        DoubleDouble {
            hi: self.hi.0[i],
            lo: self.lo.0[i],
        }
    }
    #[inline(always)]
    fn set_lane(&mut self, i: usize, x: DoubleDouble) {
        self.hi.0[i] = x.hi;
        self.lo.0[i] = x.lo;
    }
}

/// Lane `l` of a phase point.
#[inline(always)]
pub fn phase_lane<T: Lanewise, const N: usize, const K: usize>(
    y: &Phase<T, N, K>,
    l: usize,
) -> Phase<T::Lane, N, K> {
    Phase {
        q: y.q.map(|x| x.lane(l)),
        p: y.p.map(|x| x.lane(l)),
        dq: y.dq.map(|v| v.map(|x| x.lane(l))),
        dp: y.dp.map(|v| v.map(|x| x.lane(l))),
    }
}

/// Sets lane `l` of a phase point.
#[inline(always)]
pub fn set_phase_lane<T: Lanewise, const N: usize, const K: usize>(
    y: &mut Phase<T, N, K>,
    l: usize,
    x: &Phase<T::Lane, N, K>,
) {
    for i in 0..N {
        y.q[i].set_lane(l, x.q[i]);
        y.p[i].set_lane(l, x.p[i]);
        for k in 0..K {
            y.dq[k][i].set_lane(l, x.dq[k][i]);
            y.dp[k][i].set_lane(l, x.dp[k][i]);
        }
    }
}

/// Why a step could not be taken.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum StepFailure {
    /// The step size fell below what t's precision can resolve.
    StepTooSmall {
        /// Time at which the step failed.
        t: f64,
    },
    /// NaN or infinity in the state or the error estimate.
    NonFinite {
        /// Time at which the step failed.
        t: f64,
    },
}

/// What a batch's step gives its lanes: each asked lane's outcome (`None` for the others) and
/// the factor of each lane's renormalisation before it.
pub type LaneSteps<const L: usize> = ([Option<Result<(), StepFailure>>; L], [f64; L]);

/// The sums the driver tests after every step, over a state rounded to f64: generic, so that
/// a SIMD batch forms them for all its lanes at once with each lane's operations the scalar
/// ones (reading each lane's state and summing it lane by lane is a large share of a run;
/// figures: docs/performance.md).
#[derive(Clone, Copy, Debug)]
pub struct StepEnd<T, const K: usize> {
    /// q₁, the section's coordinate.
    pub q1: T,
    /// q·q.
    pub r2: T,
    /// p·p.
    pub p2: T,
    /// |δq_k|² + |δp_k|² of every deviation vector.
    pub n2: [T; K],
    /// The inner product of the first two deviation vectors.
    pub cross: T,
}

impl<T: crate::arith::real::Real, const K: usize> StepEnd<T, K> {
    /// The sums over `y`.
    #[inline(always)]
    pub fn of<const N: usize>(y: &Phase<T, N, K>) -> Self {
        StepEnd {
            q1: y.q[0],
            r2: dot(&y.q, &y.q),
            p2: dot(&y.p, &y.p),
            n2: core::array::from_fn(|k| dot(&y.dq[k], &y.dq[k]) + dot(&y.dp[k], &y.dp[k])),
            cross: dot(&y.dq[0], &y.dq[1]) + dot(&y.dp[0], &y.dp[1]),
        }
    }
}

impl<const K: usize, const L: usize> StepEnd<Lanes<L>, K> {
    /// Lane `l`'s sums.
    #[inline(always)]
    pub fn lane(&self, l: usize) -> StepEnd<f64, K> {
        StepEnd {
            q1: self.q1.0[l],
            r2: self.r2.0[l],
            p2: self.p2.0[l],
            n2: self.n2.map(|x| x.0[l]),
            cross: self.cross.0[l],
        }
    }
}

/// Scales the deviation vectors of `y` to unit length (the factors rounded to f64, then applied
/// in `T`'s precision); returns the length the first had, as f64.
pub fn unit_vectors<T: Scalar, const N: usize, const K: usize>(y: &mut Phase<T, N, K>) -> f64 {
    unit_deviations(&mut y.dq, &mut y.dp)
}

/// [`unit_vectors`] on the deviation vectors alone (δq, δp), so that a caller holding them
/// elsewhere (a lane of a SIMD batch) need not assemble a whole phase point.
#[inline(always)]
pub fn unit_deviations<T: Scalar, const N: usize, const K: usize>(
    dq: &mut [[T; N]; K],
    dp: &mut [[T; N]; K],
) -> f64 {
    let mut length0 = 0.0;
    for k in 0..K {
        let n2: f64 = dq[k]
            .iter()
            .chain(&dp[k])
            .map(|x| x.to_f64() * x.to_f64())
            .sum();
        let length = n2.sqrt();
        let s = 1.0 / length;
        if k == 0 {
            length0 = length;
        }
        let st = T::splat(s);
        for i in 0..N {
            dq[k][i] = dq[k][i] * st;
            dp[k][i] = dp[k][i] * st;
        }
    }
    length0
}

/// [`unit_deviations`] in every lane of `mask` at once (lane by lane the same operations, so
/// the same bits); the other lanes keep their vectors. Each lane's factor (1 where unmasked).
#[inline(always)]
pub fn unit_deviations_lanes<T, const N: usize, const K: usize, const L: usize>(
    dq: &mut [[T; N]; K],
    dp: &mut [[T; N]; K],
    mask: &[bool; L],
) -> [f64; L]
where
    T: Lanewise + crate::arith::real::Real<Lead = Lanes<L>>,
{
    if !mask.contains(&true) {
        return [1.0; L];
    }
    let every = mask.iter().all(|&m| m);
    let rounded = |x: T| Lanes::<L>::from_fn(|l| x.lane(l).to_f64());
    let mut length0 = Lanes([1.0; L]);
    for k in 0..K {
        // Summed as the scalar sums: left to right over δq then δp, from the first square.
        let first = rounded(dq[k][0]);
        let mut n2 = first * first;
        for x in dq[k][1..].iter().chain(&dp[k]) {
            let x = rounded(*x);
            n2 += x * x;
        }
        let length = Lanes::<L>::from_fn(|l| n2.0[l].sqrt());
        let s = Lanes::<L>::from_fn(|l| 1.0 / length.0[l]);
        if k == 0 {
            length0 = length;
        }
        let st = T::from_lead(s);
        for v in [&mut dq[k], &mut dp[k]] {
            for x in v.iter_mut() {
                let scaled = *x * st;
                if every {
                    *x = scaled;
                } else {
                    for l in (0..L).filter(|&l| mask[l]) {
                        x.set_lane(l, scaled.lane(l));
                    }
                }
            }
        }
    }
    core::array::from_fn(|l| if mask[l] { length0.0[l] } else { 1.0 })
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
