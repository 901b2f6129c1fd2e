//! Polynomials compiled for evaluation in the integrators' inner loops: every monomial the
//! outputs need, each formed by one multiplication from a lower one, and every output a linear
//! form in the monomials. Several polynomials compiled together (a gradient and a Hessian)
//! share their monomials, so a kick forms each product of coordinates once.

use super::Polynomial;
use crate::arith::real::Real;
use std::collections::HashMap;

/// Where a value comes from: the constant 1, a coordinate, or a product formed before.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub(crate) enum Factor {
    One,
    Coordinate(usize),
    /// The `i`-th entry of [`Monomials::products`].
    Product(usize),
}

/// The monomials of degree 2 and more that a set of polynomials needs, in an order where each
/// is a coordinate times a monomial before it (or times a coordinate).
#[derive(Clone, Debug, Default, PartialEq)]
pub(crate) struct Monomials {
    /// Product i = q[coordinate] · factor.
    pub products: Vec<(usize, Factor)>,
    index: HashMap<Vec<u32>, Factor>,
}

impl Monomials {
    /// The factor that stands for the monomial Π q_i^powers[i], adding it (and the lower
    /// monomials it is formed from) when new.
    pub fn factor(&mut self, powers: &[u32]) -> Factor {
        let degree: u32 = powers.iter().sum();
        match degree {
            0 => return Factor::One,
            1 => return Factor::Coordinate(powers.iter().position(|&p| p == 1).unwrap()),
            _ => {}
        }
        if let Some(&f) = self.index.get(powers) {
            return f;
        }
        // Peel off the first coordinate that appears: the lower monomial comes first.
        let first = powers.iter().position(|&p| p > 0).unwrap();
        let mut lower = powers.to_vec();
        lower[first] -= 1;
        let lower = self.factor(&lower);
        let f = Factor::Product(self.products.len());
        self.products.push((first, lower));
        self.index.insert(powers.to_vec(), f);
        f
    }
}

/// Polynomials compiled together: `eval` gives their values at a point, in the order given.
#[derive(Clone, Debug, PartialEq)]
pub(crate) struct Program {
    dof: usize,
    monomials: Monomials,
    /// Every output's terms, one after another: (monomial, coefficient).
    terms: Vec<(Factor, f64)>,
    /// Output o's terms are `terms[ends[o − 1]..ends[o]]`.
    ends: Vec<usize>,
}

impl Program {
    /// The program evaluating `polys` (all in the same number of coordinates).
    pub fn new<'a>(dof: usize, polys: impl IntoIterator<Item = &'a Polynomial>) -> Program {
        let mut monomials = Monomials::default();
        let mut terms = Vec::new();
        let mut ends = Vec::new();
        for poly in polys {
            assert_eq!(poly.dof(), dof, "a polynomial in {dof} coordinates");
            for (coeff, powers) in poly.terms() {
                terms.push((monomials.factor(powers), coeff));
            }
            ends.push(terms.len());
        }
        Program {
            dof,
            monomials,
            terms,
            ends,
        }
    }

    /// The polynomials' values at `q`, handed to `out` with their index.
    #[inline(always)]
    pub fn eval<T: Real>(&self, q: &[T], out: impl FnMut(usize, T)) {
        // The products live on the stack in a buffer of a few fixed sizes: a heap buffer per
        // call would cost more than the arithmetic of a small system.
        match self.monomials.products.len() {
            0..=8 => self.eval_with::<T, 8>(q, out),
            9..=32 => self.eval_with::<T, 32>(q, out),
            _ => {
                let mut products = vec![T::splat(0.0); self.monomials.products.len()];
                self.eval_into(q, &mut products, out)
            }
        }
    }

    #[inline(always)]
    fn eval_with<T: Real, const C: usize>(&self, q: &[T], out: impl FnMut(usize, T)) {
        let mut products = [T::splat(0.0); C];
        self.eval_into(q, &mut products, out)
    }

    #[inline(always)]
    fn eval_into<T: Real>(&self, q: &[T], products: &mut [T], mut out: impl FnMut(usize, T)) {
        assert_eq!(q.len(), self.dof);
        let value = |f: Factor, products: &[T]| match f {
            Factor::One => T::splat(1.0),
            Factor::Coordinate(i) => q[i],
            Factor::Product(i) => products[i],
        };
        for (i, &(coordinate, lower)) in self.monomials.products.iter().enumerate() {
            products[i] = q[coordinate] * value(lower, products);
        }
        let mut start = 0;
        for (o, &end) in self.ends.iter().enumerate() {
            let mut sum = T::splat(0.0);
            for &(f, coeff) in &self.terms[start..end] {
                sum = match f {
                    Factor::One => sum + T::splat(coeff),
                    _ => T::splat(coeff).mul_add(value(f, products), sum),
                };
            }
            out(o, sum);
            start = end;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A program's outputs are its polynomials' values (to rounding), and monomials shared
    /// by several polynomials are formed once.
    #[test]
    fn a_program_evaluates_its_polynomials_and_shares_monomials() {
        let texts = [
            "q1^3*q2 + 2*q2 - 0.5",
            "q1^2*q2 - q3^4",
            "7",
            "q1*q3 + q1^3*q2",
        ];
        let polys: Vec<Polynomial> = texts
            .iter()
            .map(|t| Polynomial::parse(t, 3).unwrap())
            .collect();
        let program = Program::new(3, &polys);
        assert_eq!(program.ends.len(), 4);
        // q1q2, q1²q2, q1³q2 (from q1 · lower), q3², q3³, q3⁴, q1q3: seven products.
        assert_eq!(program.monomials.products.len(), 7);
        let q = [0.3, -1.2, 0.7];
        let mut out = [0.0; 4];
        program.eval(&q, |o, x| out[o] = x);
        for (p, got) in polys.iter().zip(out) {
            let want = p.eval(&q);
            assert!(
                (got - want).abs() <= 1e-15 * want.abs().max(1.0),
                "{got} {want}"
            );
        }
    }
}
