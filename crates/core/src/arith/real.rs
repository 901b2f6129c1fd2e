//! The arithmetic the integrators are written in.
//!
//! Every formula (potentials, sub-maps, indicators' inner products) is written once, generic over
//! [`Real`]. `f64` runs one orbit; [`Lanes<L>`] runs `L` orbits in lockstep, one per SIMD lane.
//! Each lane performs exactly the IEEE operations the scalar code performs, in the same order, so
//! a lane's result is bit-identical to the same orbit run alone (there is a test for it). Fused
//! multiply-adds appear only where [`Real::mul_add`] is called explicitly; the build pins a target
//! level with FMA so they are single instructions on every host.

use core::ops::{Add, AddAssign, Mul, MulAssign, Neg, Sub, SubAssign};

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
    /// Lane `l` holds `f(l)`.
    #[inline(always)]
    pub fn from_fn(f: impl FnMut(usize) -> f64) -> Self {
        Lanes(core::array::from_fn(f))
    }
}

/// Four lanes as one 256-bit vector on x86-64 with AVX and FMA (the pinned target level).
/// LLVM's vectoriser turns the element-wise loops into such vectors too, but not reliably:
/// a change in code around a large inlined step (the batched driver's bookkeeping) can make
/// it split the step into 128-bit halves and scalars joined through memory, about three times
/// slower (figures: docs/performance.md). Written as vectors, the step compiles the same
/// whatever surrounds it. The operations are the same IEEE ones, so the bits are too.
#[cfg(all(target_arch = "x86_64", target_feature = "avx", target_feature = "fma"))]
mod avx4 {
    use super::Lanes;
    use core::arch::x86_64::*;

    #[inline(always)]
    fn load<const L: usize>(a: &Lanes<L>) -> __m256d {
        debug_assert_eq!(L, 4);
        // SAFETY: the caller checked L == 4, so the array holds four f64; AVX is enabled at
        // compile time.
        unsafe { _mm256_loadu_pd(a.0.as_ptr()) }
    }

    #[inline(always)]
    fn store<const L: usize>(v: __m256d) -> Lanes<L> {
        let mut out = Lanes([0.0; L]);
        // SAFETY: as in `load`.
        unsafe { _mm256_storeu_pd(out.0.as_mut_ptr(), v) };
        out
    }

    /// `f` on the two operands' vectors, when `L` is 4.
    #[inline(always)]
    pub(super) fn binary<const L: usize>(
        a: Lanes<L>,
        b: Lanes<L>,
        f: impl Fn(__m256d, __m256d) -> __m256d,
    ) -> Option<Lanes<L>> {
        (L == 4).then(|| store(f(load(&a), load(&b))))
    }

    #[inline(always)]
    pub(super) fn add<const L: usize>(a: Lanes<L>, b: Lanes<L>) -> Option<Lanes<L>> {
        // SAFETY (all closures below): AVX and FMA are enabled at compile time.
        binary(a, b, |x, y| unsafe { _mm256_add_pd(x, y) })
    }

    #[inline(always)]
    pub(super) fn sub<const L: usize>(a: Lanes<L>, b: Lanes<L>) -> Option<Lanes<L>> {
        binary(a, b, |x, y| unsafe { _mm256_sub_pd(x, y) })
    }

    #[inline(always)]
    pub(super) fn mul<const L: usize>(a: Lanes<L>, b: Lanes<L>) -> Option<Lanes<L>> {
        binary(a, b, |x, y| unsafe { _mm256_mul_pd(x, y) })
    }

    /// Negation flips the sign bit, as `-x` does for every f64 (NaN included).
    #[inline(always)]
    pub(super) fn neg<const L: usize>(a: Lanes<L>) -> Option<Lanes<L>> {
        binary(a, a, |x, _| unsafe {
            _mm256_xor_pd(x, _mm256_set1_pd(-0.0))
        })
    }

    #[inline(always)]
    pub(super) fn mul_add<const L: usize>(
        a: Lanes<L>,
        b: Lanes<L>,
        c: Lanes<L>,
    ) -> Option<Lanes<L>> {
        (L == 4).then(|| store(unsafe { _mm256_fmadd_pd(load(&a), load(&b), load(&c)) }))
    }

    /// The lanes where the comparison `P` (an `_CMP_*` predicate) holds, as bits, when `L`
    /// is 4.
    #[inline(always)]
    pub(super) fn cmp_bits<const L: usize, const P: i32>(a: Lanes<L>, b: Lanes<L>) -> Option<u64> {
        // SAFETY: AVX is enabled at compile time.
        (L == 4)
            .then(|| unsafe { _mm256_movemask_pd(_mm256_cmp_pd::<P>(load(&a), load(&b))) as u64 })
    }

