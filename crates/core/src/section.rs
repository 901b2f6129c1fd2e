//! The surface of section q1 = 0, p1 > 0: initial conditions on it and crossing location.

use crate::hamiltonian::Hamiltonian;
use crate::tangent::TangentMap;

/// A point where the orbit crosses q1 = 0 upwards (p1 > 0).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Crossing<const N: usize> {
    pub t: f64,
    pub q: [f64; N],
    pub p: [f64; N],
}

/// Why a point of the section cannot start an orbit.
#[derive(Clone, Debug, PartialEq)]
pub enum SectionError {
    /// 2(E − V) − |p_rest|² ≤ 0: the point is outside the energy surface's section.
    NotOnSection {
        radicand: f64,
    },
    NonFinite,
}

impl std::fmt::Display for SectionError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            SectionError::NotOnSection { radicand } => write!(
                f,
                "the point is not on the section at this energy (p1² = {radicand:.3e}, must be > 0)"
            ),
            SectionError::NonFinite => write!(f, "coordinates and energy must be finite"),
        }
    }
}

/// p1² = 2(E − V(q)) − Σ_{i≥2} p_i² for q = (0, q_rest), p = (·, p_rest).
pub fn p1_squared<H: Hamiltonian<N>, const N: usize>(
    ham: &H,
    energy: f64,
    q: &[f64; N],
    p: &[f64; N],
) -> f64 {
    let rest: f64 = p[1..].iter().map(|x| x * x).sum();
    2.0 * (energy - ham.potential(q)) - rest
}

/// The phase-space point on the section q1 = 0 with the given other coordinates and energy,
/// p1 > 0 from energy conservation.
pub fn on_section<H: Hamiltonian<N>, const N: usize>(
    ham: &H,
    energy: f64,
    q_rest: &[f64],
    p_rest: &[f64],
) -> Result<([f64; N], [f64; N]), SectionError> {
    let mut q = [0.0; N];
    let mut p = [0.0; N];
    q[1..].copy_from_slice(q_rest);
    p[1..].copy_from_slice(p_rest);
    if !energy.is_finite() || q.iter().chain(&p).any(|x| !x.is_finite()) {
        return Err(SectionError::NonFinite);
    }
    let r = p1_squared(ham, energy, &q, &p);
    if r.is_nan() || r <= 0.0 {
        return Err(SectionError::NotOnSection { radicand: r });
    }
    p[0] = r.sqrt();
    Ok((q, p))
}

/// Locates the upward crossing of q1 = 0 inside the step that starts at (`q`, `p`, `t`) with
/// q1 < 0 and ends (one step τ later) with q1 ≥ 0.
///
/// Solves q1(Φ_h(x)) = 0 for h ∈ (0, τ], Φ_h being one step of the same splitting scheme with
/// step h, by Newton's method (dq1/dh ≈ p1) kept inside a bisection bracket, so a crossing
/// nearly tangent to the section (p1 → 0) never divides by ~0. The partial steps run on a copy:
/// the symplectic trajectory itself is untouched. The error is the scheme's local error over
/// h, O(h^(p+1)).
pub fn locate_upward<H: Hamiltonian<N>, const N: usize>(
    map: &TangentMap<'_, H>,
    q: &[f64; N],
    p: &[f64; N],
    t: f64,
) -> Crossing<N> {
    let tau = map.tau();
    let at = |h: f64| {
        let (mut qh, mut ph) = (*q, *p);
        map.orbit_step(&mut qh, &mut ph, h);
        (qh, ph)
    };
    let (mut lo, mut hi) = (0.0, tau);
    let mut h = if p[0] > 0.0 {
        (-q[0] / p[0]).clamp(0.0, tau)
    } else {
        0.5 * tau
    };
    let (mut qh, mut ph) = at(h);
    for _ in 0..100 {
        let f = qh[0];
        if f == 0.0 {
            break;
        }
        if f < 0.0 {
            lo = h;
        } else {
            hi = h;
        }
        let newton = h - f / ph[0];
        let next = if ph[0] > 0.0 && newton > lo && newton < hi {
            newton
        } else {
            0.5 * (lo + hi)
        };
        let done =
            (next - h).abs() <= 4.0 * f64::EPSILON * tau || hi - lo <= 4.0 * f64::EPSILON * tau;
        h = next;
        (qh, ph) = at(h);
        if done {
            break;
        }
    }
    Crossing {
        t: t + h,
        q: qh,
        p: ph,
    }
}
