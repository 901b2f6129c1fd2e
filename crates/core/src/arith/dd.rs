//! Double-double arithmetic: a number is an unevaluated sum hi + lo of two f64 with
//! |lo| ≤ ½ ulp(hi), about 106 bits of significand. Products use the fused multiply-add
//! (error-free TwoProd), which the pinned x86-64-v3 target executes in one instruction.
//! Algorithms: Dekker (1971) TwoSum/TwoProd, and the accurate addition of Joldes, Muller &
//! Popescu (ACM TOMS 2017, "Tight and rigorous error bounds for basic building blocks of
//! double-word arithmetic", Alg. 6 for addition, Alg. 10 for multiplication).

use crate::arith::real::Real;
use core::ops::{Add, AddAssign, Div, Mul, Neg, Sub, SubAssign};

/// hi + lo, normalised so that hi = fl(hi + lo). `B` is `f64` for one number or
/// [`Lanes`](crate::arith::real::Lanes) for several side by side in SIMD lanes, each lane computing
/// exactly what the `f64` form computes (same operations, same order).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct DoubleDouble<B = f64> {
    /// The leading part.
    pub hi: B,
    /// The trailing part, below half an ulp of `hi`.
    pub lo: B,
}

/// s + e = a + b exactly.
#[inline(always)]
fn two_sum<B: Real>(a: B, b: B) -> (B, B) {
    let s = a + b;
    let bb = s - a;
    let e = (a - (s - bb)) + (b - bb);
    (s, e)
}

/// s + e = a + b exactly, given |a| ≥ |b|.
#[inline(always)]
fn fast_two_sum<B: Real>(a: B, b: B) -> (B, B) {
    let s = a + b;
    (s, b - (s - a))
}

/// p + e = a·b exactly.
#[inline(always)]
fn two_prod<B: Real>(a: B, b: B) -> (B, B) {
    let p = a * b;
    (p, a.mul_add(b, -p))
}

/// a · b as an exact high word and the sum of everything below it (TwoProd's error and the
/// cross terms), not yet normalised: the product's first steps, shared by `*` and `mul_add`.
#[inline(always)]
fn product_words<B: Real>(a: DoubleDouble<B>, b: DoubleDouble<B>) -> (B, B) {
    let (p, e) = two_prod(a.hi, b.hi);
    (p, e + a.hi.mul_add(b.lo, a.lo * b.hi))
}

impl<B: Real> DoubleDouble<B> {
    /// The double-double `x` in every lane.
    #[inline(always)]
    pub fn splat_dd(x: DoubleDouble) -> Self {
        DoubleDouble {
            hi: B::splat(x.hi),
            lo: B::splat(x.lo),
        }
    }
}

impl DoubleDouble {
    /// Zero.
    pub const ZERO: DoubleDouble = DoubleDouble { hi: 0.0, lo: 0.0 };

    /// The exact value of `x`.
    #[inline(always)]
    pub fn from_f64(x: f64) -> Self {
        DoubleDouble { hi: x, lo: 0.0 }
    }

    /// The nearest f64.
    #[inline(always)]
    pub fn to_f64(self) -> f64 {
        self.hi + self.lo
    }

    /// The absolute value.
    pub fn abs(self) -> Self {
        if self.hi < 0.0 {
            -self
        } else {
            self
        }
    }

    /// The square root (one Newton step from the f64 root); the f64 root of `hi` when `hi` ≤ 0.
    pub fn sqrt(self) -> Self {
        if self.hi <= 0.0 {
            return DoubleDouble::from_f64(self.hi.sqrt());
        }
        // One Newton step from the f64 root: x + (a − x²)/(2x).
        let x = self.hi.sqrt();
        let (p, e) = two_prod(x, x);
        let r = (self - DoubleDouble { hi: p, lo: e }).hi;
        let (s, t) = fast_two_sum(x, r / (2.0 * x));
        DoubleDouble { hi: s, lo: t }
    }
}

impl<B: Real> Add for DoubleDouble<B> {
    type Output = Self;
    #[inline(always)]
    fn add(self, b: Self) -> Self {
        let (s, t) = two_sum(self.hi, b.hi);
        let (u, v) = two_sum(self.lo, b.lo);
        let (s, t) = fast_two_sum(s, t + u);
        let (hi, lo) = fast_two_sum(s, t + v);
        DoubleDouble { hi, lo }
    }
}

impl Div for DoubleDouble {
    type Output = Self;
    /// a / b to about 2⁻¹⁰⁴ relative (two corrections of the f64 quotient).
    fn div(self, b: Self) -> Self {
        let q1 = self.hi / b.hi;
        let r = self - b * DoubleDouble::from_f64(q1);
        let q2 = r.hi / b.hi;
        let r = r - b * DoubleDouble::from_f64(q2);
        let q3 = r.hi / b.hi;
        let (s, e) = fast_two_sum(q1, q2);
        DoubleDouble { hi: s, lo: e } + DoubleDouble::from_f64(q3)
    }
}

impl<B: Real> Neg for DoubleDouble<B> {
    type Output = Self;
    #[inline(always)]
    fn neg(self) -> Self {
        DoubleDouble {
            hi: -self.hi,
            lo: -self.lo,
        }
    }
}

