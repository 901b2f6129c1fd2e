//! The Taylor method: exactness on polynomial solutions, coefficients against finite
//! differences, agreement with other methods, both protocols, and double-double accuracy.

use crate::common::{c1, end_distance, r1, srkn14a_r1};
use salient_core::adaptive::dop853::{rhs, Dop853, Dop853Config};
use salient_core::adaptive::driver::{integrate_adaptive, Protocol, TaylorOrbit};
use salient_core::adaptive::taylor::{Jet, Taylor};
use salient_core::arith::dd::DoubleDouble;
use salient_core::arith::real::Real;
use salient_core::orbit::{initial_vectors, Class, OrbitConfig, OrbitResult, Requests, Status};
use salient_core::phase::Phase;
use salient_core::systems::series::{Series, TaylorSeries};
use salient_core::{Deviation, Hamiltonian, HenonHeiles};

/// Constant force: V = g q, so q(t) = q0 + p0 t − g t²/2 exactly.
struct Gravity;
const G: f64 = 9.81;

impl Hamiltonian<1> for Gravity {
    fn name(&self) -> &'static str {
        "gravity"
    }
    fn potential<T: Real>(&self, q: &[T; 1]) -> T {
        T::splat(G) * q[0]
    }
    fn grad<T: Real>(&self, _q: &[T; 1]) -> [T; 1] {
        [T::splat(G)]
    }
    fn hess_vec<T: Real>(&self, _q: &[T; 1], _u: &[T; 1]) -> [T; 1] {
        [T::splat(0.0)]
    }
    fn third_vec<T: Real>(&self, _q: &[T; 1], _w: &[T; 1], _u: &[T; 1]) -> [T; 1] {
        [T::splat(0.0)]
    }
}

impl TaylorSeries<1> for Gravity {
    fn all_coeffs<T: Real, const K: usize>(
        &self,
        _q: &[Series<T>; 1],
        _u: &[[Series<T>; 1]; K],
        _derived: &mut [Series<T>],
        k: usize,
    ) -> ([T; 1], [[T; 1]; K]) {
        (
            [T::splat(if k == 0 { G } else { 0.0 })],
            [[T::splat(0.0)]; K],
        )
    }
}

fn start(x: ([f64; 2], [f64; 2])) -> Phase<f64, 2, 2> {
    let (dq, dp) = initial_vectors::<2, 2>(Deviation::Axes);
    Phase {
        q: x.0,
        p: x.1,
        dq,
        dp,
    }
}

fn taylor(
    x: ([f64; 2], [f64; 2]),
    delta: f64,
    protocol: Protocol,
    cfg: &OrbitConfig,
    req: &Requests,
) -> OrbitResult<2> {
    let mut integ = TaylorOrbit::new(
        &HenonHeiles,
        Taylor::new(&HenonHeiles, delta, 0.0, start(x)),
    );
    integrate_adaptive(&HenonHeiles, &mut integ, protocol, cfg, req)
}

#[test]
fn polynomial_solutions_are_exact_in_one_step() {
    let y = Phase {
        q: [1.5],
        p: [20.0],
        dq: [[1.0]],
        dp: [[0.5]],
    };
    let mut t = Taylor::new(&Gravity, 1e-10, 0.0, y);
    t.step(3.0).unwrap();
    assert_eq!(t.steps, 1);
    assert_eq!(t.t(), 3.0);
    let q = 1.5 + 20.0 * 3.0 - 0.5 * G * 9.0;
    assert!((t.y.q[0] - q).abs() < 1e-13, "{} vs {q}", t.y.q[0]);
    assert!((t.y.p[0] - (20.0 - G * 3.0)).abs() < 1e-13);
    assert!((t.y.dq[0][0] - 2.5).abs() < 1e-15 && t.y.dp[0][0] == 0.5);
}

