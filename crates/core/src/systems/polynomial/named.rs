//! Classic systems given by name, written as potentials for the polynomial path: every method
//! runs on them as on any potential given as text, and the text they expand to is what a run
//! records.

/// The FPU-β chain of `n` particles with fixed ends and quartic coupling `beta`:
/// V = Σ_{i=0}^{n} [(q_{i+1} − q_i)²/2 + β (q_{i+1} − q_i)⁴/4] with q_0 = q_{n+1} = 0, so n + 1
/// springs (Fermi, Pasta & Ulam 1955; the fixed-end form of Boost.odeint's FPU lattice
/// tutorial). As text in q1…qn; `beta` is written exactly (Rust's shortest round-trip form).
pub fn fpu_beta(n: usize, beta: f64) -> String {
    let q = |i: usize| {
        if i == 0 || i == n + 1 {
            "0".to_string()
        } else {
            format!("q{i}")
        }
    };
    (0..=n)
        .map(|i| {
            let d = format!("({} - {})", q(i + 1), q(i));
            format!("{d}^2/2 + ({beta})*{d}^4/4")
        })
        .collect::<Vec<_>>()
        .join(" + ")
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::systems::polynomial::Polynomial;

    /// Two particles: V = q1²/2 + (q2 − q1)²/2 + q2²/2 + β/4 (q1⁴ + (q2 − q1)⁴ + q2⁴).
    #[test]
    fn two_particles_expand_to_three_springs() {
        let v = Polynomial::parse(&fpu_beta(2, 1.5), 2).unwrap();
        for q in [[0.3f64, -0.2], [1.1, 0.7], [-0.4, 0.0]] {
            let d = q[1] - q[0];
            let want = (q[0] * q[0] + d * d + q[1] * q[1]) / 2.0
                + 1.5 / 4.0 * (q[0].powi(4) + d.powi(4) + q[1].powi(4));
            assert!((v.eval(&q) - want).abs() < 1e-15, "{q:?}");
        }
        assert!(fpu_beta(3, -0.25).contains("(-0.25)*"));
        assert!(Polynomial::parse(&fpu_beta(8, 1e-7), 8).is_ok());
    }
}
