//! Hamiltonians of the form H = ½|p|² + V(q) with N degrees of freedom.

use crate::arith::real::{dot, Real};

/// A separable Hamiltonian H(q, p) = ½|p|² + V(q) with `N` degrees of freedom.
///
/// The integrators need V's gradient and its Hessian applied to a vector (the kick and its
/// tangent map), and the corrector of Laskar & Robutel needs K = |∇V|² through ∇K and D²K·u.
/// ∇K = 2 D²V ∇V and D²K·u = 2 [D²V (D²V u) + D³V(∇V, u, ·)], so an implementation supplies V,
/// ∇V, D²V·u and the third-derivative contraction D³V(w, u, ·); it may override the corrector
/// terms with closed forms.
///
/// All methods are generic over [`Real`] so one formula serves the scalar and the batched
/// steppers, bit for bit.
pub trait Hamiltonian<const N: usize>: Send + Sync {
    /// A short name for reports (`henon-heiles`).
    fn name(&self) -> &'static str;

    /// V(q).
    fn potential<T: Real>(&self, q: &[T; N]) -> T;

    /// ∇V(q).
    fn grad<T: Real>(&self, q: &[T; N]) -> [T; N];

    /// D²V(q)·u.
    fn hess_vec<T: Real>(&self, q: &[T; N], u: &[T; N]) -> [T; N];

    /// D³V(q)(w, u, ·): the vector with components Σ_jk ∂³V/∂q_i∂q_j∂q_k w_j u_k.
    fn third_vec<T: Real>(&self, q: &[T; N], w: &[T; N], u: &[T; N]) -> [T; N];

    /// ∇K(q) with K = |∇V|², the corrector's force.
    #[inline(always)]
    fn corrector_grad<T: Real>(&self, q: &[T; N]) -> [T; N] {
        let g = self.grad(q);
        let hg = self.hess_vec(q, &g);
        core::array::from_fn(|i| T::splat(2.0) * hg[i])
    }

    /// D²K(q)·u with K = |∇V|², the corrector's tangent map.
    #[inline(always)]
    fn corrector_hess_vec<T: Real>(&self, q: &[T; N], u: &[T; N]) -> [T; N] {
        let g = self.grad(q);
        let hu = self.hess_vec(q, u);
        let hhu = self.hess_vec(q, &hu);
        let tgu = self.third_vec(q, &g, u);
        core::array::from_fn(|i| T::splat(2.0) * (hhu[i] + tgu[i]))
    }

    /// The Hessian D²V(q) as rows. The default builds it from [`Hamiltonian::hess_vec`]; small
    /// systems override it with a closed form, which the kicks use to apply D²V to several
    /// deviation vectors at the cost of one evaluation.
    #[inline(always)]
    fn hessian<T: Real>(&self, q: &[T; N]) -> [[T; N]; N] {
        let cols: [[T; N]; N] = core::array::from_fn(|j| {
            let e = core::array::from_fn(|i| T::splat(if i == j { 1.0 } else { 0.0 }));
            self.hess_vec(q, &e)
        });
        core::array::from_fn(|i| core::array::from_fn(|j| cols[j][i]))
    }

    /// The Hessian D²K(q) of K = |∇V|², as rows (default from [`Hamiltonian::corrector_hess_vec`]).
    #[inline(always)]
    fn corrector_hessian<T: Real>(&self, q: &[T; N]) -> [[T; N]; N] {
        let cols: [[T; N]; N] = core::array::from_fn(|j| {
            let e = core::array::from_fn(|i| T::splat(if i == j { 1.0 } else { 0.0 }));
            self.corrector_hess_vec(q, &e)
        });
        core::array::from_fn(|i| core::array::from_fn(|j| cols[j][i]))
    }

    /// What a kick by `b` combined with a corrector by `c` does at q (`None` stands for a zero
    /// coefficient, so the caller's static knowledge of which parts exist removes the rest):
    /// the momentum change −b∇V + c∇K and its Jacobian −b D²V + c D²K, which the tangent map
    /// applies to every deviation vector. The default composes [`Hamiltonian::grad`],
    /// [`Hamiltonian::hessian`] and the corrector terms; a system may override it with a fused
    /// closed form, which matters because this is the bulk of a tangent-map step's arithmetic.
    #[inline(always)]
    fn kick_terms<T: Real>(&self, q: &[T; N], b: Option<T>, c: Option<T>) -> KickTerms<T, N> {
        KickTerms::compose(
            b,
            || (self.grad(q), self.hessian(q)),
            c,
            || (self.corrector_grad(q), self.corrector_hessian(q)),
        )
    }