#[test]
fn henon_heiles_coefficients_match_finite_differences_of_the_flow() {
    let y = start(([0.0, 0.3], [0.25, -0.1]));
    let mut jet = Jet::<f64, 2, 2>::zero();
    jet.compute(&HenonHeiles, &y, 20);
    let f = rhs(&HenonHeiles, &y);
    // x_[1] = f(x).
    let mut first = Phase::<f64, 2, 2>::zero();
    for i in 0..2 {
        first.q[i] = jet.q[i][1];
        first.p[i] = jet.p[i][1];
        for k in 0..2 {
            first.dq[k][i] = jet.dq[k][i][1];
            first.dp[k][i] = jet.dp[k][i][1];
        }
    }
    first.zip_for_each(&f, |a, b| assert!((a - b).abs() < 1e-15, "{a} vs {b}"));
    // x_[2] = ½ Df·f, by central differences along f.
    let e = 1e-6;
    let (mut yp, mut ym) = (y, y);
    yp.axpy(e, &f);
    ym.axpy(-e, &f);
    let mut second = rhs(&HenonHeiles, &yp);
    second.axpy(-1.0, &rhs(&HenonHeiles, &ym));
    second.scale(1.0 / (4.0 * e));
    let mut have = Phase::<f64, 2, 2>::zero();
    for i in 0..2 {
        have.q[i] = jet.q[i][2];
        have.p[i] = jet.p[i][2];
        for k in 0..2 {
            have.dq[k][i] = jet.dq[k][i][2];
            have.dp[k][i] = jet.dp[k][i][2];
        }
    }
    have.zip_for_each(&second, |a, b| assert!((a - b).abs() < 1e-9, "{a} vs {b}"));
    // The whole series: the polynomial at s = 0.2 equals a DOP853 solution at δ = 1e-14.
    let mut d = Dop853::new(&HenonHeiles, Dop853Config::with_delta(1e-14), 0.0, y);
    while d.t < 0.2 {
        d.step(0.2, None).unwrap();
    }
    jet.eval(0.2)
        .zip_for_each(&d.y, |a, b| assert!((a - b).abs() < 1e-13, "{a} vs {b}"));
}

#[test]
fn both_protocols_agree_and_taylor_matches_srkn14a() {
    let cfg = OrbitConfig::new(0.05, 1e3);
    let a = taylor(r1(), 1e-15, Protocol::Restart, &cfg, &Requests::default());
    let b = taylor(r1(), 1e-15, Protocol::Free, &cfg, &Requests::default());
    assert!((a.sali - b.sali).abs() < 1e-8, "{} vs {}", a.sali, b.sali);
    // heyoka at tol 1e-15 gives SALI(1e3) = 1.2535960837.
    assert!((a.sali - 1.253_596_083_7).abs() < 1e-8, "{}", a.sali);
    // End state and SALI at t = 100 against SRKN14a τ = 1e-3.
    let tm = srkn14a_r1(100.0, &Requests::default());
    let ty = taylor(
        r1(),
        1e-15,
        Protocol::Restart,
        &OrbitConfig::new(0.05, 100.0),
        &Requests::default(),
    );
    assert!(
        (tm.sali - ty.sali).abs() < 1e-8,
        "{} vs {}",
        tm.sali,
        ty.sali
    );
    let e = end_distance(&tm, &ty);
    assert!(e < 1e-10, "end states differ by {e:e}");
}

#[test]
fn named_orbits_are_classified_by_taylor() {
    for protocol in [Protocol::Restart, Protocol::Free] {
        let r = taylor(
            r1(),
            1e-10,
            protocol,
            &OrbitConfig::new(0.05, 1e4),
            &Requests::default(),
        );
        assert_eq!(r.class, Some(Class::Regular), "{protocol:?}");
        let c = taylor(
            c1(),
            1e-10,
            protocol,
            &OrbitConfig::new(0.05, 1e4),
            &Requests::default(),
        );
        assert_eq!(c.status, Status::ChaoticEarlyStop, "{protocol:?}");
        assert!(c.t_reached < 1000.0, "{protocol:?}: {}", c.t_reached);
    }
}

#[test]
fn table1_shape_taylor_energy_error_grows() {
    let req = Requests {
        energy: true,
        ..Requests::default()
    };
    let at = |t: f64| {
        taylor(
            r1(),
            1e-5,
            Protocol::Restart,
            &OrbitConfig::new(0.05, t),
            &req,
        )
        .energy_error_max
        .unwrap()
    };
    let (e1, e2) = (at(1e3), at(1e4));
    assert!(e2 > 3.0 * e1, "taylor δ=1e-5: {e1:e} at 1e3, {e2:e} at 1e4");
}

