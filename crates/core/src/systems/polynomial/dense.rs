//! Dense evaluation of a few polynomials in every monomial up to a degree, with the sizes known
//! at compile time: the monomials and the sums sit in registers and every index is a constant,
//! where the sparse [`Program`](super::program::Program) walks its terms in a loop. A kick of a
//! cubic potential in 2 or 3 degrees of freedom (Hénon–Heiles and its kin) goes this way; the
//! zero coefficients cost multiply-adds that a loop's overhead costs more than.

use super::Polynomial;
use crate::arith::real::Real;
use crate::systems::series::Series;

/// The monomials of degree ≤ D in N variables, graded: monomial 0 is 1, 1…N the coordinates,
/// and each later one is a coordinate times an earlier one. `M` is their number, C(N + D, D).
#[derive(Clone, Copy, Debug, PartialEq)]
struct Basis<const N: usize, const M: usize> {
    powers: [[u8; N]; M],
    /// Monomial i (i > N) = q[factor[i].0] · monomial factor[i].1.
    factor: [(usize, usize); M],
}

/// The graded basis, built at compile time so that its indices are constants in `eval`.
const fn basis<const N: usize, const M: usize>() -> Basis<N, M> {
    let mut powers = [[0u8; N]; M];
    let mut factor = [(0usize, 0usize); M];
    let mut len = 1;
    let mut k = 0;
    while k < N {
        powers[len][k] = 1;
        factor[len] = (k, 0);
        len += 1;
        k += 1;
    }
    // Monomials of the next degree: q_k times a monomial of this degree whose first nonzero
    // power is at k or later, so each arises once.
    let mut start = 1;
    while len < M {
        let end = len;
        let mut i = start;
        while i < end {
            let mut first = 0;
            while powers[i][first] == 0 {
                first += 1;
            }
            let mut k = 0;
            while k <= first && len < M {
                powers[len] = powers[i];
                powers[len][k] += 1;
                factor[len] = (k, i);
                len += 1;
                k += 1;
            }
            i += 1;
        }
        start = end;
    }
    Basis { powers, factor }
}

/// `O` polynomials of degree ≤ D in N variables as dense rows over the `M` monomials.
#[derive(Clone, Debug, PartialEq)]
pub(crate) struct Dense<const N: usize, const M: usize, const O: usize> {
    rows: [[f64; M]; O],
}

impl<const N: usize, const M: usize, const O: usize> Dense<N, M, O> {
    /// The basis in static memory: a reference, where an associated constant would be copied
    /// onto the stack at every evaluation.
    const BASIS: &'static Basis<N, M> = &basis::<N, M>();

    /// The rows of `polys`, or `None` when one has a term beyond the basis (or there are not
    /// `O` of them).
    pub fn new<'a>(polys: impl IntoIterator<Item = &'a Polynomial>) -> Option<Self> {
        let polys: Vec<&Polynomial> = polys.into_iter().collect();
        if polys.len() != O {
            return None;
        }
        let mut rows = [[0.0; M]; O];
        for (row, poly) in rows.iter_mut().zip(polys) {
            for (coeff, powers) in poly.terms() {
                let i = (0..M).find(|&i| {
                    Self::BASIS.powers[i]
                        .iter()
                        .zip(powers)
                        .all(|(&a, &b)| u32::from(a) == b)
                })?;
                row[i] = coeff;
            }
        }
        Some(Dense { rows })
    }

    /// The polynomials' values at `q`.
    #[inline(always)]
    pub fn eval<T: Real>(&self, q: &[T; N]) -> [T; O] {
        let mut m = [T::splat(1.0); M];
        for i in 1..M {
            let (k, lower) = Self::BASIS.factor[i];
            m[i] = if i <= N { q[k] } else { q[k] * m[lower] };
        }
        // Monomial by monomial, every output's sum side by side (each still adds its terms in
        // order). Output by output, the compiler vectorises across the outputs of one lane
        // and scatters the sums, several times slower than whole lanes at a time.
        let mut out = [T::splat(0.0); O];
        for o in 0..O {
            out[o] = T::splat(self.rows[o][0]);
        }
        for i in 1..M {
            for o in 0..O {
                out[o] = T::splat(self.rows[o][i]).mul_add(m[i], out[o]);
            }
        }
        out
    }
}

