//! Taylor series along a solution: the coefficient arrays, their Cauchy products, and the
//! [`TaylorSeries`] systems whose ∇V and D²V·u have series computable from those of q and u
//! (Hénon–Heiles by hand here; polynomial systems in [`super::polynomial`]).

use crate::arith::real::Real;
use crate::systems::hamiltonian::{Hamiltonian, HenonHeiles};

/// Highest order supported (δ = 1e-32 needs p = 38).
pub const P_MAX: usize = 48;

/// Taylor coefficients of one variable up to P_MAX.
pub type Series<T> = [T; P_MAX + 1];

/// Σ_{j=0..k} a_j b_{k−j}: coefficient k of a product.
#[inline(always)]
pub fn cauchy<T: Real>(a: &Series<T>, b: &Series<T>, k: usize) -> T {
    let mut s = a[0] * b[k];
    for j in 1..=k {
        s = a[j].mul_add(b[k - j], s);
    }
    s
}

/// Hamiltonians whose ∇V is a polynomial, so its series along a solution is a finite
/// combination of Cauchy products.
pub trait TaylorSeries<const N: usize>: Hamiltonian<N> {
    /// How many series of q [`Self::all_coeffs`] keeps across orders (the length of its
    /// `derived`).
    fn derived_series(&self) -> usize {
        0
    }

    /// Coefficient k of ∇V(q(t)) and of D²V(q(t))·u(t) for every deviation vector u, given the
    /// coefficients 0..=k of q and u. Called for k = 0, 1, 2, … in turn with the same
    /// `derived` ([`Self::derived_series`] long): series of q an implementation fills at order
    /// k and reads at every later order (products of coordinates, instead of recomputing them
    /// for each).
    fn all_coeffs<T: Real, const K: usize>(
        &self,
        q: &[Series<T>; N],
        u: &[[Series<T>; N]; K],
        derived: &mut [Series<T>],
        k: usize,
    ) -> ([T; N], [[T; N]; K]);
}

impl HenonHeiles {
    #[inline(always)]
    /// Coefficient k of ∇V(q(t)), given the coefficients 0..=k of q.
    pub fn grad_coeff<T: Real>(&self, q: &[Series<T>; 2], k: usize) -> [T; 2] {
        // ∇V = (q1 + 2 q1 q2, q2 + q1² − q2²) = (q1 + 2 q1 q2, q2 + (q1 − q2)(q1 + q2)). The
        // products are summed in one pass so their chains of fused multiply-adds interleave.
        let (a, b) = (&q[0], &q[1]);
        let (mut s12, mut sd) = (a[0] * b[k], (a[0] - b[0]) * (a[k] + b[k]));
        for j in 1..=k {
            s12 = a[j].mul_add(b[k - j], s12);
            sd = (a[j] - b[j]).mul_add(a[k - j] + b[k - j], sd);
        }
        [T::splat(2.0).mul_add(s12, a[k]), b[k] + sd]
    }

    #[inline(always)]
    /// Coefficient k of D²V(q(t))·u(t), given the coefficients 0..=k of q and u.
    pub fn hess_vec_coeff<T: Real>(
        &self,
        q: &[Series<T>; 2],
        u: &[Series<T>; 2],
        k: usize,
    ) -> [T; 2] {
        // D²V u = (u1 + 2 (q2 u1 + q1 u2), u2 + 2 (q1 u1 − q2 u2)), the sums in one pass.
        let (a, b, x, y) = (&q[0], &q[1], &u[0], &u[1]);
        let (mut s1, mut s2) = (b[0] * x[k] + a[0] * y[k], a[0] * x[k] - b[0] * y[k]);
        for j in 1..=k {
            s1 = b[j].mul_add(x[k - j], a[j].mul_add(y[k - j], s1));
            s2 = a[j].mul_add(x[k - j], (-b[j]).mul_add(y[k - j], s2));
        }
        let two = T::splat(2.0);
        [two.mul_add(s1, x[k]), two.mul_add(s2, y[k])]
    }
}

impl TaylorSeries<2> for HenonHeiles {
    fn derived_series(&self) -> usize {
        2
    }