    /// Distance from the origin beyond which an orbit counts as escaped. Infinite when every
    /// energy surface is bounded.
    fn escape_radius(&self) -> f64 {
        f64::INFINITY
    }

    /// Distance from the origin within which an orbit is inside the potential well: an energy
    /// error past the limit there is the integration's fault (`energy-drift`); beyond it, on
    /// the way out through a channel, the orbit goes on until it escapes or comes back.
    /// Infinite when every energy surface is bounded.
    fn well_radius(&self) -> f64 {
        f64::INFINITY
    }

    /// The energy above which orbits can leave the potential well, if there is one.
    fn escape_energy(&self) -> Option<f64> {
        None
    }

    /// The squared radius beyond which an orbit of energy `h0` is on its way out of the well
    /// ([`Hamiltonian::well_radius`]), with `escape_radius` the radius at which it counts as
    /// escaped: infinite (never) below the escape energy, where only a blown-up integration
    /// leaves the well, and when no escape radius is set.
    fn way_out_r2(&self, h0: f64, escape_radius: f64) -> f64 {
        let can_escape = self.escape_energy().is_some_and(|e| h0 > e) && escape_radius.is_finite();
        if can_escape {
            self.well_radius() * self.well_radius()
        } else {
            f64::INFINITY
        }
    }

    /// Upper bounds of V's derivatives and the corrector's over the ball |q| ≤ r, or `None`
    /// where the system gives none (the batched driver then screens every step; see
    /// [`crate::tangent_map::batch`]'s quiet windows, which rest on these bounds).
    fn derivative_bounds(&self, _r: f64) -> Option<DerivativeBounds> {
        None
    }

    /// H(q, p).
    #[inline(always)]
    fn energy<T: Real>(&self, q: &[T; N], p: &[T; N]) -> T {
        T::splat(0.5) * dot(p, p) + self.potential(q)
    }
}

/// A kick's momentum change and its Jacobian, formed once per kick and applied to the orbit
/// and to every deviation vector (see [`Hamiltonian::kick_terms`]).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct KickTerms<T, const N: usize> {
    /// Added to p.
    pub force: [T; N],
    /// Its Jacobian: δp gains matrix·δq.
    pub matrix: [[T; N]; N],
}

impl<T: Real, const N: usize> KickTerms<T, N> {
    /// −b∇V + c∇K and −b D²V + c D²K from (∇V, D²V) and (∇K, D²K), each pair asked for only
    /// when its coefficient is present (`None` stands for zero).
    #[inline(always)]
    pub fn compose(
        b: Option<T>,
        plain: impl FnOnce() -> ([T; N], [[T; N]; N]),
        c: Option<T>,
        corrector: impl FnOnce() -> ([T; N], [[T; N]; N]),
    ) -> Self {
        let zero = T::splat(0.0);
        let mut force = [zero; N];
        let mut matrix = [[zero; N]; N];
        if let Some(b) = b {
            let nb = -b;
            let (g, h) = plain();
            force = core::array::from_fn(|i| nb * g[i]);
            matrix = core::array::from_fn(|i| core::array::from_fn(|j| nb * h[i][j]));
        }
        if let Some(c) = c {
            let (gk, hk) = corrector();
            force = core::array::from_fn(|i| gk[i].mul_add(c, force[i]));
            matrix = core::array::from_fn(|i| {
                core::array::from_fn(|j| hk[i][j].mul_add(c, matrix[i][j]))
            });
        }
        KickTerms { force, matrix }
    }
}

/// Suprema over a ball |q| ≤ r (Euclidean norms; spectral norms of the matrices).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct DerivativeBounds {
    /// |∇V|.
    pub grad: f64,
    /// ‖D²V‖.
    pub hessian: f64,
    /// |∇K| with K = |∇V|², the corrector's potential.
    pub corrector_grad: f64,
    /// ‖D²K‖.
    pub corrector_hessian: f64,
}

