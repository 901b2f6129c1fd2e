//! DOP853 on orbits with their deviation vectors: both protocols, cross-method agreement,
//! named orbits, crossings from dense output and the energy behaviour of the paper's Table 1.

use crate::common::{c1, end_distance, r1, srkn14a_r1};
use salient_core::adaptive::dop853::{Dop853, Dop853Config};
use salient_core::adaptive::driver::{integrate_adaptive, Dop853Orbit, Protocol};
use salient_core::orbit::{
    initial_vectors, integrate, Class, OrbitConfig, OrbitResult, Requests, Status,
};
use salient_core::phase::Phase;
use salient_core::{Deviation, HenonHeiles, Scheme, TangentMap};

fn dop(
    x: ([f64; 2], [f64; 2]),
    delta: f64,
    protocol: Protocol,
    cfg: &OrbitConfig,
    req: &Requests,
) -> OrbitResult<2> {
    let (dq, dp) = initial_vectors::<2, 2>(Deviation::Axes);
    let y = Phase {
        q: x.0,
        p: x.1,
        dq,
        dp,
    };
    let mut integ = Dop853Orbit::new(
        &HenonHeiles,
        Dop853::new(&HenonHeiles, Dop853Config::with_delta(delta), 0.0, y),
    );
    integrate_adaptive(&HenonHeiles, &mut integ, protocol, cfg, req)
}

#[test]
fn both_protocols_give_the_same_sali_on_r1() {
    let cfg = OrbitConfig::new(0.05, 1e3);
    let req = Requests {
        samples_per_decade: 5,
        ..Requests::default()
    };
    let a = dop(r1(), 1e-12, Protocol::Restart, &cfg, &req);
    let b = dop(r1(), 1e-12, Protocol::Free, &cfg, &req);
    assert_eq!((a.status, b.status), (Status::Ok, Status::Ok));
    assert_eq!(a.t_reached, 1e3);
    assert_eq!(b.t_reached, 1e3);
    assert!(
        (a.sali - b.sali).abs() < 1e-8,
        "restart {} vs free {}",
        a.sali,
        b.sali
    );
    assert_eq!(a.series.len(), b.series.len());
    for (x, y) in a.series.iter().zip(&b.series) {
        assert_eq!(x.t, y.t);
        assert!(
            (x.sali - y.sali).abs() < 1e-8,
            "t = {}: {} vs {}",
            x.t,
            x.sali,
            y.sali
        );
        assert!(
            (x.mle - y.mle).abs() < 1e-8,
            "t = {}: mLE {} vs {}",
            x.t,
            x.mle,
            y.mle
        );
    }
    // At δ = 1e-12 the natural step (≈ 0.13) is well above τ = 0.05: the free protocol needs fewer.
    assert!(
        b.steps * 2 < a.steps,
        "free {} steps vs restart {}",
        b.steps,
        a.steps
    );
}

#[test]
fn dop853_agrees_with_srkn14a_on_r1() {
    let cfg = OrbitConfig::new(0.05, 100.0);
    let a = dop(r1(), 1e-13, Protocol::Restart, &cfg, &Requests::default());
    let b = srkn14a_r1(100.0, &Requests::default());
    assert!(
        (a.sali - b.sali).abs() < 1e-8,
        "SALI {} vs {}",
        a.sali,
        b.sali
    );
    assert!((a.mle - b.mle).abs() < 1e-8, "mLE {} vs {}", a.mle, b.mle);
    let e = end_distance(&a, &b);
    assert!(e < 1e-10, "end states differ by {e:e}");
}

#[test]
fn named_orbits_are_classified_by_dop853() {
    for protocol in [Protocol::Restart, Protocol::Free] {
        let r = dop(
            r1(),
            1e-10,
            protocol,
            &OrbitConfig::new(0.05, 1e4),
            &Requests::default(),
        );
        assert_eq!(r.class, Some(Class::Regular), "{protocol:?}");
        let c = dop(
            c1(),
            1e-10,
            protocol,
            &OrbitConfig::new(0.05, 1e4),
            &Requests::default(),
        );
        assert_eq!(c.status, Status::ChaoticEarlyStop, "{protocol:?}");
        assert!(
            c.t_reached < 1000.0,
            "{protocol:?}: C1 stopped at {}",
            c.t_reached
        );
    }
}

#[test]
fn crossings_from_dense_output_match_the_tangent_map_ones() {
    let req = Requests {
        crossings: true,
        ..Requests::default()
    };
    let a = dop(
        r1(),
        1e-13,
        Protocol::Free,
        &OrbitConfig::new(0.05, 100.0),
        &req,
    );
    let b = srkn14a_r1(100.0, &req);
    assert_eq!(a.crossings.len(), b.crossings.len());
    for (x, y) in a.crossings.iter().zip(&b.crossings) {
        assert!(x.q[0].abs() < 1e-13 && x.p[0] > 0.0);
        assert!(
            (x.q[1] - y.q[1]).abs() < 1e-10 && (x.p[1] - y.p[1]).abs() < 1e-10,
            "{x:?} vs {y:?}"
        );
        assert!((x.t - y.t).abs() < 1e-10);
    }
}

#[test]
fn table1_shape_adaptive_energy_error_grows_symplectic_does_not() {
    let req = Requests {
        energy: true,
        ..Requests::default()
    };
    let energy_at = |t: f64| {
        dop(
            r1(),
            1e-5,
            Protocol::Restart,
            &OrbitConfig::new(0.05, t),
            &req,
        )
        .energy_error_max
        .unwrap()
    };
    let (e1, e2) = (energy_at(1e3), energy_at(1e4));
    assert!(
        e2 > 3.0 * e1,
        "dop853 δ=1e-5: |ΔH/H| {e1:e} at 1e3, {e2:e} at 1e4 — expected growth"
    );
    let map = TangentMap::new(&HenonHeiles, &Scheme::by_name("sbab2c").unwrap(), 0.05);
    let tm = |t: f64| {
        integrate::<_, 2, 2>(&map, r1().0, r1().1, &OrbitConfig::new(0.05, t), &req)
            .energy_error_max
            .unwrap()
    };
    let (s1, s2) = (tm(1e3), tm(1e4));
    assert!(
        s2 < 1.5 * s1,
        "tm-sbab2c: |ΔH/H| {s1:e} at 1e3, {s2:e} at 1e4 — expected bounded"
    );
}
