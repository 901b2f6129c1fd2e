//! Chaos indicators from deviation vectors: SALI, GALI_k and the maximal Lyapunov exponent.
//!
//! Deviation vectors are kept finite by rescaling with exact powers of two (see
//! [`pow2_rescale`]): every floating-point operation commutes exactly with such a scaling, so
//! the normalised vectors — hence SALI and GALI — are bit-identical to those of unit
//! renormalisation at every τ, with fewer roundings, and ln‖w‖ is carried as an integer count of
//! binary orders of magnitude plus the logarithm of the current norm.

use nalgebra::DMatrix;

/// Norm² bounds outside which a deviation vector is rescaled.
pub(crate) const RESCALE_ABOVE: f64 = f64::from_bits((1023 + 256) << 52); // 2^256
pub(crate) const RESCALE_BELOW: f64 = f64::from_bits((1023 - 256) << 52); // 2^-256

/// If the squared norm `n2` has left [2^-256, 2^256], the power of two `s` that brings the norm
/// back to [1, 4) and its exponent: the vector must be multiplied by `s = 2^-e`. `None` when the
/// vector needs no rescaling. `n2` must be finite and positive.
#[inline(always)]
pub fn pow2_rescale(n2: f64) -> Option<(f64, i64)> {
    if in_band(n2) {
        return None;
    }
    Some(pow2_factor(n2))
}

#[cold]
fn pow2_factor(n2: f64) -> (f64, i64) {
    let biased = ((n2.to_bits() >> 52) & 0x7ff) as i64;
    let e = (biased - 1023).div_euclid(2);
    (f64::from_bits(((1023 - e) as u64) << 52), e)
}

/// Squared norm of the phase-space vector (δq, δp).
#[inline(always)]
pub fn norm2<const N: usize>(dq: &[f64; N], dp: &[f64; N]) -> f64 {
    crate::arith::real::dot(dq, dq) + crate::arith::real::dot(dp, dp)
}

/// SALI = min(‖ŵ1 + ŵ2‖, ‖ŵ1 − ŵ2‖) of two deviation vectors given as (δq, δp).
pub fn sali<const N: usize>(w1: (&[f64; N], &[f64; N]), w2: (&[f64; N], &[f64; N])) -> f64 {
    let s1 = 1.0 / norm2(w1.0, w1.1).sqrt();
    let s2 = 1.0 / norm2(w2.0, w2.1).sqrt();
    let (mut plus, mut minus) = (0.0f64, 0.0f64);
    for (a, b) in w1.0.iter().chain(w1.1).zip(w2.0.iter().chain(w2.1)) {
        let (u, v) = (a * s1, b * s2);
        plus = (u + v).mul_add(u + v, plus);
        minus = (u - v).mul_add(u - v, minus);
    }
    plus.min(minus).sqrt()
}

/// Whether the two vectors may be within SALI `theta` of (anti)parallel, decided from their
/// squared norms `a`, `b` and inner product `c` without roots or divisions. Exact SALI is only
/// needed when this says yes. SALI² = 2 − 2|cos| ≈ 1 − cos² near alignment; the margin keeps
/// the test conservative for any theta down to the ~1e-7 where cos² stops resolving it.
#[inline(always)]
pub fn may_be_aligned(a: f64, b: f64, c: f64, theta: f64) -> bool {
    c * c >= a * b * alignment_factor(theta)
}

/// The smallest threshold [`may_be_below`] resolves: below it, it passes everything.
pub const MINORS_RESOLVE: f64 = 1e-13;

/// Whether SALI of `w1` and `w2` may be below `theta`; `false` proves it is not. Where
/// [`may_be_aligned`] passes everything within ~3e-7 of alignment (cos² is 1 to f64's
/// precision there), this resolves angles down to ~1e-15: the sine of the angle between the
/// vectors comes from their 2×2 minors (Lagrange's identity |w1|²|w2|² sin² =
/// Σ_{i<j} (w1_i w2_j − w1_j w2_i)², a sum of squares, so nothing cancels between its terms),
/// and SALI = 2 sin(θ'/2) ≥ sin θ' for the angle θ' ≤ π/2 between the two lines. The test asks
/// for sin θ' ≥ 2·theta, which leaves room for the minors' rounding (~1e-15 of |w1||w2|);
/// below `theta` = 1e-13 it passes everything.
#[inline(always)]
pub fn may_be_below<const N: usize>(
    w1: (&[f64; N], &[f64; N]),
    w2: (&[f64; N], &[f64; N]),
    theta: f64,
) -> bool {
    if theta < MINORS_RESOLVE {
        return true;
    }
    let z1 = |i: usize| if i < N { w1.0[i] } else { w1.1[i - N] };
    let z2 = |i: usize| if i < N { w2.0[i] } else { w2.1[i - N] };
    let mut g = 0.0f64;
    for i in 0..2 * N {
        for j in i + 1..2 * N {
            let m = z1(i).mul_add(z2(j), -(z1(j) * z2(i)));
            g = m.mul_add(m, g);
        }
    }
    g < 4.0 * theta * theta * norm2(w1.0, w1.1) * norm2(w2.0, w2.1)
}