/// The kick and corrector terms of a cubic potential (degree ≤ 3), from V's derivatives alone:
/// ∇V as dense rows over the monomials of degree ≤ 2 (`M` of them), D²V's upper triangle (`S`
/// entries) over 1, q1…qN (`L` = N + 1), and D³V, which is constant. The corrector's potential
/// K = |∇V|² then follows by the chain rule, ∇K = 2 D²V ∇V and D²K = 2 (D²V D²V + Σ_i ∂_iV D³V_i),
/// instead of rows of K's own derivatives (degree 3 and 2: twice the monomials, most of their
/// coefficients zero), about half the work of a corrected kick.
#[derive(Clone, Debug, PartialEq)]
pub(crate) struct CubicKick<const N: usize, const M: usize, const L: usize, const S: usize> {
    grad: Dense<N, M, N>,
    hessian: Dense<N, L, S>,
    /// ∂³V/∂q_i∂q_j∂q_l at [i][j][l].
    third: [[[f64; N]; N]; N],
}

impl<const N: usize, const M: usize, const L: usize, const S: usize> CubicKick<N, M, L, S> {
    /// From ∇V's N polynomials, D²V's N² (by rows, symmetric) and D³V's N³ (i N² + j N + l);
    /// `None` unless the potential is at most cubic (D³V constant).
    pub fn new(grad: &[Polynomial], hessian: &[Polynomial], third: &[Polynomial]) -> Option<Self> {
        let upper = (0..N).flat_map(|i| (i..N).map(move |j| &hessian[i * N + j]));
        let mut constant = [[[0.0; N]; N]; N];
        for (at, t) in third.iter().enumerate() {
            if t.degree() > 0 {
                return None;
            }
            constant[at / (N * N)][(at / N) % N][at % N] = t.eval(&[0.0; N]);
        }
        Some(CubicKick {
            grad: Dense::new(grad)?,
            hessian: Dense::new(upper)?,
            third: constant,
        })
    }

    /// ∇V at `q`.
    #[inline(always)]
    pub fn grad<T: Real>(&self, q: &[T; N]) -> [T; N] {
        self.grad.eval(q)
    }

    /// D²V at `q`, the whole symmetric matrix.
    #[inline(always)]
    pub fn hessian<T: Real>(&self, q: &[T; N]) -> [[T; N]; N] {
        let upper = self.hessian.eval(q);
        let mut h = [[T::splat(0.0); N]; N];
        let mut at = 0;
        for i in 0..N {
            for j in i..N {
                h[i][j] = upper[at];
                h[j][i] = upper[at];
                at += 1;
            }
        }
        h
    }

    /// −b∇V + c∇K and −b D²V + c D²K at `q` (`None` stands for a zero coefficient).
    #[inline(always)]
    pub fn kick_terms<T: Real>(
        &self,
        q: &[T; N],
        b: Option<T>,
        c: Option<T>,
    ) -> ([T; N], [[T; N]; N]) {
        let zero = T::splat(0.0);
        let g = self.grad(q);
        let h = self.hessian(q);
        let mut force = [zero; N];
        let mut matrix = [[zero; N]; N];
        if let Some(b) = b {
            let nb = -b;
            for i in 0..N {
                force[i] = nb * g[i];
                for j in 0..N {
                    matrix[i][j] = nb * h[i][j];
                }
            }
        }
        if let Some(c) = c {
            let c2 = c + c;
            for i in 0..N {
                let mut hg = h[i][0] * g[0];
                for j in 1..N {
                    hg = h[i][j].mul_add(g[j], hg);
                }
                force[i] = c2.mul_add(hg, force[i]);
            }
            for j in 0..N {
                for l in j..N {
                    let mut s = h[j][0] * h[0][l];
                    for i in 1..N {
                        s = h[j][i].mul_add(h[i][l], s);
                    }
                    for i in 0..N {
                        s = T::splat(self.third[i][j][l]).mul_add(g[i], s);
                    }
                    matrix[j][l] = c2.mul_add(s, matrix[j][l]);
                    matrix[l][j] = matrix[j][l];
                }
            }
        }
        (force, matrix)
    }
}

