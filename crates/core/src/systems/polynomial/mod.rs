//! Polynomials in q1…qN read from text ("(q1^2 + q2^2)/2 + q1^2*q2 - q2^3/3"), with exact
//! partial derivatives: the potentials of systems given as data, and the system
//! ([`PolynomialSystem`]) the integrators run on. Terms are kept merged and
//! sorted by their powers, so equal polynomials compare equal however they were written.

use crate::arith::real::Real;

mod dense;
pub mod named;
mod program;
mod system;

pub use system::PolynomialSystem;

/// One monomial: `coeff` · Π q_i^powers[i].
#[derive(Clone, Debug, PartialEq)]
struct Term {
    coeff: f64,
    powers: Vec<u32>,
}

/// A polynomial in `dof` variables q1…q_dof with f64 coefficients.
#[derive(Clone, Debug, PartialEq)]
pub struct Polynomial {
    dof: usize,
    /// Sorted by `powers`, no two alike, no zero coefficient.
    terms: Vec<Term>,
}

/// Largest power [`Polynomial::parse`] takes: far beyond any potential of interest, and small
/// enough that expanding a power of a sum stays cheap.
pub const MAX_POWER: u32 = 64;

impl Polynomial {
    /// The constant `c`.
    pub fn constant(dof: usize, c: f64) -> Polynomial {
        Polynomial::from_terms(
            dof,
            vec![Term {
                coeff: c,
                powers: vec![0; dof],
            }],
        )
    }

    /// The coordinate q_{k+1} (`k` counts from 0).
    pub fn variable(dof: usize, k: usize) -> Polynomial {
        assert!(k < dof, "q{} in {dof} degrees of freedom", k + 1);
        let mut powers = vec![0; dof];
        powers[k] = 1;
        Polynomial::from_terms(dof, vec![Term { coeff: 1.0, powers }])
    }

    fn from_terms(dof: usize, mut terms: Vec<Term>) -> Polynomial {
        terms.sort_by(|a, b| a.powers.cmp(&b.powers));
        let mut merged: Vec<Term> = Vec::with_capacity(terms.len());
        for t in terms {
            match merged.last_mut() {
                Some(last) if last.powers == t.powers => last.coeff += t.coeff,
                _ => merged.push(t),
            }
        }
        merged.retain(|t| t.coeff != 0.0);
        Polynomial { dof, terms: merged }
    }

    /// The number of variables.
    pub fn dof(&self) -> usize {
        self.dof
    }

    /// The terms as (coefficient, powers of q1…q_dof), sorted by their powers.
    pub fn terms(&self) -> impl Iterator<Item = (f64, &[u32])> {
        self.terms.iter().map(|t| (t.coeff, t.powers.as_slice()))
    }

    /// The largest total degree of a term (0 for a constant, and for zero).
    pub fn degree(&self) -> u32 {
        self.terms
            .iter()
            .map(|t| t.powers.iter().sum())
            .max()
            .unwrap_or(0)
    }

    /// The constant term's value, when the polynomial is a constant.
    pub fn as_constant(&self) -> Option<f64> {
        match self.terms.as_slice() {
            [] => Some(0.0),
            [t] if t.powers.iter().all(|&p| p == 0) => Some(t.coeff),
            _ => None,
        }
    }

    /// `self` plus `other`.
    pub fn add(&self, other: &Polynomial) -> Polynomial {
        let terms = self.terms.iter().chain(&other.terms).cloned().collect();
        Polynomial::from_terms(self.dof, terms)
    }

    /// `self` times the number `c`.
    pub fn scale(&self, c: f64) -> Polynomial {
        let terms = self
            .terms
            .iter()
            .map(|t| Term {
                coeff: t.coeff * c,
                powers: t.powers.clone(),
            })
            .collect();
        Polynomial::from_terms(self.dof, terms)
    }

    /// `self` times `other`.
    pub fn mul(&self, other: &Polynomial) -> Polynomial {
        let mut terms = Vec::with_capacity(self.terms.len() * other.terms.len());
        for a in &self.terms {
            for b in &other.terms {
                terms.push(Term {
                    coeff: a.coeff * b.coeff,
                    powers: a.powers.iter().zip(&b.powers).map(|(x, y)| x + y).collect(),
                });
            }
        }
        Polynomial::from_terms(self.dof, terms)
    }