/// The factor of [`may_be_aligned`], hoisted by callers that screen many vectors.
#[inline(always)]
pub fn alignment_factor(theta: f64) -> f64 {
    1.0 - (4.0 * theta * theta + 1e-13)
}

/// Whether a squared norm lies inside the band where no rescaling is needed.
#[inline(always)]
pub fn in_band(n2: f64) -> bool {
    n2 < RESCALE_ABOVE && n2 > RESCALE_BELOW
}

/// The lanes whose squared norm lies outside [`in_band`]'s band (or is NaN), as bits.
#[inline(always)]
pub fn out_of_band_bits<const L: usize>(n2: crate::arith::real::Lanes<L>) -> u64 {
    use crate::arith::real::Real;
    n2.not_lt_bits(Real::splat(RESCALE_ABOVE)) | n2.not_gt_bits(Real::splat(RESCALE_BELOW))
}

/// GALI_k for k = 2..=vectors.len(): the volume spanned by the first k normalised deviation
/// vectors, as the product of |R_ii| of a Householder QR (never a Gram determinant, whose square
/// loses everything below ~1e-8).
pub fn gali<const N: usize>(dq: &[[f64; N]], dp: &[[f64; N]]) -> Vec<f64> {
    let k = dq.len();
    let mut out = Vec::with_capacity(k.saturating_sub(1));
    let m = DMatrix::from_fn(2 * N, k, |r, c| {
        let n = norm2(&dq[c], &dp[c]).sqrt();
        let v = if r < N { dq[c][r] } else { dp[c][r - N] };
        v / n
    });
    for kk in 2..=k {
        let qr = m.columns(0, kk).into_owned().qr();
        let r = qr.r();
        out.push((0..kk).map(|i| r[(i, i)].abs()).product());
    }
    out
}

/// Accumulates ln‖w‖ of a deviation vector across power-of-two rescalings.
#[derive(Clone, Copy, Debug, Default)]
pub struct LogGrowth {
    /// Σ of the exponents e of the rescalings by 2^-e.
    pub binary_orders: i64,
}

impl LogGrowth {
    /// ln of the vector's norm relative to its initial unit norm, given its current squared norm.
    pub fn ln_norm(&self, n2: f64) -> f64 {
        0.5 * n2.ln() + self.binary_orders as f64 * core::f64::consts::LN_2
    }
}

/// MEGNO and the FLI of one orbit, from ln‖w₁‖ of its first deviation vector (unit at t = 0).
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize)]
pub struct GrowthIndicators {
    /// MEGNO Y(t) = (2/t) ∫₀ᵗ s d(ln‖w₁‖) (Cincotta & Simó 2000).
    pub megno: f64,
    /// Its running mean ⟨Y⟩(t) = (1/t) ∫₀ᵗ Y ds: → 2 on quasi-periodic orbits, → 0 on stable
    /// periodic ones, ≈ λt/2 on chaotic ones.
    pub megno_mean: f64,
    /// The fast Lyapunov indicator sup_{s ≤ t} ln‖w₁(s)‖ (Froeschlé, Lega & Gonczi 1997): grows
    /// like ln t on regular orbits and like λt on chaotic ones.
    pub fli: f64,
}

/// Accumulates [`GrowthIndicators`] from ln‖w₁‖ at the nodes of an orbit (its steps, or its
/// multiples of τ). With L = ln‖w₁‖, Y(t) = 2[L(t) − (1/t) ∫₀ᵗ L ds] (integration by parts of
/// the definition), so the renormalised vectors' log-growth is all it needs; both integrals are
/// trapezoids over the nodes. A `Copy` value with plain arithmetic, so the scalar and the SIMD
/// drivers that feed it the same nodes agree bit for bit.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct GrowthHistory {
    t: f64,
    ln_norm: f64,
    ln_norm_integral: f64,
    megno: f64,
    megno_integral: f64,
    ln_norm_max: f64,
}

impl GrowthHistory {
    /// A history with no node yet.
    pub const NEW: GrowthHistory = GrowthHistory {
        t: 0.0,
        ln_norm: 0.0,
        ln_norm_integral: 0.0,
        megno: 0.0,
        megno_integral: 0.0,
        ln_norm_max: 0.0,
    };

