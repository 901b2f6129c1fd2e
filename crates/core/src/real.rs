//! The arithmetic the integrators are written in.
//!
//! Every formula (potentials, sub-maps, indicators' inner products) is written once, generic over
//! [`Real`]. `f64` runs one orbit; [`Lanes<L>`] runs `L` orbits in lockstep, one per SIMD lane.
//! Each lane performs exactly the IEEE operations the scalar code performs, in the same order, so
//! a lane's result is bit-identical to the same orbit run alone (there is a test for it). Fused
//! multiply-adds appear only where [`Real::mul_add`] is called explicitly; the build pins a target
//! level with FMA so they are single instructions on every host.

use core::ops::{Add, AddAssign, Mul, Neg, Sub, SubAssign};

/// A field of floating-point numbers: `f64`, or `f64` lanes.
pub trait Real:
    Copy
    + Add<Output = Self>
    + Sub<Output = Self>
    + Mul<Output = Self>
    + Neg<Output = Self>
    + AddAssign
    + SubAssign
    + Send
    + Sync
    + 'static
    + core::fmt::Debug
{
    /// The constant `x` in every lane.
    fn splat(x: f64) -> Self;
    /// `self * a + b` with one rounding.
    fn mul_add(self, a: Self, b: Self) -> Self;
    /// num / den in this type's precision (Taylor recursions divide by k + 1).
    #[inline(always)]
    fn ratio(num: f64, den: f64) -> Self {
        Self::splat(num / den)
    }
    /// The type of this one's leading word: itself for f64 and lanes of f64, the high word's
    /// type for double-double. Work whose rounding is far below the error a method allows
    /// anyway runs in it (the Taylor recursion's high orders, see `taylor::lead_order`).
    type Lead: Real;
    /// Whether this type carries more precision than its leading word.
    const EXTENDED: bool;
    /// The leading word (the value itself when not [`Real::EXTENDED`]).
    fn lead(self) -> Self::Lead;
    /// The value of a leading word, exactly.
    fn from_lead(x: Self::Lead) -> Self;
}

impl Real for f64 {
    type Lead = f64;
    const EXTENDED: bool = false;
    #[inline(always)]
    fn lead(self) -> f64 {
        self
    }
    #[inline(always)]
    fn from_lead(x: f64) -> Self {
        x
    }
    #[inline(always)]
    fn splat(x: f64) -> Self {
        x
    }
    #[inline(always)]
    fn mul_add(self, a: Self, b: Self) -> Self {
        f64::mul_add(self, a, b)
    }
}

/// `L` independent `f64` values operated on together (structure of arrays).
#[derive(Clone, Copy, Debug, PartialEq)]
#[repr(C, align(32))]
pub struct Lanes<const L: usize>(pub [f64; L]);

impl<const L: usize> Lanes<L> {
    #[inline(always)]
    pub fn from_fn(f: impl FnMut(usize) -> f64) -> Self {
        Lanes(core::array::from_fn(f))
    }
}

macro_rules! lane_binop {
    ($trait:ident, $method:ident, $op:tt, $assign_trait:ident, $assign_method:ident) => {
        impl<const L: usize> $trait for Lanes<L> {
            type Output = Self;
            #[inline(always)]
            fn $method(self, rhs: Self) -> Self {
                Lanes(core::array::from_fn(|i| self.0[i] $op rhs.0[i]))
            }
        }
        impl<const L: usize> $assign_trait for Lanes<L> {
            #[inline(always)]
            fn $assign_method(&mut self, rhs: Self) {
                for i in 0..L {
                    self.0[i] = self.0[i] $op rhs.0[i];
                }
            }
        }
    };
}
lane_binop!(Add, add, +, AddAssign, add_assign);
lane_binop!(Sub, sub, -, SubAssign, sub_assign);

impl<const L: usize> Mul for Lanes<L> {
    type Output = Self;
    #[inline(always)]
    fn mul(self, rhs: Self) -> Self {
        Lanes(core::array::from_fn(|i| self.0[i] * rhs.0[i]))
    }
}

impl<const L: usize> Neg for Lanes<L> {
    type Output = Self;
    #[inline(always)]
    fn neg(self) -> Self {
        Lanes(core::array::from_fn(|i| -self.0[i]))
    }
}

impl<const L: usize> Real for Lanes<L> {
    type Lead = Self;
    const EXTENDED: bool = false;
    #[inline(always)]
    fn lead(self) -> Self {
        self
    }
    #[inline(always)]
    fn from_lead(x: Self) -> Self {
        x
    }
    #[inline(always)]
    fn splat(x: f64) -> Self {
        Lanes([x; L])
    }
    #[inline(always)]
    fn mul_add(self, a: Self, b: Self) -> Self {
        Lanes(core::array::from_fn(|i| {
            f64::mul_add(self.0[i], a.0[i], b.0[i])
        }))
    }
}

/// Dot product of two `N`-vectors, summed left to right.
#[inline(always)]
pub fn dot<T: Real, const N: usize>(a: &[T; N], b: &[T; N]) -> T {
    let mut s = a[0] * b[0];
    for i in 1..N {
        s = a[i].mul_add(b[i], s);
    }
    s
}