    /// `self` to the power `n` (by squaring).
    pub fn pow(&self, mut n: u32) -> Polynomial {
        let mut result = Polynomial::constant(self.dof, 1.0);
        let mut base = self.clone();
        while n > 0 {
            if n & 1 == 1 {
                result = result.mul(&base);
            }
            n >>= 1;
            if n > 0 {
                base = base.mul(&base);
            }
        }
        result
    }

    /// Every first derivative of every polynomial of `polys`, polynomial by polynomial: ∇V
    /// from [V], D²V by rows from ∇V, D³V (i N² + j N + k) from D²V.
    pub fn derivatives(polys: &[Polynomial]) -> Vec<Polynomial> {
        polys
            .iter()
            .flat_map(|p| (0..p.dof()).map(|k| p.derivative(k)))
            .collect()
    }

    /// ∂/∂q_{k+1} (`k` counts from 0), exactly.
    pub fn derivative(&self, k: usize) -> Polynomial {
        let terms = self
            .terms
            .iter()
            .filter(|t| t.powers[k] > 0)
            .map(|t| {
                let mut powers = t.powers.clone();
                powers[k] -= 1;
                Term {
                    coeff: t.coeff * f64::from(t.powers[k]),
                    powers,
                }
            })
            .collect();
        Polynomial::from_terms(self.dof, terms)
    }

    /// The same polynomial with q_{a+1} and q_{b+1} exchanged (`a`, `b` count from 0): a
    /// section on the plane q_{a+1} = 0 runs as one on q1 = 0 of the exchanged system.
    pub fn swapped(&self, a: usize, b: usize) -> Polynomial {
        assert!(
            a < self.dof && b < self.dof,
            "coordinates of {} dof",
            self.dof
        );
        let terms = self
            .terms
            .iter()
            .map(|t| {
                let mut powers = t.powers.clone();
                powers.swap(a, b);
                Term {
                    coeff: t.coeff,
                    powers,
                }
            })
            .collect();
        Polynomial::from_terms(self.dof, terms)
    }

    /// The value at `q` (`q.len()` = dof), in `T`'s arithmetic.
    pub fn eval<T: Real>(&self, q: &[T]) -> T {
        assert_eq!(q.len(), self.dof, "a point of {} coordinates", self.dof);
        let mut sum = T::splat(0.0);
        for t in &self.terms {
            let mut m = T::splat(t.coeff);
            for (&x, &p) in q.iter().zip(&t.powers) {
                for _ in 0..p {
                    m = m * x;
                }
            }
            sum += m;
        }
        sum
    }

    /// Reads a polynomial in q1…q`dof` from `text`: numbers, the coordinates, `+ - * /`,
    /// integer powers (`^` or `**`) and parentheses. Division only by numbers.
    pub fn parse(text: &str, dof: usize) -> Result<Polynomial, ParseError> {
        let mut p = Parser {
            chars: text.chars().collect(),
            at: 0,
            dof,
        };
        let poly = p.sum()?;
        p.skip_space();
        if p.at < p.chars.len() {
            return Err(p.error("expected an operator (+ - * / ^) or the end"));
        }
        Ok(poly)
    }
}

/// Why a text is not a polynomial: the character position (from 0) and what was wrong there.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct ParseError {
    /// Character position (from 0) of the error.
    pub at: usize,
    /// What was wrong there.
    pub message: String,
}

impl core::fmt::Display for ParseError {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        write!(f, "at character {}: {}", self.at + 1, self.message)
    }
}

impl std::error::Error for ParseError {}

/// A recursive-descent reader: sum → product → signed → power → atom.
struct Parser {
    chars: Vec<char>,
    at: usize,
    dof: usize,
}

impl Parser {
    fn error(&self, message: impl Into<String>) -> ParseError {
        ParseError {
            at: self.at,
            message: message.into(),
        }
    }