    /// Takes the node (t, ln‖w₁(t)‖), t after the previous node's.
    #[inline]
    pub fn note(&mut self, t: f64, ln_norm: f64) {
        let h = t - self.t;
        self.ln_norm_integral += 0.5 * h * (self.ln_norm + ln_norm);
        let megno = 2.0 * (ln_norm - self.ln_norm_integral / t);
        self.megno_integral += 0.5 * h * (self.megno + megno);
        self.t = t;
        self.ln_norm = ln_norm;
        self.megno = megno;
        self.ln_norm_max = self.ln_norm_max.max(ln_norm);
    }

    /// The indicators at the last node (zeros before any).
    pub fn values(&self) -> GrowthIndicators {
        GrowthIndicators {
            megno: self.megno,
            megno_mean: if self.t > 0.0 {
                self.megno_integral / self.t
            } else {
                0.0
            },
            fli: self.ln_norm_max,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Linear growth (a regular orbit's deviation vectors) gives Y → 2 and ⟨Y⟩ → 2;
    /// exponential growth e^{λt} gives Y = λt and ⟨Y⟩ = λt/2; FLI is the largest ln‖w‖.
    #[test]
    fn growth_history_of_linear_and_exponential_growth() {
        let (mut linear, mut exponential) = (GrowthHistory::NEW, GrowthHistory::NEW);
        let (tau, lambda) = (0.01, 0.05);
        for n in 1..=1_000_000u64 {
            let t = n as f64 * tau;
            linear.note(t, (1.0 + t).ln());
            exponential.note(t, lambda * t);
        }
        let l = linear.values();
        assert!((l.megno - 2.0).abs() < 2e-3, "{l:?}");
        assert!((l.megno_mean - 2.0).abs() < 2e-2, "{l:?}");
        assert!((l.fli - 10_001f64.ln()).abs() < 1e-9, "{l:?}");
        let e = exponential.values();
        let t = 1e4;
        assert!((e.megno / (lambda * t) - 1.0).abs() < 1e-6, "{e:?}");
        assert!(
            (e.megno_mean / (lambda * t / 2.0) - 1.0).abs() < 1e-6,
            "{e:?}"
        );
        assert_eq!(e.fli, lambda * t);
        // A shrinking vector keeps the FLI at its supremum.
        let mut shrinking = GrowthHistory::NEW;
        shrinking.note(1.0, 3.0);
        shrinking.note(2.0, -1.0);
        assert_eq!(shrinking.values().fli, 3.0);
    }

    #[test]
    fn pow2_rescale_is_exact_and_lands_in_range() {
        for n2 in [1e-200, 3.7e-90, 2.5e80, 1e300, f64::MIN_POSITIVE * 3.0] {
            let (s, e) = pow2_rescale(n2).unwrap();
            assert_eq!(s, 2f64.powi(-e as i32));
            // The norm is scaled by s, its square by s².
            let scaled = n2 * s * s;
            assert!((1.0..4.0).contains(&scaled), "{n2} -> {scaled}");
        }
        assert!(pow2_rescale(1.0).is_none());
        assert!(pow2_rescale(1e70).is_none());
    }

    #[test]
    fn sali_of_known_configurations() {
        let e1 = ([1.0, 0.0], [0.0, 0.0]);
        let e2 = ([0.0, 1.0], [0.0, 0.0]);
        let s = sali((&e1.0, &e1.1), (&e2.0, &e2.1));
        assert!((s - 2f64.sqrt()).abs() < 1e-15);
        // Anti-parallel at angle 1e-9 from each other: SALI = 2 sin(θ/2) ≈ 1e-9.
        let th = 1e-9f64;
        let a = ([1.0, 0.0], [0.0, 0.0]);
        let b = ([-3.0 * th.cos(), -3.0 * th.sin()], [0.0, 0.0]);
        let s = sali((&a.0, &a.1), (&b.0, &b.1));
        assert!((s / th - 1.0).abs() < 1e-6, "{s}");
    }

    #[test]
    fn alignment_prefilter_never_misses_a_small_sali() {
        for &th in &[1e-3f64, 1e-5, 1e-7, 1e-9] {
            let a = [1.0, 0.5, -0.2, 0.1];
            let b = [1.0 + th, 0.5, -0.2, 0.1 - th];
            let n2a: f64 = a.iter().map(|x| x * x).sum();
            let n2b: f64 = b.iter().map(|x| x * x).sum();
            let c: f64 = a.iter().zip(&b).map(|(x, y)| x * y).sum();
            let s = sali(
                (&[a[0], a[1]], &[a[2], a[3]]),
                (&[b[0], b[1]], &[b[2], b[3]]),
            );
            if s < 1e-8 {
                assert!(may_be_aligned(n2a, n2b, c, 1e-8));
            }
            if s < 1e-4 {
                assert!(may_be_aligned(n2a, n2b, c, 1e-4));
            }
        }
        // Orthogonal vectors are never flagged.
        assert!(!may_be_aligned(1.0, 1.0, 0.0, 1e-8));
    }

    /// The minor test never clears a pair whose SALI is below the threshold, and it clears
    /// pairs 3e-8 to 2e-7 from alignment, which the cos² test passes on.
    #[test]
    fn minor_test_never_misses_a_small_sali_and_resolves_below_the_cosine_test() {
        let mut s = 0x9e37_79b9_7f4a_7c15u64;
        let mut rnd = move || {
            s ^= s << 13;
            s ^= s >> 7;
            s ^= s << 17;
            (s >> 11) as f64 / (1u64 << 53) as f64 - 0.5
        };
        let theta = 1e-8;
        let (mut cleared, mut near, mut passed_by_cosine) = (0, 0, 0);
        for k in 0..200_000 {
            let a: [f64; 4] = core::array::from_fn(|_| rnd());
            // b = ±scale·(a + angle·d): angles from 1e-12 to 1e-5 around the threshold.
            let angle = 10f64.powf(-12.0 + 7.0 * (rnd() + 0.5));
            let d: [f64; 4] = core::array::from_fn(|_| rnd());
            let scale = if k % 2 == 0 { 3.7 } else { -0.02 };
            let b: [f64; 4] = core::array::from_fn(|i| scale * (a[i] + angle * d[i]));
            let (w1, w2) = (([a[0], a[1]], [a[2], a[3]]), ([b[0], b[1]], [b[2], b[3]]));
            let exact = sali((&w1.0, &w1.1), (&w2.0, &w2.1));
            let maybe = may_be_below((&w1.0, &w1.1), (&w2.0, &w2.1), theta);
            if exact < theta {
                assert!(maybe, "SALI {exact:e} cleared");
            }
            if !maybe {
                cleared += 1;
            }
            let c: f64 = a.iter().zip(&b).map(|(x, y)| x * y).sum();
            let (n2a, n2b): (f64, f64) = (norm2(&w1.0, &w1.1), norm2(&w2.0, &w2.1));
            if (3e-8..2e-7).contains(&exact) {
                near += 1;
                if may_be_aligned(n2a, n2b, c, theta) {
                    passed_by_cosine += 1;
                }
                assert!(!maybe, "SALI {exact:e} not cleared");
            }
        }
        assert!(cleared > 50_000 && near > 1_000, "{cleared} {near}");
        assert!(
            passed_by_cosine * 10 > near * 9,
            "{passed_by_cosine} of {near}"
        );
    }

    #[test]
    fn gali_equals_singular_value_product_and_sali_relation() {
        // Columns with known volume: orthogonal unit vectors give 1; a sheared pair gives |sin|.
        let th = 0.3f64;
        let dq = [[1.0, 0.0], [th.cos(), th.sin()], [0.0, 0.0], [0.0, 0.0]];
        let dp = [[0.0, 0.0], [0.0, 0.0], [1.0, 0.0], [0.0, 2.0]];
        let g = gali(&dq, &dp);
        assert_eq!(g.len(), 3);
        assert!((g[0] - th.sin()).abs() < 1e-15);
        assert!((g[1] - th.sin()).abs() < 1e-15);
        assert!((g[2] - th.sin()).abs() < 1e-15);
        // GALI_2 = ‖ŵ1+ŵ2‖·‖ŵ1−ŵ2‖/2 and ‖ŵ1+ŵ2‖² + ‖ŵ1−ŵ2‖² = 4, so SALI/√2 ≤ GALI_2 ≤ SALI.
        let s = sali((&dq[0], &dp[0]), (&dq[1], &dp[1]));
        assert!(g[0] <= s * (1.0 + 1e-15) && s <= 2f64.sqrt() * g[0] * (1.0 + 1e-15));
    }

    #[test]
    fn tiny_gali_is_resolved_where_a_gram_determinant_would_not_be() {
        let eps = 1e-12f64;
        let dq = [[1.0, 0.0], [1.0, eps]];
        let dp = [[0.0, 0.0], [0.0, 0.0]];
        let g = gali(&dq, &dp);
        assert!((g[0] / eps - 1.0).abs() < 1e-3, "{}", g[0]);
    }
}
