//! The system H = ½|p|² + V(q) of a polynomial potential: every derivative the integrators ask
//! for derived once, exactly, and compiled ([`Program`]); the Taylor recursion's Cauchy
//! products planned from the same polynomials.

use super::dense::{CubicKick, PlaneCubicSeries};
use super::program::{Factor, Monomials, Program};
use super::Polynomial;
use crate::arith::real::Real;
use crate::systems::hamiltonian::{DerivativeBounds, Hamiltonian, KickTerms};
use crate::systems::series::{Series, TaylorSeries, P_MAX};

/// The system of a polynomial potential in `N` degrees of freedom.
#[derive(Clone, Debug, PartialEq)]
pub struct PolynomialSystem<const N: usize> {
    potential: Polynomial,
    /// V.
    value: Program,
    /// ∇V.
    grad: Program,
    /// D²V by rows.
    hessian: Program,
    /// ∇V, then D²V by rows: a kick's terms from one set of monomials.
    kick: Program,
    /// ∇K, then D²K by rows, with K = |∇V|² (the corrector's potential).
    corrector: Program,
    /// ∂³V/∂q_i∂q_j∂q_k at i N² + j N + k.
    third: Program,
    /// ∇V, D²V, ∇K, D²K and D³V, whose bounds term by term bound the derivatives (see
    /// [`Hamiltonian::derivative_bounds`]).
    bounds: [Vec<Polynomial>; 5],
    /// A cubic potential's kick and corrector terms from dense rows of its derivatives
    /// ([`CubicKick`]), in 2 and in 3 degrees of freedom.
    plane_cubic: Option<CubicKick<2, 6, 3, 3>>,
    space_cubic: Option<CubicKick<3, 10, 4, 6>>,
    taylor: TaylorPlan,
    /// A cubic potential's Taylor recursion in 2 degrees of freedom, sizes fixed at compile
    /// time ([`PlaneCubicSeries`]).
    plane_series: Option<PlaneCubicSeries>,
}

impl<const N: usize> PolynomialSystem<N> {
    /// The system of `potential`, a polynomial in q1…qN.
    pub fn new(potential: Polynomial) -> Self {
        assert_eq!(potential.dof(), N, "a potential in {N} coordinates");
        let grad = Polynomial::derivatives(core::slice::from_ref(&potential));
        let hessian = Polynomial::derivatives(&grad);
        let third = Polynomial::derivatives(&hessian);
        let mut k = Polynomial::constant(N, 0.0);
        for g in &grad {
            k = k.add(&g.mul(g));
        }
        let k_grad = Polynomial::derivatives(core::slice::from_ref(&k));
        let k_hessian = Polynomial::derivatives(&k_grad);
        PolynomialSystem {
            plane_cubic: (N == 2)
                .then(|| CubicKick::new(&grad, &hessian, &third))
                .flatten(),
            space_cubic: (N == 3)
                .then(|| CubicKick::new(&grad, &hessian, &third))
                .flatten(),
            value: Program::new(N, [&potential]),
            grad: Program::new(N, &grad),
            hessian: Program::new(N, &hessian),
            kick: Program::new(N, grad.iter().chain(&hessian)),
            corrector: Program::new(N, k_grad.iter().chain(&k_hessian)),
            third: Program::new(N, &third),
            taylor: TaylorPlan::new(&grad, &hessian),
            plane_series: (N == 2).then(|| PlaneCubicSeries::new(&grad)).flatten(),
            bounds: [grad, hessian, k_grad, k_hessian, third],
            potential,
        }
    }

    /// The potential V.
    pub fn potential_polynomial(&self) -> &Polynomial {
        &self.potential
    }

    /// A vector and a matrix (by rows) from a program whose outputs are N, then N².
    #[inline(always)]
    fn vector_and_matrix<T: Real>(program: &Program, q: &[T; N]) -> ([T; N], [[T; N]; N]) {
        let zero = T::splat(0.0);
        let (mut v, mut m) = ([zero; N], [[zero; N]; N]);
        program.eval(q, |o, x| {
            if o < N {
                v[o] = x;
            } else {
                m[(o - N) / N][(o - N) % N] = x;
            }
        });
        (v, m)
    }
}

/// A vector and matrix of M degrees of freedom as those of N, where M = N (the callers check).
#[inline(always)]
#[allow(clippy::type_complexity)]
fn widen<T: Real, const M: usize, const N: usize>(
    (v, m): ([T; M], [[T; M]; M]),
) -> ([T; N], [[T; N]; N]) {
    let mut force = [T::splat(0.0); N];
    let mut matrix = [[T::splat(0.0); N]; N];
    for i in 0..N {
        force[i] = v[i];
        for j in 0..N {
            matrix[i][j] = m[i][j];
        }
    }
    (force, matrix)
}