#[test]
fn double_double_taylor_conserves_energy_to_1e_20() {
    let x = r1();
    // The initial condition in double-double: p1 from the energy in extended precision.
    let h = DoubleDouble::ratio(1.0, 8.0);
    let q2 = DoubleDouble::from_f64(0.558);
    let v = HenonHeiles.potential(&[DoubleDouble::ZERO, q2]);
    let p1 = ((h - v) * DoubleDouble::from_f64(2.0)).sqrt();
    let (dq, dp) = initial_vectors::<2, 2>(Deviation::Axes);
    let y = Phase {
        q: [DoubleDouble::ZERO, q2],
        p: [p1, DoubleDouble::ZERO],
        dq: dq.map(|v| v.map(DoubleDouble::from_f64)),
        dp: dp.map(|v| v.map(DoubleDouble::from_f64)),
    };
    assert!((p1.to_f64() - x.1[0]).abs() < 1e-16);
    let h0 = HenonHeiles.energy(&y.q, &y.p);
    let mut t = Taylor::new(&HenonHeiles, 1e-28, 0.0, y);
    assert_eq!(t.order(), 33);
    let mut worst = 0.0f64;
    while t.t() < 100.0 {
        t.step(100.0).unwrap();
        let e = (HenonHeiles.energy(&t.y.q, &t.y.p) - h0).to_f64().abs() / 0.125;
        worst = worst.max(e);
    }
    assert!(worst < 1e-20, "max |ΔH/H| = {worst:e}");
    assert!(worst > 0.0);
}

#[test]
fn crossings_from_the_taylor_polynomial_match_srkn14a() {
    let req = Requests {
        crossings: true,
        ..Requests::default()
    };
    let a = taylor(
        r1(),
        1e-15,
        Protocol::Free,
        &OrbitConfig::new(0.05, 100.0),
        &req,
    );
    let b = srkn14a_r1(100.0, &req);
    assert_eq!(a.crossings.len(), b.crossings.len());
    assert!(a.crossings.len() > 10);
    for (x, y) in a.crossings.iter().zip(&b.crossings) {
        assert!(x.q[0].abs() < 1e-13 && x.p[0] > 0.0);
        assert!(
            (x.q[1] - y.q[1]).abs() < 1e-10 && (x.p[1] - y.p[1]).abs() < 1e-10,
            "{x:?} vs {y:?}"
        );
    }
}

#[test]
fn orbits_that_blow_up_end_with_a_status_not_a_hang() {
    // Above the escape energy and with no escape radius, the cubic potential sends the orbit
    // to infinity in finite time: the step size collapses or the state overflows.
    let (q, p) = salient_core::section::on_section(&HenonHeiles, 0.3, &[0.5], &[0.6]).unwrap();
    let mut cfg = OrbitConfig::new(0.05, 1e4);
    cfg.escape_radius = Some(f64::INFINITY);
    // With the default energy limit the growing energy error stops it first.
    let r = taylor((q, p), 1e-12, Protocol::Free, &cfg, &Requests::default());
    assert_eq!(r.status, Status::EnergyDrift);
    assert!(r.t_reached < 100.0 && r.class.is_none());
    // Without it, the step size collapses or the state overflows.
    cfg.thresholds.energy_drift = f64::INFINITY;
    for protocol in [Protocol::Restart, Protocol::Free] {
        let r = taylor((q, p), 1e-12, protocol, &cfg, &Requests::default());
        assert!(
            matches!(r.status, Status::StepLimit | Status::NonFinite),
            "{:?}",
            r.status
        );
        assert!(r.t_reached < 100.0 && r.class.is_none());
        let (dq, dp) = initial_vectors::<2, 2>(Deviation::Axes);
        let mut d = salient_core::adaptive::driver::Dop853Orbit::new(
            &HenonHeiles,
            Dop853::new(
                &HenonHeiles,
                Dop853Config::with_delta(1e-12),
                0.0,
                Phase { q, p, dq, dp },
            ),
        );
        let r = integrate_adaptive(&HenonHeiles, &mut d, protocol, &cfg, &Requests::default());
        assert!(
            matches!(r.status, Status::StepLimit | Status::NonFinite),
            "{:?}",
            r.status
        );
        assert!(r.t_reached < 100.0 && r.class.is_none());
    }
}