    fn skip_space(&mut self) {
        while self.chars.get(self.at).is_some_and(|c| c.is_whitespace()) {
            self.at += 1;
        }
    }

    /// The next non-space character, not taken.
    fn peek(&mut self) -> Option<char> {
        self.skip_space();
        self.chars.get(self.at).copied()
    }

    fn sum(&mut self) -> Result<Polynomial, ParseError> {
        let mut acc = self.product()?;
        while let Some(c @ ('+' | '-')) = self.peek() {
            self.at += 1;
            let rhs = self.product()?;
            acc = acc.add(&if c == '-' { rhs.scale(-1.0) } else { rhs });
        }
        Ok(acc)
    }

    fn product(&mut self) -> Result<Polynomial, ParseError> {
        let mut acc = self.signed()?;
        loop {
            match self.peek() {
                Some('*') if self.chars.get(self.at + 1) != Some(&'*') => {
                    self.at += 1;
                    acc = acc.mul(&self.signed()?);
                }
                Some('/') => {
                    let slash = self.at;
                    self.at += 1;
                    let divisor = self.signed()?;
                    let c = divisor.as_constant().ok_or_else(|| ParseError {
                        at: slash,
                        message: "not a polynomial: division by an expression in q (divide by numbers only)".into(),
                    })?;
                    if c == 0.0 {
                        return Err(ParseError {
                            at: slash,
                            message: "division by zero".into(),
                        });
                    }
                    acc = acc.scale(1.0 / c);
                }
                _ => return Ok(acc),
            }
        }
    }

    /// A power with optional signs before it: −q1^2 is −(q1^2).
    fn signed(&mut self) -> Result<Polynomial, ParseError> {
        match self.peek() {
            Some('-') => {
                self.at += 1;
                Ok(self.signed()?.scale(-1.0))
            }
            Some('+') => {
                self.at += 1;
                self.signed()
            }
            _ => self.power(),
        }
    }

    fn power(&mut self) -> Result<Polynomial, ParseError> {
        let base = self.atom()?;
        let caret = match self.peek() {
            Some('^') => 1,
            Some('*') if self.chars.get(self.at + 1) == Some(&'*') => 2,
            _ => return Ok(base),
        };
        self.at += caret;
        self.skip_space();
        let start = self.at;
        while self.chars.get(self.at).is_some_and(|c| c.is_ascii_digit()) {
            self.at += 1;
        }
        if start == self.at {
            self.at = start;
            let what = if self.chars.get(start) == Some(&'-') {
                "a negative power is not a polynomial"
            } else {
                "expected a whole number as the power"
            };
            return Err(self.error(what));
        }
        if matches!(self.chars.get(self.at), Some('.' | 'e' | 'E')) {
            return Err(ParseError {
                at: start,
                message: "expected a whole number as the power".into(),
            });
        }
        let digits: String = self.chars[start..self.at].iter().collect();
        match digits.parse::<u32>() {
            Ok(n) if n <= MAX_POWER => Ok(base.pow(n)),
            _ => Err(ParseError {
                at: start,
                message: format!("powers go up to {MAX_POWER} (got {digits})"),
            }),
        }
    }

    fn atom(&mut self) -> Result<Polynomial, ParseError> {
        match self.peek() {
            Some('(') => {
                let open = self.at;
                self.at += 1;
                let inner = self.sum()?;
                if self.peek() != Some(')') {
                    return Err(self.error(format!(
                        "expected ')' to close the '(' at character {}",
                        open + 1
                    )));
                }
                self.at += 1;
                Ok(inner)
            }
            Some('q') => self.coordinate(),
            Some(c) if c.is_ascii_digit() || c == '.' => self.number(),
            _ => Err(self.error(format!(
                "expected a number, a coordinate q1…q{} or '('",
                self.dof
            ))),
        }
    }