/// The Taylor recursion of a cubic potential in 2 degrees of freedom with every size known at
/// compile time: ∇V is linear in the coordinates and in their three products q_a q_b, and D²V
/// is linear in the coordinates (D³V constant), so order k of ∇V and of D²V·u needs only the
/// Cauchy products q_a ⋆ q_b and q_a ⋆ u_j, all summed side by side in one pass (as the
/// hand-written Hénon–Heiles recursion sums its own), where the general plan walks its terms.
#[derive(Clone, Debug, PartialEq)]
pub(crate) struct PlaneCubicSeries {
    /// ∇V_i's constant term.
    grad_const: [f64; 2],
    /// ∇V_i's coefficient of q_a, at [i][a].
    grad_linear: [[f64; 2]; 2],
    /// ∇V_i's coefficients of q1², q1 q2, q2², at [i][p].
    grad_quadratic: [[f64; 3]; 2],
    /// D²V at q = 0, at [i][j].
    hessian_const: [[f64; 2]; 2],
    /// ∂³V/∂q_a∂q_i∂q_j at [a][i][j].
    third: [[[f64; 2]; 2]; 2],
}

impl PlaneCubicSeries {
    /// From ∇V's two polynomials; `None` unless V is at most cubic.
    pub fn new(grad: &[Polynomial]) -> Option<Self> {
        let mut series = PlaneCubicSeries {
            grad_const: [0.0; 2],
            grad_linear: [[0.0; 2]; 2],
            grad_quadratic: [[0.0; 3]; 2],
            hessian_const: [[0.0; 2]; 2],
            third: [[[0.0; 2]; 2]; 2],
        };
        for (i, g) in grad.iter().enumerate() {
            for (c, powers) in g.terms() {
                match powers {
                    [0, 0] => series.grad_const[i] = c,
                    [1, 0] => series.grad_linear[i][0] = c,
                    [0, 1] => series.grad_linear[i][1] = c,
                    [2, 0] => series.grad_quadratic[i][0] = c,
                    [1, 1] => series.grad_quadratic[i][1] = c,
                    [0, 2] => series.grad_quadratic[i][2] = c,
                    _ => return None,
                }
            }
        }
        for i in 0..2 {
            for j in 0..2 {
                series.hessian_const[i][j] = series.grad_linear[i][j];
            }
            // ∂_j of q1², q1 q2, q2² is (2 q1, q2, 0) for j = 1 and (0, q1, 2 q2) for j = 2;
            // ∂_a of that is constant.
            let [c11, c12, c22] = series.grad_quadratic[i];
            series.third[0][i][0] = 2.0 * c11;
            series.third[1][i][0] = c12;
            series.third[0][i][1] = c12;
            series.third[1][i][1] = 2.0 * c22;
        }
        Some(series)
    }