/// The Hénon–Heiles system: V = ½(q1² + q2²) + q1²q2 − q2³/3. Escape energy 1/6.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct HenonHeiles;

impl Hamiltonian<2> for HenonHeiles {
    fn name(&self) -> &'static str {
        "henon-heiles"
    }

    #[inline(always)]
    fn potential<T: Real>(&self, q: &[T; 2]) -> T {
        let [x, y] = *q;
        let half = T::splat(0.5);
        half * (x * x + y * y) + x * x * y - y * y * y * T::ratio(1.0, 3.0)
    }

    #[inline(always)]
    fn grad<T: Real>(&self, q: &[T; 2]) -> [T; 2] {
        let [x, y] = *q;
        // ∂V/∂x = x(1 + 2y), ∂V/∂y = y + x² − y² = y + (x − y)(x + y)
        [
            x * T::splat(2.0).mul_add(y, T::splat(1.0)),
            (x - y).mul_add(x + y, y),
        ]
    }

    #[inline(always)]
    fn hess_vec<T: Real>(&self, q: &[T; 2], u: &[T; 2]) -> [T; 2] {
        let [x, y] = *q;
        let two = T::splat(2.0);
        let one = T::splat(1.0);
        let h11 = two.mul_add(y, one);
        let h22 = (-two).mul_add(y, one);
        let h12 = two * x;
        [h11.mul_add(u[0], h12 * u[1]), h12.mul_add(u[0], h22 * u[1])]
    }

    #[inline(always)]
    fn third_vec<T: Real>(&self, _q: &[T; 2], w: &[T; 2], u: &[T; 2]) -> [T; 2] {
        // The only non-zero third derivatives: V_112 = 2, V_222 = −2.
        let two = T::splat(2.0);
        [
            two * w[0].mul_add(u[1], w[1] * u[0]),
            two * w[0].mul_add(u[0], -(w[1] * u[1])),
        ]
    }

    #[inline(always)]
    fn hessian<T: Real>(&self, q: &[T; 2]) -> [[T; 2]; 2] {
        let [x, y] = *q;
        let (one, two) = (T::splat(1.0), T::splat(2.0));
        let h12 = two * x;
        [[two.mul_add(y, one), h12], [h12, (-two).mul_add(y, one)]]
    }

    #[inline(always)]
    fn corrector_grad<T: Real>(&self, q: &[T; 2]) -> [T; 2] {
        // ∇K = (2x(1 + 2x² + 6y + 2y²), 2(y + 3x² − 3y² + 2x²y + 2y³)).
        let [x, y] = *q;
        let c = T::splat;
        let (xx, yy) = (x * x, y * y);
        let a = c(2.0).mul_add(xx, c(2.0).mul_add(yy, c(6.0).mul_add(y, c(1.0))));
        let b = xx.mul_add(
            c(3.0) + c(2.0) * y,
            yy.mul_add(c(2.0).mul_add(y, c(-3.0)), y),
        );
        [c(2.0) * x * a, c(2.0) * b]
    }

    #[inline(always)]
    fn corrector_hessian<T: Real>(&self, q: &[T; 2]) -> [[T; 2]; 2] {
        // D²K = [[2(1 + 6x² + 6y + 2y²), 4x(3 + 2y)], [4x(3 + 2y), 2(1 + 2x² − 6y + 6y²)]].
        let [x, y] = *q;
        let c = T::splat;
        let (xx, yy) = (x * x, y * y);
        let k11 = c(12.0).mul_add(xx, c(4.0).mul_add(yy, c(12.0).mul_add(y, c(2.0))));
        let k22 = c(4.0).mul_add(xx, c(12.0).mul_add(yy, c(-12.0).mul_add(y, c(2.0))));
        let k12 = c(4.0) * x * c(2.0).mul_add(y, c(3.0));
        [[k11, k12], [k12, k22]]
    }

    /// The fused closed form of −b∇V + c∇K and −b D²V + c D²K. With x = q1, y = q2,
    /// r = x² + y², d = x² − y², α = 2c − b, β = 12c − 2b, γ = 4c (from the closed forms of ∇K
    /// and D²K checked in the tests below):
    /// F = (x(α + βy + γr), αy + (6c − b)d + γyr),
    /// M = [[α + βy + γr + 2γx², x(β + 2γy)], [·, α − βy + γr + 2γy²]].
    /// About 17 operations against 39 for the composition of the separate terms; a plain kick
    /// (no corrector) takes the same shape with c = 0 and fewer terms.
    #[inline(always)]
    fn kick_terms<T: Real>(&self, q: &[T; 2], b: Option<T>, c: Option<T>) -> KickTerms<T, 2> {
        let [x, y] = *q;
        match (b, c) {
            (Some(b), None) => {
                let nb = -b;
                let nb2 = nb + nb;
                let m11 = nb2.mul_add(y, nb);
                let m22 = (-nb2).mul_add(y, nb);
                let m12 = nb2 * x;
                KickTerms {
                    force: [x * m11, nb * (x - y).mul_add(x + y, y)],
                    matrix: [[m11, m12], [m12, m22]],
                }
            }
            (b, Some(c)) => {
                let b = b.unwrap_or(T::splat(0.0));
                let two = T::splat(2.0);
                let alpha = c.mul_add(two, -b);
                let beta = T::splat(12.0).mul_add(c, -(b + b));
                let gamma = T::splat(4.0) * c;
                let gamma2 = T::splat(8.0) * c;
                let delta = T::splat(6.0).mul_add(c, -b);
                let (xx, yy) = (x * x, y * y);
                let (r, d) = (xx + yy, xx - yy);
                let w = gamma.mul_add(r, beta.mul_add(y, alpha));
                let m11 = gamma2.mul_add(xx, w);
                let m22 = gamma2.mul_add(yy, gamma.mul_add(r, (-beta).mul_add(y, alpha)));
                let m12 = x * gamma2.mul_add(y, beta);
                KickTerms {
                    force: [x * w, (gamma * y).mul_add(r, delta.mul_add(d, alpha * y))],
                    matrix: [[m11, m12], [m12, m22]],
                }
            }
            (None, None) => KickTerms {
                force: [T::splat(0.0); 2],
                matrix: [[T::splat(0.0); 2]; 2],
            },
        }
    }

    fn well_radius(&self) -> f64 {
        // The saddles sit at distance 1 and the well's triangle lies within that circle.
        1.0
    }

    fn escape_radius(&self) -> f64 {
        // The saddles sit at distance 1; beyond radius 2 the cubic term wins for good and the
        // orbit runs off to infinity in finite time.
        2.0
    }

    /// With ρ = |q|: ∇V = q + (2q1q2, q1² − q2²), and the second part has length ρ², so
    /// |∇V| ≤ ρ + ρ². D²V = I + 2[[q2, q1], [q1, −q2]] has eigenvalues 1 ± 2ρ. The only third
    /// derivatives are V_112 = 2 and V_222 = −2, so D³V(w, ·, ·) = 2[[w2, w1], [w1, −w2]] has
    /// norm 2|w|. Then ∇K = 2 D²V ∇V and D²K = 2(D²V² + D³V(∇V, ·, ·)).
    fn derivative_bounds(&self, r: f64) -> Option<DerivativeBounds> {
        let (grad, hessian) = (r + r * r, 1.0 + 2.0 * r);
        Some(DerivativeBounds {
            grad,
            hessian,
            corrector_grad: 2.0 * hessian * grad,
            corrector_hessian: 2.0 * (hessian * hessian + 2.0 * grad),
        })
    }

    fn escape_energy(&self) -> Option<f64> {
        Some(1.0 / 6.0)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Explicit formulas for ∇K and D²K (checked with sympy), written apart from the code
    /// under test.
    fn grad_k_note(q1: f64, q2: f64) -> [f64; 2] {
        [
            2.0 * q1 * (1.0 + 2.0 * q1 * q1 + 6.0 * q2 + 2.0 * q2 * q2),
            2.0 * (q2 + 3.0 * q1 * q1 - 3.0 * q2 * q2 + 2.0 * q1 * q1 * q2 + 2.0 * q2 * q2 * q2),
        ]
    }
    fn hess_k_note(q1: f64, q2: f64) -> [[f64; 2]; 2] {
        let off = 4.0 * q1 * (3.0 + 2.0 * q2);
        [
            [2.0 * (1.0 + 6.0 * q1 * q1 + 6.0 * q2 + 2.0 * q2 * q2), off],
            [off, 2.0 * (1.0 + 2.0 * q1 * q1 - 6.0 * q2 + 6.0 * q2 * q2)],
        ]
    }

    const POINTS: [[f64; 2]; 5] = [
        [0.0, 0.0],
        [0.3, -0.2],
        [-0.41, 0.17],
        [0.05, 0.6],
        [1.3, -0.9],
    ];

    /// The bounds hold at points all over and on the edge of balls of several radii: the
    /// norms of ∇V, D²V, ∇K and D²K (2×2 symmetric: the largest |eigenvalue|) never exceed
    /// them, and on the edge the gradient's and Hessian's bounds are reached to 1 %.
    #[test]
    fn derivative_bounds_hold_over_the_ball() {
        let h = HenonHeiles;
        let spectral = |m: [[f64; 2]; 2]| {
            let (mean, d) = ((m[0][0] + m[1][1]) / 2.0, (m[0][0] - m[1][1]) / 2.0);
            let rad = (d * d + m[0][1] * m[0][1]).sqrt();
            (mean + rad).abs().max((mean - rad).abs())
        };
        let norm = |v: [f64; 2]| v[0].hypot(v[1]);
        for r in [0.1, 0.7, 1.0, 2.0] {
            let b = h.derivative_bounds(r).unwrap();
            let mut reached = [0.0f64; 2];
            for i in 0..720 {
                let angle = i as f64 * core::f64::consts::PI / 360.0;
                for frac in [1.0, 0.9, 0.5, 0.1] {
                    let q = [r * frac * angle.cos(), r * frac * angle.sin()];
                    let seen = [
                        norm(h.grad(&q)),
                        spectral(h.hessian(&q)),
                        norm(h.corrector_grad(&q)),
                        spectral(h.corrector_hessian(&q)),
                    ];
                    let bound = [b.grad, b.hessian, b.corrector_grad, b.corrector_hessian];
                    for k in 0..4 {
                        assert!(seen[k] <= bound[k] * (1.0 + 1e-12), "r {r} q {q:?} {k}");
                    }
                    reached[0] = reached[0].max(seen[0] / b.grad);
                    reached[1] = reached[1].max(seen[1] / b.hessian);
                }
            }
            assert!(reached.iter().all(|&x| x > 0.99), "r {r}: {reached:?}");
        }
    }

    #[test]
    fn gradient_matches_finite_differences_of_potential() {
        let h = HenonHeiles;
        for q in POINTS {
            let g = h.grad(&q);
            for i in 0..2 {
                let e = 1e-5;
                let mut qp = q;
                let mut qm = q;
                qp[i] += e;
                qm[i] -= e;
                let fd = (h.potential(&qp) - h.potential(&qm)) / (2.0 * e);
                assert!((fd - g[i]).abs() < 1e-9, "q={q:?} i={i} fd={fd} g={}", g[i]);
            }
        }
    }

    #[test]
    fn hessian_and_third_derivative_match_finite_differences() {
        let h = HenonHeiles;
        let u = [0.7, -1.3];
        let w = [-0.4, 0.9];
        for q in POINTS {
            let e = 1e-6;
            let qp = [q[0] + e * u[0], q[1] + e * u[1]];
            let qm = [q[0] - e * u[0], q[1] - e * u[1]];
            let (gp, gm) = (h.grad(&qp), h.grad(&qm));
            let hu = h.hess_vec(&q, &u);
            let (hwp, hwm) = (h.hess_vec(&qp, &w), h.hess_vec(&qm, &w));
            let tw = h.third_vec(&q, &w, &u);
            for i in 0..2 {
                assert!(((gp[i] - gm[i]) / (2.0 * e) - hu[i]).abs() < 1e-8);
                assert!(((hwp[i] - hwm[i]) / (2.0 * e) - tw[i]).abs() < 1e-8);
            }
        }
    }

    #[test]
    fn corrector_terms_equal_the_closed_forms_of_the_research_note() {
        let h = HenonHeiles;
        for q in POINTS {
            let gk = h.corrector_grad(&q);
            let note = grad_k_note(q[0], q[1]);
            let hk = hess_k_note(q[0], q[1]);
            let hk_closed = h.corrector_hessian(&q);
            for i in 0..2 {
                for j in 0..2 {
                    assert!((hk_closed[i][j] - hk[i][j]).abs() < 1e-12 * (1.0 + hk[i][j].abs()));
                }
            }
            for i in 0..2 {
                assert!((gk[i] - note[i]).abs() < 1e-12 * (1.0 + note[i].abs()));
            }
            for (col, u) in [[1.0, 0.0], [0.0, 1.0]].iter().enumerate() {
                let hku = h.corrector_hess_vec(&q, u);
                for (row, hk_row) in hk.iter().enumerate() {
                    let want = hk_row[col];
                    assert!((hku[row] - want).abs() < 1e-12 * (1.0 + want.abs()));
                }
            }
        }
    }

    /// The closed forms agree with the generic defaults built from hess_vec and third_vec.
    #[test]
    fn closed_forms_equal_the_generic_defaults() {
        struct Generic;
        impl Hamiltonian<2> for Generic {
            fn name(&self) -> &'static str {
                "generic"
            }
            fn potential<T: Real>(&self, q: &[T; 2]) -> T {
                HenonHeiles.potential(q)
            }
            fn grad<T: Real>(&self, q: &[T; 2]) -> [T; 2] {
                HenonHeiles.grad(q)
            }
            fn hess_vec<T: Real>(&self, q: &[T; 2], u: &[T; 2]) -> [T; 2] {
                HenonHeiles.hess_vec(q, u)
            }
            fn third_vec<T: Real>(&self, q: &[T; 2], w: &[T; 2], u: &[T; 2]) -> [T; 2] {
                HenonHeiles.third_vec(q, w, u)
            }
        }
        let h = HenonHeiles;
        // The fused kick terms against the default composition of the separate terms, for a
        // plain kick, a plain corrector, both (signs and sizes as in SBAB2C at τ = 0.5 and
        // beyond), and neither.
        let coeffs = [
            (Some(0.25), None),
            (None, Some(-0.0017)),
            (Some(0.105662), Some(-0.0017361)),
            (Some(-1.3), Some(0.8)),
            (None, None),
        ];
        for q in POINTS {
            for (b, c) in coeffs {
                let (fused, composed) = (h.kick_terms(&q, b, c), Generic.kick_terms(&q, b, c));
                let close = |x: f64, y: f64| (x - y).abs() <= 4e-15 * (1.0 + y.abs());
                for i in 0..2 {
                    assert!(
                        close(fused.force[i], composed.force[i]),
                        "{q:?} {b:?} {c:?}"
                    );
                    for j in 0..2 {
                        let (x, y) = (fused.matrix[i][j], composed.matrix[i][j]);
                        assert!(close(x, y), "{q:?} {b:?} {c:?} M{i}{j}: {x} vs {y}");
                    }
                }
            }
        }
        for q in POINTS {
            let (a, b) = (h.corrector_grad(&q), Generic.corrector_grad(&q));
            let (ha, hb) = (h.hessian(&q), Generic.hessian(&q));
            let (ka, kb) = (h.corrector_hessian(&q), Generic.corrector_hessian(&q));
            for i in 0..2 {
                assert!((a[i] - b[i]).abs() < 1e-13 * (1.0 + b[i].abs()));
                for j in 0..2 {
                    assert!((ha[i][j] - hb[i][j]).abs() < 1e-15);
                    assert!((ka[i][j] - kb[i][j]).abs() < 1e-13 * (1.0 + kb[i][j].abs()));
                }
            }
        }
    }

    #[test]
    fn saddles_sit_at_the_escape_energy() {
        let h = HenonHeiles;
        let s3 = 3f64.sqrt() / 2.0;
        for q in [[0.0, 1.0], [s3, -0.5], [-s3, -0.5]] {
            let g = h.grad(&q);
            assert!(g[0].abs() < 1e-15 && g[1].abs() < 1e-15);
            assert!((h.potential(&q) - 1.0 / 6.0).abs() < 1e-15);
        }
    }
}