    pub(super) const LT: i32 = _CMP_LT_OQ;
    pub(super) const GE: i32 = _CMP_GE_OQ;
    pub(super) const NLE: i32 = _CMP_NLE_UQ;
    pub(super) const NLT: i32 = _CMP_NLT_UQ;
    pub(super) const NGT: i32 = _CMP_NGT_UQ;
}

/// The element-wise fallback where [`avx4`] does not apply.
#[cfg(not(all(target_arch = "x86_64", target_feature = "avx", target_feature = "fma")))]
mod avx4 {
    use super::Lanes;

    #[inline(always)]
    pub(super) fn add<const L: usize>(_: Lanes<L>, _: Lanes<L>) -> Option<Lanes<L>> {
        None
    }
    #[inline(always)]
    pub(super) fn sub<const L: usize>(_: Lanes<L>, _: Lanes<L>) -> Option<Lanes<L>> {
        None
    }
    #[inline(always)]
    pub(super) fn mul<const L: usize>(_: Lanes<L>, _: Lanes<L>) -> Option<Lanes<L>> {
        None
    }
    #[inline(always)]
    pub(super) fn neg<const L: usize>(_: Lanes<L>) -> Option<Lanes<L>> {
        None
    }
    #[inline(always)]
    pub(super) fn mul_add<const L: usize>(
        _: Lanes<L>,
        _: Lanes<L>,
        _: Lanes<L>,
    ) -> Option<Lanes<L>> {
        None
    }
    #[inline(always)]
    pub(super) fn cmp_bits<const L: usize, const P: i32>(_: Lanes<L>, _: Lanes<L>) -> Option<u64> {
        None
    }

    pub(super) const LT: i32 = 0;
    pub(super) const GE: i32 = 1;
    pub(super) const NLE: i32 = 2;
    pub(super) const NLT: i32 = 3;
    pub(super) const NGT: i32 = 4;
}

/// The lanes where `f` holds, as bits (lane `l` is bit `l`; at most 64 lanes).
#[inline(always)]
pub fn lane_bits<const L: usize>(f: impl Fn(usize) -> bool) -> u64 {
    const { assert!(L <= 64, "lane masks hold at most 64 lanes") };
    (0..L).fold(0, |bits, l| bits | (u64::from(f(l)) << l))
}

/// Lane-wise comparisons as bit masks (lane `l` is bit `l`): one vector compare and a mask
/// extraction where [`avx4`] applies. The `not_*` forms are true where either side is NaN.
impl<const L: usize> Lanes<L> {
    /// Lanes where `self < rhs`.
    #[inline(always)]
    pub fn lt_bits(self, rhs: Self) -> u64 {
        avx4::cmp_bits::<L, { avx4::LT }>(self, rhs)
            .unwrap_or_else(|| lane_bits::<L>(|l| self.0[l] < rhs.0[l]))
    }
    /// Lanes where `self >= rhs`.
    #[inline(always)]
    pub fn ge_bits(self, rhs: Self) -> u64 {
        avx4::cmp_bits::<L, { avx4::GE }>(self, rhs)
            .unwrap_or_else(|| lane_bits::<L>(|l| self.0[l] >= rhs.0[l]))
    }
    /// Lanes where `!(self <= rhs)`.
    #[inline(always)]
    pub fn not_le_bits(self, rhs: Self) -> u64 {
        #[allow(clippy::neg_cmp_op_on_partial_ord)]
        avx4::cmp_bits::<L, { avx4::NLE }>(self, rhs)
            .unwrap_or_else(|| lane_bits::<L>(|l| !(self.0[l] <= rhs.0[l])))
    }
    /// Lanes where `!(self < rhs)`.
    #[inline(always)]
    pub fn not_lt_bits(self, rhs: Self) -> u64 {
        #[allow(clippy::neg_cmp_op_on_partial_ord)]
        avx4::cmp_bits::<L, { avx4::NLT }>(self, rhs)
            .unwrap_or_else(|| lane_bits::<L>(|l| !(self.0[l] < rhs.0[l])))
    }
    /// Lanes where `!(self > rhs)`.
    #[inline(always)]
    pub fn not_gt_bits(self, rhs: Self) -> u64 {
        #[allow(clippy::neg_cmp_op_on_partial_ord)]
        avx4::cmp_bits::<L, { avx4::NGT }>(self, rhs)
            .unwrap_or_else(|| lane_bits::<L>(|l| !(self.0[l] > rhs.0[l])))
    }
}