    fn coordinate(&mut self) -> Result<Polynomial, ParseError> {
        let start = self.at;
        self.at += 1;
        let digits_from = self.at;
        while self.chars.get(self.at).is_some_and(|c| c.is_ascii_digit()) {
            self.at += 1;
        }
        let digits: String = self.chars[digits_from..self.at].iter().collect();
        match digits.parse::<usize>() {
            Ok(k) if (1..=self.dof).contains(&k) => Ok(Polynomial::variable(self.dof, k - 1)),
            _ => Err(ParseError {
                at: start,
                message: format!(
                    "q{digits} is not a coordinate of a system of {} degrees of freedom (q1…q{})",
                    self.dof, self.dof
                ),
            }),
        }
    }

    fn number(&mut self) -> Result<Polynomial, ParseError> {
        let start = self.at;
        let digit = |c: Option<&char>| c.is_some_and(|c| c.is_ascii_digit());
        while digit(self.chars.get(self.at)) || self.chars.get(self.at) == Some(&'.') {
            self.at += 1;
        }
        if matches!(self.chars.get(self.at), Some('e' | 'E')) {
            let sign = matches!(self.chars.get(self.at + 1), Some('+' | '-'));
            if digit(self.chars.get(self.at + 1 + usize::from(sign))) {
                self.at += 1 + usize::from(sign);
                while digit(self.chars.get(self.at)) {
                    self.at += 1;
                }
            }
        }
        let text: String = self.chars[start..self.at].iter().collect();
        match text.parse::<f64>() {
            Ok(x) if x.is_finite() => Ok(Polynomial::constant(self.dof, x)),
            _ => Err(ParseError {
                at: start,
                message: format!("{text:?} is not a finite number"),
            }),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::{Hamiltonian, HenonHeiles};

    const HENON_HEILES: &str = "(q1^2 + q2^2)/2 + q1^2*q2 - q2^3/3";

    #[test]
    fn henon_heiles_from_text_is_the_built_in_potential() {
        let v = Polynomial::parse(HENON_HEILES, 2).unwrap();
        assert_eq!(v.degree(), 3);
        for (x, y) in [(0.1, -0.2), (0.3, 0.55), (-0.4, 0.0), (0.0, 0.0)] {
            let want = HenonHeiles.potential(&[x, y]);
            let got = v.eval(&[x, y]);
            assert!(
                (got - want).abs() <= 1e-16 * want.abs().max(1e-3),
                "{got} {want}"
            );
            let grad = HenonHeiles.grad(&[x, y]);
            for k in 0..2 {
                let d = v.derivative(k).eval(&[x, y]);
                assert!((d - grad[k]).abs() <= 1e-15, "∂{k}: {d} {}", grad[k]);
            }
        }
    }

    #[test]
    fn equal_polynomials_compare_equal_however_written() {
        let a = Polynomial::parse("(q1 + q2)^2", 2).unwrap();
        let b = Polynomial::parse("q2**2 + 2*q1*q2 + q1 ^ 2", 2).unwrap();
        assert_eq!(a, b);
        let c = Polynomial::parse("-q1^2 + +3 - -q1*q1 - 3", 2).unwrap();
        assert_eq!(c, Polynomial::constant(2, 0.0));
        let d = Polynomial::parse("2.5e-1 * q3 / 0.5", 3).unwrap();
        assert_eq!(d, Polynomial::variable(3, 2).scale(0.5));
    }

    #[test]
    fn bad_text_is_refused_with_its_position() {
        let cases = [
            ("q1 / q2", 2, 3, "division by an expression"),
            ("q1 / (2 - 2)", 2, 3, "division by zero"),
            ("q1^-2", 2, 3, "negative power"),
            ("q1^0.5", 2, 3, "expected a whole number"),
            ("q1^65", 2, 3, "powers go up to 64"),
            ("q3 + q1", 2, 0, "q3 is not a coordinate"),
            ("q1 + x", 2, 5, "expected a number"),
            ("(q1 + q2", 2, 8, "expected ')'"),
            ("q1 q2", 2, 3, "expected an operator"),
            ("", 2, 0, "expected a number"),
            ("1e999 * q1", 2, 0, "not a finite number"),
        ];
        for (text, dof, at, says) in cases {
            let e = Polynomial::parse(text, dof).unwrap_err();
            assert_eq!(e.at, at, "{text}: {e}");
            assert!(e.message.contains(says), "{text}: {e}");
        }
    }
}