/// A bound over the ball |q| ≤ r of the Euclidean norm of the vector the polynomials form (and
/// so of the spectral norm of a matrix, through its Frobenius norm): √(Σ_p b_p²) with
/// b_p = Σ_t |c_t| r^{deg t} over p's terms, which bounds |p| there (every |q_i| ≤ r).
fn norm_bound(polys: &[Polynomial], r: f64) -> f64 {
    let mut sum2 = 0.0;
    for p in polys {
        let b: f64 = p
            .terms()
            .map(|(c, powers)| c.abs() * r.powi(powers.iter().sum::<u32>() as i32))
            .sum();
        sum2 += b * b;
    }
    sum2.sqrt()
}

impl<const N: usize> Hamiltonian<N> for PolynomialSystem<N> {
    fn name(&self) -> &'static str {
        "polynomial"
    }

    #[inline(always)]
    fn potential<T: Real>(&self, q: &[T; N]) -> T {
        let mut v = T::splat(0.0);
        self.value.eval(q, |_, x| v = x);
        v
    }

    /// From a cubic's dense rows in 2 and 3 dof ([`CubicKick`]), else from the program.
    #[inline(always)]
    fn grad<T: Real>(&self, q: &[T; N]) -> [T; N] {
        if let (2, Some(cubic)) = (N, &self.plane_cubic) {
            let q: &[T; 2] = q[..].try_into().expect("N = 2");
            return widen((cubic.grad(q), [[T::splat(0.0); 2]; 2])).0;
        }
        if let (3, Some(cubic)) = (N, &self.space_cubic) {
            let q: &[T; 3] = q[..].try_into().expect("N = 3");
            return widen((cubic.grad(q), [[T::splat(0.0); 3]; 3])).0;
        }
        let mut g = [T::splat(0.0); N];
        self.grad.eval(q, |i, x| g[i] = x);
        g
    }

    #[inline(always)]
    fn hess_vec<T: Real>(&self, q: &[T; N], u: &[T; N]) -> [T; N] {
        let h = self.hessian(q);
        core::array::from_fn(|i| {
            let mut s = T::splat(0.0);
            for j in 0..N {
                s = h[i][j].mul_add(u[j], s);
            }
            s
        })
    }

    /// As [`Self::grad`].
    #[inline(always)]
    fn hessian<T: Real>(&self, q: &[T; N]) -> [[T; N]; N] {
        if let (2, Some(cubic)) = (N, &self.plane_cubic) {
            let q: &[T; 2] = q[..].try_into().expect("N = 2");
            return widen(([T::splat(0.0); 2], cubic.hessian(q))).1;
        }
        if let (3, Some(cubic)) = (N, &self.space_cubic) {
            let q: &[T; 3] = q[..].try_into().expect("N = 3");
            return widen(([T::splat(0.0); 3], cubic.hessian(q))).1;
        }
        let mut h = [[T::splat(0.0); N]; N];
        self.hessian.eval(q, |o, x| h[o / N][o % N] = x);
        h
    }

    fn third_vec<T: Real>(&self, q: &[T; N], w: &[T; N], u: &[T; N]) -> [T; N] {
        let mut out = [T::splat(0.0); N];
        self.third.eval(q, |o, x| {
            let (i, j, k) = (o / (N * N), (o / N) % N, o % N);
            out[i] = x.mul_add(w[j] * u[k], out[i]);
        });
        out
    }

    #[inline(always)]
    fn corrector_grad<T: Real>(&self, q: &[T; N]) -> [T; N] {
        Self::vector_and_matrix(&self.corrector, q).0
    }

    #[inline(always)]
    fn corrector_hessian<T: Real>(&self, q: &[T; N]) -> [[T; N]; N] {
        Self::vector_and_matrix(&self.corrector, q).1
    }

    /// −b∇V + c∇K and −b D²V + c D²K: from a cubic's derivatives by the chain rule in 2 and 3
    /// degrees of freedom ([`CubicKick`]), else each pair from one program.
    #[inline(always)]
    fn kick_terms<T: Real>(&self, q: &[T; N], b: Option<T>, c: Option<T>) -> KickTerms<T, N> {
        if let (2, Some(cubic)) = (N, &self.plane_cubic) {
            let q: &[T; 2] = q[..].try_into().expect("N = 2");
            let (force, matrix) = widen(cubic.kick_terms(q, b, c));
            return KickTerms { force, matrix };
        }
        if let (3, Some(cubic)) = (N, &self.space_cubic) {
            let q: &[T; 3] = q[..].try_into().expect("N = 3");
            let (force, matrix) = widen(cubic.kick_terms(q, b, c));
            return KickTerms { force, matrix };
        }
        // The programs index their point at run time, so they read a copy: indexing the
        // caller's own array would keep the whole step's state in memory (copied in and out
        // at every step) even where the dense branch runs.
        let q = *q;
        KickTerms::compose(
            b,
            || Self::vector_and_matrix(&self.kick, &q),
            c,
            || Self::vector_and_matrix(&self.corrector, &q),
        )
    }

    /// K's derivatives are bounded both term by term and through V's by the chain rule,
    /// |∇K| ≤ 2‖D²V‖|∇V| and ‖D²K‖ ≤ 2(‖D²V‖² + |∇V| ‖D³V‖_F), and the smaller bound holds:
    /// the expanded K loses the cancellations between its terms, so the chain rule is usually
    /// far tighter, and tighter bounds open longer quiet windows in the batched driver.
    fn derivative_bounds(&self, r: f64) -> Option<DerivativeBounds> {
        let [grad, hessian, corrector_grad, corrector_hessian, third] =
            self.bounds.each_ref().map(|polys| norm_bound(polys, r));
        Some(DerivativeBounds {
            grad,
            hessian,
            corrector_grad: corrector_grad.min(2.0 * hessian * grad),
            corrector_hessian: corrector_hessian.min(2.0 * (hessian * hessian + grad * third)),
        })
    }
}

