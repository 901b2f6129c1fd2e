//! Dense evaluation of a few polynomials in every monomial up to a degree, with the sizes known
//! at compile time: the monomials and the sums sit in registers and every index is a constant,
//! where the sparse [`Program`](super::program::Program) walks its terms in a loop. A kick of a
//! cubic potential in 2 or 3 degrees of freedom (Hénon–Heiles and its kin) goes this way; the
//! zero coefficients cost multiply-adds that a loop's overhead costs more than.

use super::Polynomial;
use crate::arith::real::Real;

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

/// A vector and a symmetric matrix from polynomials of degree ≤ D: the N vector rows, then
/// the matrix's upper triangle by rows (N(N+1)/2), so `O` = N + N(N+1)/2.
#[derive(Clone, Debug, PartialEq)]
pub(crate) struct VectorAndMatrix<const N: usize, const M: usize, const O: usize> {
    dense: Dense<N, M, O>,
}

impl<const N: usize, const M: usize, const O: usize> VectorAndMatrix<N, M, O> {
    /// From the vector's N polynomials and the matrix's N² (by rows, symmetric).
    pub fn new(vector: &[Polynomial], matrix: &[Polynomial]) -> Option<Self> {
        let upper = (0..N).flat_map(|i| (i..N).map(move |j| &matrix[i * N + j]));
        Some(VectorAndMatrix {
            dense: Dense::new(vector.iter().chain(upper))?,
        })
    }

    /// The vector and the whole matrix at `q`.
    #[inline(always)]
    pub fn eval<T: Real>(&self, q: &[T; N]) -> ([T; N], [[T; N]; N]) {
        let out = self.dense.eval(q);
        let mut vector = [T::splat(0.0); N];
        vector.copy_from_slice(&out[..N]);
        let mut matrix = [[T::splat(0.0); N]; N];
        let mut at = N;
        for i in 0..N {
            for j in i..N {
                matrix[i][j] = out[at];
                matrix[j][i] = out[at];
                at += 1;
            }
        }
        (vector, matrix)
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

    /// A cubic's gradient and Hessian through dense rows: the vector, and the whole symmetric
    /// matrix from its upper triangle.
    #[test]
    fn a_vector_and_a_symmetric_matrix_come_from_their_rows() {
        let v = Polynomial::parse("(q1^2 + q2^2)/2 + q1^2*q2 - q2^3/3 + 0.3*q1*q2^2", 2).unwrap();
        let grad: Vec<Polynomial> = (0..2).map(|i| v.derivative(i)).collect();
        let hessian: Vec<Polynomial> = grad
            .iter()
            .flat_map(|g| (0..2).map(|j| g.derivative(j)))
            .collect();
        let dense = VectorAndMatrix::<2, 6, 5>::new(&grad, &hessian).unwrap();
        let q = [0.37, -0.21];
        let (g, h) = dense.eval(&q);
        for i in 0..2 {
            assert!((g[i] - grad[i].eval(&q)).abs() < 1e-15);
            for j in 0..2 {
                assert!((h[i][j] - hessian[2 * i + j].eval(&q)).abs() < 1e-15);
            }
        }
    }
}
