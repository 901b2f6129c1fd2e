//! DOP853: measured orders of the method and of its dense output, and tolerance tracking.

use salient_core::adaptive::dop853::{Dop853, Dop853Config};
use salient_core::arith::real::Real;
use salient_core::phase::Phase;
use salient_core::Hamiltonian;

/// The harmonic oscillator V = ½ q²: q(t) = cos t, p(t) = −sin t from (1, 0).
struct Oscillator;

impl Hamiltonian<1> for Oscillator {
    fn name(&self) -> &'static str {
        "oscillator"
    }
    fn potential<T: Real>(&self, q: &[T; 1]) -> T {
        T::splat(0.5) * q[0] * q[0]
    }
    fn grad<T: Real>(&self, q: &[T; 1]) -> [T; 1] {
        *q
    }
    fn hess_vec<T: Real>(&self, _q: &[T; 1], u: &[T; 1]) -> [T; 1] {
        *u
    }
    fn third_vec<T: Real>(&self, _q: &[T; 1], _w: &[T; 1], _u: &[T; 1]) -> [T; 1] {
        [T::splat(0.0)]
    }
}

fn start() -> Phase<f64, 1, 1> {
    Phase {
        q: [1.0],
        p: [0.0],
        dq: [[0.0]],
        dp: [[1.0]],
    }
}

/// Max error against the exact solution at t: orbit (cos t, −sin t), deviation (sin t, cos t).
fn error(y: &Phase<f64, 1, 1>, t: f64) -> f64 {
    [
        y.q[0] - t.cos(),
        y.p[0] + t.sin(),
        y.dq[0][0] - t.sin(),
        y.dp[0][0] - t.cos(),
    ]
    .iter()
    .fold(0.0f64, |m, e| m.max(e.abs()))
}

#[test]
fn fixed_step_order_is_eight() {
    let run = |h: f64| {
        let mut d = Dop853::new(&Oscillator, Dop853Config::with_delta(1e-10), 0.0, start());
        for _ in 0..(8.0 / h).round() as u64 {
            d.fixed_step(h);
        }
        error(&d.y, d.t)
    };
    let (e1, e2) = (run(0.8), run(0.4));
    let order = (e1 / e2).log2();
    assert!(
        (order - 8.0).abs() < 0.3,
        "order {order:.3} (errors {e1:e}, {e2:e})"
    );
}

#[test]
fn dense_output_has_local_error_of_order_eight() {
    // Order-7 interpolation: its error within one step from exact data is O(h⁸).
    let local = |h: f64| {
        let mut d = Dop853::new(&Oscillator, Dop853Config::with_delta(1e-10), 0.0, start());
        let dense = d.fixed_step_dense(h);
        [0.3, 0.5, 0.8]
            .iter()
            .map(|&th| error(&dense.at(th * h), th * h))
            .fold(0.0, f64::max)
    };
    let (e1, e2) = (local(1.0), local(0.5));
    let slope = (e1 / e2).log2();
    assert!(
        (slope - 8.0).abs() < 0.6,
        "dense output local order {slope:.3} ({e1:e}, {e2:e})"
    );
    // The interpolant passes through both step ends.
    let mut d = Dop853::new(&Oscillator, Dop853Config::with_delta(1e-10), 0.0, start());
    let dense = d.fixed_step_dense(0.5);
    assert_eq!(dense.at(0.0), start());
    assert!(error(&dense.at(0.5), 0.5) - error(&d.y, 0.5) < 1e-15);
}

#[test]
fn global_error_tracks_the_tolerance() {
    let mut last = f64::INFINITY;
    for delta in [1e-6, 1e-8, 1e-10, 1e-12] {
        let mut d = Dop853::new(&Oscillator, Dop853Config::with_delta(delta), 0.0, start());
        while d.t < 20.0 {
            d.step(20.0, None).unwrap();
        }
        assert_eq!(d.t, 20.0);
        let e = error(&d.y, 20.0);
        assert!(e < 20.0 * delta, "δ = {delta:e}: error {e:e}");
        assert!(e < last, "error did not fall with δ");
        last = e;
        // Twelve evaluations per accepted step, eleven per rejected one, plus start-up.
        assert_eq!(
            d.evaluations,
            2 + 12 * d.ctl.accepted + 11 * (d.ctl.rejected + rejected_first(&d))
        );
    }
}

/// Rejections of the very first step are not counted as rejections (Hairer's convention); they
/// still cost evaluations. None happen on this smooth problem.
fn rejected_first(_d: &Dop853<'_, Oscillator, 1, 1>) -> u64 {
    0
}