/// The Taylor recursion's plan. A jet's derived series hold q1…qN (copied order by order) and
/// then every product of coordinates in ∇V (degree 2 and more), each the product of two series
/// before it; ∇V's terms read them, and D²V·u is grouped by monomial and column so that each
/// Cauchy product m ⋆ u_j is formed once and added to every row it appears in. The Cauchy sums
/// of one order run side by side, one accumulator each: one sum is a chain of dependent
/// multiply-adds, and many chains overlap in the pipeline (the hand-written Hénon–Heiles
/// recursion does the same with its few sums), four at a time ([`cauchy_sums`]).
#[derive(Clone, Debug, PartialEq)]
struct TaylorPlan {
    dof: usize,
    /// Derived series dof + i = series a · series b.
    products: Vec<(usize, usize)>,
    /// ∇V_i's terms: (derived series or `None` for the constant 1, coefficient), by row i.
    grad: Vec<Vec<(Option<usize>, f64)>>,
    /// D²V·u's terms with a monomial of degree 1 or more.
    hess: Vec<HessianTerm>,
    /// D²V·u's constant terms: (row i, column j, coefficient).
    hess_constant: Vec<(usize, usize, f64)>,
}

/// The monomial (a derived series) of D²V's column j: row i of D²V·u gains Σ c_i (m ⋆ u_j)
/// for its `rows`.
#[derive(Clone, Debug, PartialEq)]
struct HessianTerm {
    monomial: usize,
    column: usize,
    rows: Vec<(usize, f64)>,
}

impl TaylorPlan {
    /// `hessian` by rows (N² polynomials).
    fn new(grad: &[Polynomial], hessian: &[Polynomial]) -> TaylorPlan {
        let dof = grad.len();
        let mut monomials = Monomials::default();
        let mut grad_terms = Vec::new();
        for (i, g) in grad.iter().enumerate() {
            for (c, powers) in g.terms() {
                grad_terms.push((i, monomials.factor(powers), c));
            }
        }
        let mut hess_terms = Vec::new();
        for (o, h) in hessian.iter().enumerate() {
            for (c, powers) in h.terms() {
                hess_terms.push((o / dof, o % dof, monomials.factor(powers), c));
            }
        }
        let series = |f: Factor| match f {
            Factor::One => None,
            Factor::Coordinate(i) => Some(i),
            Factor::Product(i) => Some(dof + i),
        };
        let products = monomials
            .products
            .iter()
            .map(|&(c, lower)| (c, series(lower).expect("a product has degree 2 or more")))
            .collect();
        let mut hess: Vec<HessianTerm> = Vec::new();
        let mut hess_constant = Vec::new();
        for (i, column, f, c) in hess_terms {
            let Some(monomial) = series(f) else {
                hess_constant.push((i, column, c));
                continue;
            };
            match hess
                .iter_mut()
                .find(|t| t.monomial == monomial && t.column == column)
            {
                Some(t) => t.rows.push((i, c)),
                None => hess.push(HessianTerm {
                    monomial,
                    column,
                    rows: vec![(i, c)],
                }),
            }
        }
        TaylorPlan {
            dof,
            products,
            grad: (0..dof)
                .map(|row| {
                    let terms = grad_terms.iter().filter(|&&(i, _, _)| i == row);
                    terms.map(|&(_, f, c)| (series(f), c)).collect()
                })
                .collect(),
            hess,
            hess_constant,
        }
    }
}