    /// Coefficient k of ∇V(q(t)) and of D²V(q(t))·u_v(t) for every deviation vector, from the
    /// coefficients 0..=k of q and u.
    #[inline(always)]
    pub fn all_coeffs<T: Real, const K: usize>(
        &self,
        q: &[Series<T>; 2],
        u: [&[Series<T>; 2]; K],
        k: usize,
    ) -> ([T; 2], [[T; 2]; K]) {
        let (a, b) = (&q[0], &q[1]);
        let mut products = [a[0] * a[k], a[0] * b[k], b[0] * b[k]];
        // mixed[v][c][j] = (q_c ⋆ u_vj)[k]; plain loops, not `array::from_fn` (an outlined
        // call in the recursion stalls store forwarding).
        let mut mixed = [[[T::splat(0.0); 2]; 2]; K];
        for v in 0..K {
            for c in 0..2 {
                for j in 0..2 {
                    mixed[v][c][j] = q[c][0] * u[v][j][k];
                }
            }
        }
        for m in 1..=k {
            products[0] = a[m].mul_add(a[k - m], products[0]);
            products[1] = a[m].mul_add(b[k - m], products[1]);
            products[2] = b[m].mul_add(b[k - m], products[2]);
            for v in 0..K {
                for c in 0..2 {
                    for j in 0..2 {
                        mixed[v][c][j] = q[c][m].mul_add(u[v][j][k - m], mixed[v][c][j]);
                    }
                }
            }
        }
        let mut grad = [T::splat(0.0); 2];
        for i in 0..2 {
            let mut g = T::splat(if k == 0 { self.grad_const[i] } else { 0.0 });
            for c in 0..2 {
                g = T::splat(self.grad_linear[i][c]).mul_add(q[c][k], g);
            }
            for p in 0..3 {
                g = T::splat(self.grad_quadratic[i][p]).mul_add(products[p], g);
            }
            grad[i] = g;
        }
        let mut hv = [[T::splat(0.0); 2]; K];
        for v in 0..K {
            for i in 0..2 {
                let mut h = T::splat(self.hessian_const[i][0]) * u[v][0][k];
                h = T::splat(self.hessian_const[i][1]).mul_add(u[v][1][k], h);
                for c in 0..2 {
                    for j in 0..2 {
                        h = T::splat(self.third[c][i][j]).mul_add(mixed[v][c][j], h);
                    }
                }
                hv[v][i] = h;
            }
        }
        (grad, hv)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_basis_holds_every_monomial_once_each_from_an_earlier_one() {
        let b = basis::<3, 20>();
        let mut seen = std::collections::HashSet::new();
        for i in 0..20 {
            assert!(seen.insert(b.powers[i]), "{:?} twice", b.powers[i]);
            let degree: u8 = b.powers[i].iter().sum();
            assert!(degree <= 3);
            if i > 3 {
                let (k, lower) = b.factor[i];
                let mut want = b.powers[lower];
                want[k] += 1;
                assert_eq!(want, b.powers[i]);
                assert!(lower < i);
            }
        }
        assert_eq!(basis::<2, 10>().powers[9], [0, 3]);
    }

    #[test]
    fn dense_rows_evaluate_their_polynomials() {
        let texts = ["1 + q1 - 2*q2*q3 + q1^3", "q3^3 - 0.5*q1*q2*q3", "7"];
        let polys: Vec<Polynomial> = texts
            .iter()
            .map(|t| Polynomial::parse(t, 3).unwrap())
            .collect();
        let dense = Dense::<3, 20, 3>::new(&polys).unwrap();
        let q = [0.3, -1.2, 0.7];
        for (p, got) in polys.iter().zip(dense.eval(&q)) {
            let want = p.eval(&q);
            assert!(
                (got - want).abs() <= 1e-14 * want.abs().max(1.0),
                "{got} {want}"
            );
        }
        let quartic = Polynomial::parse("q1^4", 3).unwrap();
        assert!(Dense::<3, 20, 1>::new([&quartic]).is_none());
    }

    /// A cubic's kick and corrector terms through the chain rule equal those of K = |∇V|²
    /// differentiated exactly; a quartic is refused.
    #[test]
    fn a_cubics_kick_terms_follow_from_its_derivatives() {
        fn check<const N: usize, const M: usize, const L: usize, const S: usize>(text: &str) {
            let v = Polynomial::parse(text, N).unwrap();
            let grad = Polynomial::derivatives(&[v]);
            let hessian = Polynomial::derivatives(&grad);
            let third = Polynomial::derivatives(&hessian);
            let mut k = Polynomial::constant(N, 0.0);
            for g in &grad {
                k = k.add(&g.mul(g));
            }
            let kick = CubicKick::<N, M, L, S>::new(&grad, &hessian, &third).unwrap();
            let q: [f64; N] = core::array::from_fn(|i| 0.37 - 0.29 * i as f64);
            let (b, c) = (0.7, -0.013);
            let (force, matrix) = kick.kick_terms(&q, Some(b), Some(c));
            for i in 0..N {
                let want = -b * grad[i].eval(&q) + c * k.derivative(i).eval(&q);
                assert!(
                    (force[i] - want).abs() < 1e-14,
                    "{text}: {} {want}",
                    force[i]
                );
                for j in 0..N {
                    let want = -b * hessian[i * N + j].eval(&q)
                        + c * k.derivative(i).derivative(j).eval(&q);
                    assert!((matrix[i][j] - want).abs() < 1e-14, "{text}: {i}{j}");
                }
            }
            let (plain, _) = kick.kick_terms(&q, Some(b), None);
            assert!((plain[0] + b * grad[0].eval(&q)).abs() < 1e-15);
        }
        check::<2, 6, 3, 3>("(q1^2 + q2^2)/2 + q1^2*q2 - q2^3/3 + 0.3*q1*q2^2");
        check::<3, 10, 4, 6>("(q1^2 + 2*q2^2 + 3*q3^2)/2 + q1^2*q2 + q1^2*q3 - 0.4*q1*q2*q3");
        let quartic = Polynomial::parse("q1^4 + q2^2", 2).unwrap();
        let grad = Polynomial::derivatives(&[quartic]);
        let hessian = Polynomial::derivatives(&grad);
        let third = Polynomial::derivatives(&hessian);
        assert!(CubicKick::<2, 6, 3, 3>::new(&grad, &hessian, &third).is_none());
    }
}