impl<B: Real> Sub for DoubleDouble<B> {
    type Output = Self;
    #[inline(always)]
    fn sub(self, b: Self) -> Self {
        self + (-b)
    }
}

impl<B: Real> Mul for DoubleDouble<B> {
    type Output = Self;
    #[inline(always)]
    fn mul(self, b: Self) -> Self {
        let (p, low) = product_words(self, b);
        let (hi, lo) = fast_two_sum(p, low);
        DoubleDouble { hi, lo }
    }
}

impl<B: Real> AddAssign for DoubleDouble<B> {
    #[inline(always)]
    fn add_assign(&mut self, b: Self) {
        *self = *self + b;
    }
}

impl<B: Real> SubAssign for DoubleDouble<B> {
    #[inline(always)]
    fn sub_assign(&mut self, b: Self) {
        *self = *self - b;
    }
}

impl<B: Real> Real for DoubleDouble<B> {
    type Lead = B;
    const EXTENDED: bool = true;
    #[inline(always)]
    fn lead(self) -> B {
        self.hi
    }
    #[inline(always)]
    fn from_lead(x: B) -> Self {
        DoubleDouble {
            hi: x,
            lo: B::splat(0.0),
        }
    }
    #[inline(always)]
    fn splat(x: f64) -> Self {
        DoubleDouble {
            hi: B::splat(x),
            lo: B::splat(0.0),
        }
    }
    /// self · a + b in one pass (16 floating-point operations against 28 for the product
    /// and the accurate sum): the exact product's high part is added to b.hi error-free, and
    /// everything below the first word — the product's rounding error, its cross terms and
    /// b.lo — is summed in f64 and folded in once (the "sloppy" addition of Joldes, Muller &
    /// Popescu, Alg. 5, with the product left unnormalised). Its error is at most a few u²
    /// of |self · a| + |b| rather than of the result, so a sum that cancels keeps an
    /// absolute, not a relative, 106-bit accuracy: what the Taylor recursions need, whose
    /// Cauchy sums are almost all of a double-double step (figures: docs/performance.md).
    #[inline(always)]
    fn mul_add(self, a: Self, b: Self) -> Self {
        let (p, low) = product_words(self, a);
        let (s, t) = two_sum(p, b.hi);
        let (hi, lo) = fast_two_sum(s, t + (low + b.lo));
        DoubleDouble { hi, lo }
    }
    #[inline(always)]
    fn ratio(num: f64, den: f64) -> Self {
        Self::splat_dd(DoubleDouble::from_f64(num) / DoubleDouble::from_f64(den))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn arithmetic_carries_106_bits() {
        let third = DoubleDouble::ratio(1.0, 3.0);
        // 3 · (1/3) = 1 to ~1e-32.
        let one = third * DoubleDouble::from_f64(3.0);
        assert!((one - DoubleDouble::from_f64(1.0)).to_f64().abs() < 1e-31);
        // (1 + 2⁻⁶⁰)² − 1 = 2⁻⁵⁹ + 2⁻¹²⁰: f64 would give 0.
        let x = DoubleDouble::from_f64(1.0) + DoubleDouble::from_f64(2f64.powi(-60));
        let y = x * x - DoubleDouble::from_f64(1.0);
        assert!((y.to_f64() / 2f64.powi(-59) - 1.0).abs() < 1e-15);
        let r = DoubleDouble::from_f64(2.0).sqrt();
        assert!((r * r - DoubleDouble::from_f64(2.0)).to_f64().abs() < 1e-31);
        let q = DoubleDouble::from_f64(1.0).div(DoubleDouble::from_f64(7.0))
            * DoubleDouble::from_f64(7.0);
        assert!((q - DoubleDouble::from_f64(1.0)).to_f64().abs() < 1e-31);
    }

    #[test]
    fn fused_multiply_add_is_accurate_to_a_few_u_squared_of_its_terms() {
        // Against the product and the accurate sum (each within ~2u² of its exact value), on
        // full double-words of mixed signs and magnitudes, sums that cancel included.
        let mut state = 0x9e37_79b9_7f4a_7c15u64;
        let mut uniform = || {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            (state >> 11) as f64 / (1u64 << 53) as f64 * 2.0 - 1.0
        };
        let u = f64::EPSILON / 2.0;
        let mut word = |scale: f64| {
            let hi = uniform() * scale;
            let (s, e) = fast_two_sum(hi, uniform() * hi.abs() * u);
            DoubleDouble { hi: s, lo: e }
        };
        let mut worst = 0.0f64;
        for i in 0..100_000 {
            let (a, b) = (word(1.0), word(4.0));
            let c = if i % 4 == 0 {
                -(a * b) + word(1e-12)
            } else {
                word(2.0)
            };
            let fused = a.mul_add(b, c);
            let reference = a * b + c;
            let scale = (a * b).to_f64().abs() + c.to_f64().abs();
            let err = (fused - reference).to_f64().abs() / (u * u * scale);
            worst = worst.max(err);
            assert!(
                fused.lo.abs() <= fused.hi.abs() * u,
                "not normalised: {fused:?}"
            );
        }
        // Dropping the cross terms or b.lo would give errors of order u/u² = 2⁵³.
        assert!(worst < 8.0, "worst error {worst} u² of |a·b| + |c|");
    }
}