/// Runs `f` on `len` zeroed accumulators, on the stack where they fit.
#[inline(always)]
fn with_accumulators<T: Real, R>(len: usize, f: impl FnOnce(&mut [T]) -> R) -> R {
    if len <= 8 {
        f(&mut [T::splat(0.0); 8][..len])
    } else if len <= 32 {
        f(&mut [T::splat(0.0); 32][..len])
    } else {
        f(&mut vec![T::splat(0.0); len])
    }
}

/// The sums Σ_{j = from..=k} a[j] b[k − j] of the pairs `pair(0..count)`, four at a time in one
/// loop over j (four independent chains of multiply-adds), each handed to `out` with its index.
#[inline(always)]
fn cauchy_sums<'a, T: Real + 'a>(
    count: usize,
    pair: impl Fn(usize) -> (&'a Series<T>, &'a Series<T>),
    from: usize,
    k: usize,
    mut out: impl FnMut(usize, T),
) {
    assert!(k <= P_MAX);
    for first in (0..count).step_by(4) {
        // A last group of fewer than four repeats its last pair and drops the extra sums.
        let pairs: [(&Series<T>, &Series<T>); 4] =
            core::array::from_fn(|i| pair((first + i).min(count - 1)));
        let mut sums = [T::splat(0.0); 4];
        for j in from..=k {
            for (s, (a, b)) in sums.iter_mut().zip(&pairs) {
                *s = a[j].mul_add(b[k - j], *s);
            }
        }
        for (i, &s) in sums.iter().enumerate().take(count - first) {
            out(first + i, s);
        }
    }
}

impl<const N: usize> TaylorSeries<N> for PolynomialSystem<N> {
    fn derived_series(&self) -> usize {
        if N == 2 && self.plane_series.is_some() {
            return 0;
        }
        N + self.taylor.products.len()
    }

    #[inline(always)]
    fn all_coeffs<T: Real, const K: usize>(
        &self,
        q: &[Series<T>; N],
        u: &[[Series<T>; N]; K],
        derived: &mut [Series<T>],
        k: usize,
    ) -> ([T; N], [[T; N]; K]) {
        if let (2, Some(series)) = (N, &self.plane_series) {
            let q2: &[Series<T>; 2] = q[..].try_into().expect("N = 2");
            let mut u2 = [q2; K];
            for (to, from) in u2.iter_mut().zip(u) {
                *to = from[..].try_into().expect("N = 2");
            }
            let (g, hv) = series.all_coeffs(q2, u2, k);
            let mut grad = [T::splat(0.0); N];
            let mut hess = [[T::splat(0.0); N]; K];
            grad[..2].copy_from_slice(&g);
            for v in 0..K {
                hess[v][..2].copy_from_slice(&hv[v]);
            }
            return (grad, hess);
        }
        let plan = &self.taylor;
        debug_assert_eq!(plan.dof, N);
        for i in 0..N {
            derived[i][k] = q[i][k];
        }
        // Order k of every product: the terms j ≥ 1 of all sums (they read only orders below
        // k of the lower factor), then the term j = 0 in dependency order.
        with_accumulators(plan.products.len(), |acc: &mut [T]| {
            let d = &*derived;
            let pair = |p: usize| (&d[plan.products[p].0], &d[plan.products[p].1]);
            cauchy_sums(plan.products.len(), pair, 1, k, |p, s| acc[p] = s);
            for (p, (&s, &(a, b))) in acc.iter().zip(&plan.products).enumerate() {
                derived[N + p][k] = derived[a][0].mul_add(derived[b][k], s);
            }
        });
        let derived = &*derived;
        let zero = T::splat(0.0);
        let g: [T; N] = core::array::from_fn(|i| {
            let mut sum = zero;
            for &(series, c) in &plan.grad[i] {
                let x = match series {
                    Some(s) => derived[s][k],
                    None if k == 0 => T::splat(1.0),
                    None => zero,
                };
                sum = T::splat(c).mul_add(x, sum);
            }
            sum
        });
        let mut hv = [[zero; N]; K];
        for &(i, column, c) in &plan.hess_constant {
            for v in 0..K {
                hv[v][i] = T::splat(c).mul_add(u[v][column][k], hv[v][i]);
            }
        }
        if K > 0 {
            let pair = |c: usize| {
                let term = &plan.hess[c / K];
                (&derived[term.monomial], &u[c % K][term.column])
            };
            cauchy_sums(plan.hess.len() * K, pair, 0, k, |c, s| {
                for &(i, coeff) in &plan.hess[c / K].rows {
                    hv[c % K][i] = T::splat(coeff).mul_add(s, hv[c % K][i]);
                }
            });
        }
        (g, hv)
    }
}
