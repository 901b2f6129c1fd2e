//! The state every method advances: a phase-space point and its deviation vectors, with the
//! component-wise arithmetic the general-purpose integrators use.

use crate::arith::real::Real;

/// A phase-space point and `K` deviation vectors (δq, δp).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Phase<T, const N: usize, const K: usize> {
    /// Coordinates.
    pub q: [T; N],
    /// Momenta.
    pub p: [T; N],
    /// The δq part of each deviation vector.
    pub dq: [[T; N]; K],
    /// The δp part of each deviation vector.
    pub dp: [[T; N]; K],
}

impl<T: Copy, const N: usize, const K: usize> Phase<T, N, K> {
    /// The phase point of `f` applied to every component.
    #[inline(always)]
    pub fn map<U>(self, f: impl Fn(T) -> U) -> Phase<U, N, K> {
        Phase {
            q: self.q.map(&f),
            p: self.p.map(&f),
            dq: self.dq.map(|v| v.map(&f)),
            dp: self.dp.map(|v| v.map(&f)),
        }
    }
}

impl<T: Real, const N: usize, const K: usize> Phase<T, N, K> {
    /// All zeros.
    pub fn zero() -> Self {
        let z = [T::splat(0.0); N];
        Phase {
            q: z,
            p: z,
            dq: [z; K],
            dp: [z; K],
        }
    }
}

/// Component-wise arithmetic on a phase point as one vector of 2N(K + 1) numbers, for the
/// general-purpose integrators (DOP853, Taylor), in f64 or in SIMD lanes of it.
impl<T: Real, const N: usize, const K: usize> Phase<T, N, K> {
    /// self += a·x.
    #[inline(always)]
    pub fn axpy(&mut self, a: T, x: &Self) {
        self.zip_mut(x, |s, v| *s = v.mul_add(a, *s));
    }

    /// self *= a.
    #[inline(always)]
    pub fn scale(&mut self, a: T) {
        let copy = *self;
        self.zip_mut(&copy, |s, _| *s = *s * a);
    }

    /// Calls `f(self_i, x_i)` on every component pair, mutably.
    #[inline(always)]
    pub fn zip_mut(&mut self, x: &Self, mut f: impl FnMut(&mut T, T)) {
        for i in 0..N {
            f(&mut self.q[i], x.q[i]);
            f(&mut self.p[i], x.p[i]);
        }
        for k in 0..K {
            for i in 0..N {
                f(&mut self.dq[k][i], x.dq[k][i]);
                f(&mut self.dp[k][i], x.dp[k][i]);
            }
        }
    }

    /// Calls `f(self_i, x_i)` on every component pair.
    #[inline(always)]
    pub fn zip_for_each(&self, x: &Self, mut f: impl FnMut(T, T)) {
        let mut me = *self;
        me.zip_mut(x, |s, v| f(*s, v));
    }

    /// Calls `f(self_i, a_i, b_i, c_i)` on every component.
    #[inline(always)]
    pub fn zip3_for_each(&self, a: &Self, b: &Self, c: &Self, mut f: impl FnMut(T, T, T, T)) {
        for i in 0..N {
            f(self.q[i], a.q[i], b.q[i], c.q[i]);
            f(self.p[i], a.p[i], b.p[i], c.p[i]);
        }
        for k in 0..K {
            for i in 0..N {
                f(self.dq[k][i], a.dq[k][i], b.dq[k][i], c.dq[k][i]);
                f(self.dp[k][i], a.dp[k][i], b.dp[k][i], c.dp[k][i]);
            }
        }
    }
}