    #[inline(always)]
    fn all_coeffs<T: Real, const K: usize>(
        &self,
        q: &[Series<T>; 2],
        u: &[[Series<T>; 2]; K],
        derived: &mut [Series<T>],
        k: usize,
    ) -> ([T; 2], [[T; 2]; K]) {
        // The sums of grad_coeff and of every hess_vec_coeff in one pass over j, each summed
        // in the same order as there (same bits); in double-double each sum is a long chain
        // of dependent operations, and side by side they overlap. q1 − q2 and q1 + q2 are
        // kept as series (`derived`): grad_coeff forms them afresh for every product, which
        // in double-double is a visible share of the step (figures: docs/performance.md).
        let (a, b) = (&q[0], &q[1]);
        let [dif, sum, ..] = derived else {
            panic!("Hénon–Heiles keeps two derived series")
        };
        dif[k] = a[k] - b[k];
        sum[k] = a[k] + b[k];
        let (dif, sum) = (&*dif, &*sum);
        let (mut s12, mut sd) = (a[0] * b[k], dif[0] * sum[k]);
        // Plain loops rather than `array::from_fn`: the compiler may outline an array builder,
        // and a call in this loop costs a `vzeroupper` and stalls store forwarding, a large
        // share of the 8-lane AVX-512 step (figures: docs/performance.md).
        let mut s1 = [T::splat(0.0); K];
        let mut s2 = [T::splat(0.0); K];
        for v in 0..K {
            s1[v] = b[0] * u[v][0][k] + a[0] * u[v][1][k];
            s2[v] = a[0] * u[v][0][k] - b[0] * u[v][1][k];
        }
        for j in 1..=k {
            s12 = a[j].mul_add(b[k - j], s12);
            sd = dif[j].mul_add(sum[k - j], sd);
            for v in 0..K {
                let (x, y) = (&u[v][0], &u[v][1]);
                s1[v] = b[j].mul_add(x[k - j], a[j].mul_add(y[k - j], s1[v]));
                s2[v] = a[j].mul_add(x[k - j], (-b[j]).mul_add(y[k - j], s2[v]));
            }
        }
        let two = T::splat(2.0);
        let mut hv = [[T::splat(0.0); 2]; K];
        for v in 0..K {
            let (x, y) = (&u[v][0], &u[v][1]);
            hv[v] = [two.mul_add(s1[v], x[k]), two.mul_add(s2[v], y[k])];
        }
        ([two.mul_add(s12, a[k]), b[k] + sd], hv)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::adaptive::stepping::Scalar;
    use crate::arith::dd::DoubleDouble;

    /// Hénon–Heiles' one-pass coefficients are the separate ones, bit for bit, in f64 and in
    /// double-double.
    #[test]
    fn one_pass_coefficients_equal_the_separate_ones() {
        fn check<T: Scalar + PartialEq + core::fmt::Debug>(from: impl Fn(f64) -> T) {
            let mut x = 0.3f64;
            let mut next = || {
                // A fixed, irregular sequence in (−1, 1).
                x = (x * 3.7 + 0.19).fract();
                from(2.0 * x - 1.0)
            };
            let q: [Series<T>; 2] = core::array::from_fn(|_| core::array::from_fn(|_| next()));
            let u: [[Series<T>; 2]; 3] = core::array::from_fn(|_| {
                core::array::from_fn(|_| core::array::from_fn(|_| next()))
            });
            let mut derived = [[T::splat(0.0); P_MAX + 1]; 2];
            assert_eq!(HenonHeiles.derived_series(), derived.len());
            for k in 0..12 {
                let (g, h) = HenonHeiles.all_coeffs(&q, &u, &mut derived, k);
                assert_eq!(g, HenonHeiles.grad_coeff(&q, k), "k = {k}");
                for v in 0..3 {
                    assert_eq!(h[v], HenonHeiles.hess_vec_coeff(&q, &u[v], k), "k = {k}");
                }
            }
        }
        check(|x| x);
        check(|x| DoubleDouble::from_f64(x) * DoubleDouble::from_f64(1.0 + x * 1e-9));
    }

    #[test]
    fn cauchy_product_multiplies_polynomials() {
        let mut a = [0.0; P_MAX + 1];
        let mut b = [0.0; P_MAX + 1];
        a[..3].copy_from_slice(&[1.0, 2.0, 3.0]);
        b[..2].copy_from_slice(&[4.0, 5.0]);
        // (1 + 2s + 3s²)(4 + 5s) = 4 + 13s + 22s² + 15s³
        let c: Vec<f64> = (0..5).map(|k| cauchy(&a, &b, k)).collect();
        assert_eq!(c, vec![4.0, 13.0, 22.0, 15.0, 0.0]);
    }
}