macro_rules! lane_binop {
    ($trait:ident, $method:ident, $op:tt, $assign_trait:ident, $assign_method:ident) => {
        impl<const L: usize> $trait for Lanes<L> {
            type Output = Self;
            #[inline(always)]
            fn $method(self, rhs: Self) -> Self {
                avx4::$method(self, rhs)
                    .unwrap_or_else(|| Lanes(core::array::from_fn(|i| self.0[i] $op rhs.0[i])))
            }
        }
        impl<const L: usize> $assign_trait for Lanes<L> {
            #[inline(always)]
            fn $assign_method(&mut self, rhs: Self) {
                *self = *self $op rhs;
            }
        }
    };
}
lane_binop!(Add, add, +, AddAssign, add_assign);
lane_binop!(Sub, sub, -, SubAssign, sub_assign);
lane_binop!(Mul, mul, *, MulAssign, mul_assign);

impl<const L: usize> Neg for Lanes<L> {
    type Output = Self;
    #[inline(always)]
    fn neg(self) -> Self {
        avx4::neg(self).unwrap_or_else(|| Lanes(core::array::from_fn(|i| -self.0[i])))
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
        avx4::mul_add(self, a, b).unwrap_or_else(|| {
            Lanes(core::array::from_fn(|i| {
                f64::mul_add(self.0[i], a.0[i], b.0[i])
            }))
        })
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

#[cfg(test)]
mod tests {
    use super::*;

    /// Values that exercise every comparison and rounding corner: signed zeros, infinities,
    /// NaN, subnormals and ordinary numbers of both signs.
    const SPECIAL: [f64; 10] = [
        0.0,
        -0.0,
        1.5,
        -2.25,
        f64::INFINITY,
        f64::NEG_INFINITY,
        f64::NAN,
        f64::MIN_POSITIVE / 8.0,
        1e300,
        -3.0e-7,
    ];

    fn lanes<const L: usize>(seed: usize) -> Lanes<L> {
        Lanes::from_fn(|l| SPECIAL[(seed * 7 + l * 3) % SPECIAL.len()])
    }

    /// Arithmetic and comparisons of `L` lanes agree bit for bit with the scalar operations
    /// lane by lane (the 4-lane AVX form and the element-wise one alike).
    fn agree<const L: usize>() {
        for s in 0..SPECIAL.len() {
            let (a, b, c) = (lanes::<L>(s), lanes::<L>(s + 1), lanes::<L>(s + 5));
            let same = |x: Lanes<L>, f: &dyn Fn(usize) -> f64| {
                for l in 0..L {
                    assert_eq!(x.0[l].to_bits(), f(l).to_bits(), "lane {l}");
                }
            };
            same(a + b, &|l| a.0[l] + b.0[l]);
            same(a - b, &|l| a.0[l] - b.0[l]);
            same(a * b, &|l| a.0[l] * b.0[l]);
            same(-a, &|l| -a.0[l]);
            same(a.mul_add(b, c), &|l| a.0[l].mul_add(b.0[l], c.0[l]));
            let mut d = a;
            d += b;
            same(d, &|l| a.0[l] + b.0[l]);
            d -= c;
            same(d, &|l| a.0[l] + b.0[l] - c.0[l]);
            // Against another vector, itself (equal values) and one holding 0.0 where `a`
            // holds -0.0 and the like (seeds 3 apart).
            for b in [b, a, lanes::<L>(s + 3)] {
                #[allow(clippy::neg_cmp_op_on_partial_ord)]
                let want = [
                    lane_bits::<L>(|l| a.0[l] < b.0[l]),
                    lane_bits::<L>(|l| a.0[l] >= b.0[l]),
                    lane_bits::<L>(|l| !(a.0[l] <= b.0[l])),
                    lane_bits::<L>(|l| !(a.0[l] < b.0[l])),
                    lane_bits::<L>(|l| !(a.0[l] > b.0[l])),
                ];
                let got = [
                    a.lt_bits(b),
                    a.ge_bits(b),
                    a.not_le_bits(b),
                    a.not_lt_bits(b),
                    a.not_gt_bits(b),
                ];
                assert_eq!(got, want, "seed {s}");
            }
        }
    }

    #[test]
    fn lane_operations_equal_scalar_ones_bit_for_bit() {
        agree::<1>();
        agree::<3>();
        agree::<4>();
        agree::<8>();
    }

    #[test]
    fn lane_bits_sets_bit_l_for_lane_l() {
        assert_eq!(lane_bits::<4>(|l| l == 2), 0b100);
        assert_eq!(lane_bits::<64>(|l| l == 63), 1 << 63);
        let x = Lanes([1.0, f64::NAN, -1.0, 0.0]);
        assert_eq!(x.lt_bits(Lanes::splat(0.0)), 0b0100);
        assert_eq!(x.not_le_bits(Lanes::splat(0.0)), 0b0011);
    }
}
