//! Named orbits, indicators and section crossings, plus property tests over random initial
//! conditions on the section.

#![allow(clippy::needless_range_loop, clippy::excessive_precision)]

use crate::common::{c1, ic, r1, ENERGY};
use proptest::prelude::*;
use salient_core::orbit::{integrate, Class, Deviation, OrbitConfig, Requests, Status};
use salient_core::phase::Phase;
use salient_core::section::p1_squared;
use salient_core::{Hamiltonian, HenonHeiles, Scheme, TangentMap};

fn sbab2c() -> Scheme {
    Scheme::by_name("sbab2c").unwrap()
}

#[test]
fn r1_is_regular_at_1e5() {
    let ham = HenonHeiles;
    let map = TangentMap::new(&ham, &sbab2c(), 0.05);
    let x = r1();
    let res = integrate::<_, 2, 2>(
        &map,
        x.0,
        x.1,
        &OrbitConfig::new(0.05, 1e5),
        &Requests::default(),
    );
    assert_eq!(res.status, Status::Ok);
    assert_eq!(res.class, Some(Class::Regular));
    assert!(res.sali > 1e-2, "SALI(1e5) = {}", res.sali);
    // The reference computation gives SALI(1e5) = 0.259 for this orbit, method and step.
    assert!((res.sali - 0.259).abs() < 0.05, "SALI(1e5) = {}", res.sali);
    // A regular orbit's finite-time mLE decays like ln t / t.
    assert!(res.mle < 1e-3, "mLE = {}", res.mle);
}

#[test]
fn c1_is_chaotic_and_stops_early_before_t_1000() {
    let ham = HenonHeiles;
    let map = TangentMap::new(&ham, &sbab2c(), 0.05);
    let x = c1();
    let res = integrate::<_, 2, 2>(
        &map,
        x.0,
        x.1,
        &OrbitConfig::new(0.05, 1e4),
        &Requests::default(),
    );
    assert_eq!(res.status, Status::ChaoticEarlyStop);
    assert_eq!(res.class, Some(Class::Chaotic));
    assert!(res.t_reached < 1000.0, "stopped at t = {}", res.t_reached);
    assert!(
        res.t_reached > 200.0,
        "stopped implausibly early at t = {}",
        res.t_reached
    );
    assert!(res.sali < 1e-8);
    // Without the early stop it integrates on and still ends chaotic.
    let mut cfg = OrbitConfig::new(0.05, 2000.0);
    cfg.thresholds.early_stop = false;
    let res = integrate::<_, 2, 2>(&map, x.0, x.1, &cfg, &Requests::default());
    assert_eq!(res.status, Status::Ok);
    assert_eq!(res.t_reached, 2000.0);
    assert_eq!(res.class, Some(Class::Chaotic));
}

#[test]
fn c1_lyapunov_exponent_is_near_the_chaotic_sea_value() {
    // λ ≈ 0.045 ± 0.002 at H = 1/8 (SRKN14a τ = 0.1, t = 1e7; C1 gives
    // 0.0471 at t = 1e6). Finite-time values of one chaotic orbit depend on its round-off
    // history, so the band is 10 % at t = 1e6.
    let ham = HenonHeiles;
    let map = TangentMap::new(&ham, &sbab2c(), 0.1);
    let x = c1();
    let mut cfg = OrbitConfig::new(0.1, 1e6);
    cfg.thresholds.early_stop = false;
    let res = integrate::<_, 2, 2>(&map, x.0, x.1, &cfg, &Requests::default());
    assert!(
        (res.mle - 0.0471).abs() < 0.1 * 0.0471,
        "mLE(1e6) = {}",
        res.mle
    );
}

#[test]
fn gali2_and_sali_obey_their_factor_relation_along_orbits() {
    let ham = HenonHeiles;
    let map = TangentMap::new(&ham, &sbab2c(), 0.05);
    let req = Requests {
        gali: true,
        samples_per_decade: 10,
        ..Requests::default()
    };
    for x in [r1(), c1()] {
        let res = integrate::<_, 2, 4>(&map, x.0, x.1, &OrbitConfig::new(0.05, 1e3), &req);
        assert!(res.series.len() > 30);
        for s in &res.series {
            let g2 = s.gali[0];
            assert!(
                // Both are computed to ~1e-16 absolute, so relative 1e-6 at the 1e-8 floor.
                g2 <= s.sali * (1.0 + 1e-6) && s.sali <= 2f64.sqrt() * g2 * (1.0 + 1e-6),
                "t={}: SALI {} GALI_2 {}",
                s.t,
                s.sali,
                g2
            );
        }
    }
}

/// Least-squares slope of log10 y against log10 t.
fn loglog_slope(points: &[(f64, f64)]) -> f64 {
    let n = points.len() as f64;
    let (mut sx, mut sy, mut sxx, mut sxy) = (0.0, 0.0, 0.0, 0.0);
    for &(t, y) in points {
        let (x, y) = (t.log10(), y.log10());
        sx += x;
        sy += y;
        sxx += x * x;
        sxy += x * y;
    }
    (n * sxy - sx * sy) / (n * sxx - sx * sx)
}

#[test]
fn regular_gali_decays_like_powers_of_t_and_chaotic_gali_exponentially() {
    let ham = HenonHeiles;
    let map = TangentMap::new(&ham, &sbab2c(), 0.05);
    let req = Requests {
        gali: true,
        samples_per_decade: 10,
        ..Requests::default()
    };
    let x = r1();
    // Generic initial vectors: R1 sits on the symmetry line p2 = 0 and the δq1 axis is special
    // for it (‖w1‖ stays O(1) up to t = 1e7, so with the axes GALI_4 only falls like t⁻²).
    let mut cfg = OrbitConfig::new(0.05, 1e5);
    cfg.deviation = Deviation::Random { seed: 3 };
    let res = integrate::<_, 2, 4>(&map, x.0, x.1, &cfg, &req);
    let pick = |k: usize| -> Vec<(f64, f64)> {
        res.series
            .iter()
            .filter(|s| s.t >= 300.0)
            .map(|s| (s.t, s.gali[k]))
            .collect()
    };
    // HH regular orbits lie on 2-tori in 4-D: GALI_2 ~ const, GALI_3 ~ t⁻², GALI_4 ~ t⁻⁴.
    let s4 = loglog_slope(&pick(2));
    let s3 = loglog_slope(&pick(1));
    let s2 = loglog_slope(&pick(0));
    assert!((s4 + 4.0).abs() < 0.3, "GALI_4 slope {s4}");
    assert!((s3 + 2.0).abs() < 0.3, "GALI_3 slope {s3}");
    assert!(s2.abs() < 0.3, "GALI_2 slope {s2}");
    // Chaotic: GALI_4 collapses far faster than any power.
    let x = c1();
    let mut cfg = OrbitConfig::new(0.05, 300.0);
    cfg.thresholds.early_stop = false;
    let res = integrate::<_, 2, 4>(&map, x.0, x.1, &cfg, &req);
    assert!(res.gali[2] < 1e-15, "chaotic GALI_4(300) = {}", res.gali[2]);
}

#[test]
fn crossing_points_do_not_add_error_beyond_the_trajectorys() {
    let ham = HenonHeiles;
    let scheme = Scheme::by_name("srkn14a").unwrap();
    let x = r1();
    let req = Requests {
        crossings: true,
        ..Requests::default()
    };
    let run = |tau: f64| {
        let map = TangentMap::new(&ham, &scheme, tau);
        integrate::<_, 2, 2>(&map, x.0, x.1, &OrbitConfig::new(tau, 100.0), &req).crossings
    };
    let (a, b) = (run(1e-3), run(5e-4));
    assert!(a.len() >= 10, "{} crossings", a.len());
    assert_eq!(a.len(), b.len());
    for (ca, cb) in a.iter().zip(&b) {
        assert!((ca.q[1] - cb.q[1]).abs() <= 1e-10, "{ca:?} vs {cb:?}");
        assert!((ca.p[1] - cb.p[1]).abs() <= 1e-10, "{ca:?} vs {cb:?}");
        assert!((ca.t - cb.t).abs() <= 1e-10, "{ca:?} vs {cb:?}");
    }
    // And the located points are far more accurate than linear interpolation would be at the
    // coarse step that the grid engine uses: compare τ = 0.5 SBAB2C crossings with the above.
    let map = TangentMap::new(&ham, &sbab2c(), 0.05);
    let coarse =
        integrate::<_, 2, 2>(&map, x.0, x.1, &OrbitConfig::new(0.05, 100.0), &req).crossings;
    assert_eq!(coarse.len(), a.len());
    for (c, f) in coarse.iter().zip(&a) {
        assert!((c.q[1] - f.q[1]).abs() < 1e-5 && (c.p[1] - f.p[1]).abs() < 1e-5);
    }
}

#[test]
fn no_crossing_is_reported_at_t_zero_and_none_unless_asked() {
    let ham = HenonHeiles;
    let map = TangentMap::new(&ham, &sbab2c(), 0.05);
    let x = r1();
    let res = integrate::<_, 2, 2>(
        &map,
        x.0,
        x.1,
        &OrbitConfig::new(0.05, 50.0),
        &Requests::default(),
    );
    assert!(res.crossings.is_empty() && res.series.is_empty() && res.gali.is_empty());
    assert!(res.energy_error_max.is_none());
    let req = Requests {
        crossings: true,
        energy: true,
        ..Requests::default()
    };
    let res = integrate::<_, 2, 2>(&map, x.0, x.1, &OrbitConfig::new(0.05, 50.0), &req);
    assert!(res.crossings.iter().all(|c| c.t > 1.0));
    assert!(res.energy_error_max.unwrap() > 0.0);
}

#[test]
fn escaping_and_exploding_orbits_get_a_status_not_a_class() {
    let ham = HenonHeiles;
    let map = TangentMap::new(&ham, &sbab2c(), 0.05);
    // Above the escape energy, aimed at the saddle (0, 1): leaves the well.
    let (q, p) = salient_core::section::on_section(&ham, 0.3, &[0.5], &[0.6]).unwrap();
    let res = integrate::<_, 2, 2>(
        &map,
        q,
        p,
        &OrbitConfig::new(0.05, 1e4),
        &Requests::default(),
    );
    assert_eq!(res.status, Status::Escaped);
    assert_eq!(res.class, None);
    assert!(res.t_reached < 1e4);
    // Without an escape radius the cubic potential blows the orbit up in finite time: the
    // energy check sees the step fail first, and without it the values overflow.
    let mut cfg = OrbitConfig::new(0.05, 1e4);
    cfg.escape_radius = Some(f64::INFINITY);
    let res = integrate::<_, 2, 2>(&map, q, p, &cfg, &Requests::default());
    assert_eq!(res.status, Status::EnergyDrift);
    assert!(res.sali.is_nan() && res.class.is_none() && res.t_reached < 1e4);
    cfg.thresholds.energy_drift = f64::INFINITY;
    let res = integrate::<_, 2, 2>(&map, q, p, &cfg, &Requests::default());
    assert_eq!(res.status, Status::NonFinite);
    assert!(res.sali.is_nan() && res.class.is_none() && res.t_reached < 1e4);
}

/// Above the escape energy an orbit on its way out through a channel escapes, also when a
/// coarse step lets its energy error pass the limit there (beyond the well): the error is
/// reported, the status is `escaped` at the escape time of a fine step, give or take a step.
#[test]
fn an_orbit_leaving_the_well_escapes_whatever_its_energy_error_outside() {
    let ham = HenonHeiles;
    let (q, p) = salient_core::section::on_section(&ham, 0.2, &[-0.5292], &[-0.137]).unwrap();
    let req = Requests {
        energy: true,
        ..Requests::default()
    };
    let run = |tau: f64| {
        let map = TangentMap::new(&ham, &sbab2c(), tau);
        integrate::<_, 2, 2>(&map, q, p, &OrbitConfig::new(tau, 100.0), &req)
    };
    let (fine, coarse) = (run(0.05), run(0.5));
    assert_eq!(fine.status, Status::Escaped);
    assert!(fine.energy_error_max.unwrap() < 1e-4);
    assert_eq!(coarse.status, Status::Escaped);
    assert!(
        coarse.energy_error_max.unwrap() > 1e-2,
        "the error past the limit is shown"
    );
    assert!((coarse.t_reached - fine.t_reached).abs() <= 0.5);
    // Below the escape energy the same coarse step blowing R1 up out of the well is not an
    // escape (the splitting-stability test below).
    assert!(ham.way_out_r2(ENERGY, 2.0).is_infinite());
    assert_eq!(ham.way_out_r2(0.2, 2.0), 1.0);
    assert!(ham.way_out_r2(0.2, f64::INFINITY).is_infinite());
}

#[test]
fn a_splitting_step_beyond_its_stability_limit_ends_in_energy_drift() {
    let ham = HenonHeiles;
    let x = r1();
    let run = |tau: f64, limit: f64| {
        let map = TangentMap::new(&ham, &sbab2c(), tau);
        let mut cfg = OrbitConfig::new(tau, 1e3);
        cfg.thresholds.energy_drift = limit;
        integrate::<_, 2, 2>(&map, x.0, x.1, &cfg, &Requests::default())
    };
    // τ = 0.5: R1's energy error stays near 2e-3, the orbit is classified.
    let ok = run(0.5, 1e-2);
    assert_eq!((ok.status, ok.class), (Status::Ok, Some(Class::Regular)));
    // τ = 1, 2, 5: the energy error passes 1e-2 (or the orbit leaves the well with the
    // energy it gained — not an escape at H = 1/8) within the first checks.
    for tau in [1.0, 2.0, 5.0] {
        let r = run(tau, 1e-2);
        assert_eq!(r.status, Status::EnergyDrift, "τ = {tau}");
        assert!(r.class.is_none() && r.sali.is_nan(), "τ = {tau}");
        let checks = salient_core::orbit::ENERGY_CHECK_EVERY as f64 * tau;
        assert!(
            r.t_reached <= checks,
            "τ = {tau}: stopped at {}",
            r.t_reached
        );
    }
    // The limit is the user's: at τ = 1 a limit of 0.5 lets R1 through.
    assert_eq!(run(1.0, 0.5).status, Status::Ok);
    // A true escape conserves the energy and stays `escaped`.
    let map = TangentMap::new(&ham, &sbab2c(), 0.05);
    let (q, p) = salient_core::section::on_section(&ham, 0.3, &[0.5], &[0.6]).unwrap();
    let res = integrate::<_, 2, 2>(
        &map,
        q,
        p,
        &OrbitConfig::new(0.05, 1e4),
        &Requests::default(),
    );
    assert_eq!(res.status, Status::Escaped);
}

#[test]
fn random_deviation_vectors_are_seeded_and_give_the_same_classes() {
    let ham = HenonHeiles;
    let map = TangentMap::new(&ham, &sbab2c(), 0.05);
    let mut cfg = OrbitConfig::new(0.05, 2e3);
    cfg.deviation = Deviation::Random { seed: 7 };
    let a = integrate::<_, 2, 2>(&map, r1().0, r1().1, &cfg, &Requests::default());
    let b = integrate::<_, 2, 2>(&map, r1().0, r1().1, &cfg, &Requests::default());
    assert_eq!(a, b);
    assert_eq!(a.class, Some(Class::Regular));
    let c = integrate::<_, 2, 2>(&map, c1().0, c1().1, &cfg, &Requests::default());
    assert_eq!(c.class, Some(Class::Chaotic));
    cfg.deviation = Deviation::Random { seed: 8 };
    let d = integrate::<_, 2, 2>(&map, r1().0, r1().1, &cfg, &Requests::default());
    assert_ne!(a.sali, d.sali);
}

/// Compatible section points: q2 in the allowed band, p2 with a positive radicand.
fn section_point() -> impl Strategy<Value = (f64, f64)> {
    (-0.43f64..0.67, -0.49f64..0.49).prop_filter("on the section", |&(q2, p2)| {
        p1_squared(&HenonHeiles, ENERGY, &[0.0, q2], &[0.0, p2]) > 1e-6
    })
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 64, ..ProptestConfig::default() })]

    #[test]
    fn initial_conditions_lie_on_the_energy_surface((q2, p2) in section_point()) {
        let (q, p) = ic(q2, p2);
        prop_assert!(q[0] == 0.0 && p[0] > 0.0);
        prop_assert!((HenonHeiles.energy(&q, &p) - ENERGY).abs() <= 1e-15);
    }

    #[test]
    fn one_step_tangent_map_is_symplectic((q2, p2) in section_point(), tau in 0.01f64..0.5) {
        let ham = HenonHeiles;
        let map = TangentMap::new(&ham, &sbab2c(), tau);
        let (q, p) = ic(q2, p2);
        let mut ph: Phase<f64, 2, 4> = Phase::zero();
        ph.q = q;
        ph.p = p;
        ph.dq[0][0] = 1.0;
        ph.dq[1][1] = 1.0;
        ph.dp[2][0] = 1.0;
        ph.dp[3][1] = 1.0;
        map.step(&mut ph, tau);
        // Symplecticity as ω(w_a, w_b) = δq_a·δp_b − δp_a·δq_b preserved for all pairs.
        for a in 0..4 {
            for b in 0..4 {
                let w = |k: usize| (ph.dq[k], ph.dp[k]);
                let (wa, wb) = (w(a), w(b));
                let omega = wa.0[0] * wb.1[0] + wa.0[1] * wb.1[1] - wa.1[0] * wb.0[0] - wa.1[1] * wb.0[1];
                let expect = match (a, b) { (0, 2) | (1, 3) => 1.0, (2, 0) | (3, 1) => -1.0, _ => 0.0 };
                prop_assert!((omega - expect).abs() <= 1e-12, "ω({a},{b}) = {omega}");
            }
        }
    }

    #[test]
    fn crossings_lie_on_the_section_going_up((q2, p2) in section_point()) {
        let ham = HenonHeiles;
        let map = TangentMap::new(&ham, &sbab2c(), 0.05);
        let (q, p) = ic(q2, p2);
        let req = Requests { crossings: true, ..Requests::default() };
        let mut cfg = OrbitConfig::new(0.05, 60.0);
        cfg.thresholds.early_stop = false;
        let res = integrate::<_, 2, 2>(&map, q, p, &cfg, &req);
        prop_assert!(!res.crossings.is_empty());
        for c in &res.crossings {
            prop_assert!(c.q[0].abs() <= 1e-12, "q1 = {}", c.q[0]);
            prop_assert!(c.p[0] > 0.0);
            prop_assert!((ham.energy(&c.q, &c.p) - ENERGY).abs() < 1e-5);
        }
    }
}

/// MEGNO and the FLI against their theory (Cincotta & Simó 2000; Froeschlé, Lega & Gonczi
/// 1997) for the tangent map, DOP853 and f64 Taylor: on R1 Y → 2 (within 0.05 at t = 1e4; the
/// running mean ⟨Y⟩, which still carries the first thousand time units where Y climbs from 0,
/// within 0.1) and the FLI grows like ln t; on C1 ⟨Y⟩ ≈ λt/2 with λ the finite-time mLE and the
/// FLI grows like λt.
#[test]
fn megno_and_fli_follow_theory_on_r1_and_c1() {
    use salient_core::adaptive::driver::Protocol;
    use salient_core::run::{run_henon_heiles, MethodRun, Vectors};
    use salient_core::Method;
    let requests = Requests {
        growth: true,
        samples_per_decade: 1,
        ..Requests::default()
    };
    let methods = [
        (Method::TangentMap(sbab2c()), None),
        (Method::Dop853, Some(1e-10)),
        (Method::Taylor, Some(1e-10)),
    ];
    for (method, delta) in methods {
        let run = MethodRun {
            method,
            delta,
            protocol: Protocol::Restart,
        };
        let mut config = OrbitConfig::new(0.05, 1e4);
        config.thresholds.early_stop = false;
        let fli_at = |r: &salient_core::orbit::OrbitResult<2>, t: f64| {
            let s = r.series.iter().find(|s| s.t == t).expect("sampled");
            s.growth.expect("requested").fli
        };
        // R1 sits on the symmetry line p2 = 0, where the δq1 axis hardly grows (‖w1‖ = O(1):
        // ⟨Y⟩ ≈ 0, as on a periodic orbit); a generic vector shows the torus's linear growth.
        config.deviation = Deviation::Random { seed: 3 };
        let r = run_henon_heiles(&run, ENERGY, r1(), &config, &requests, Vectors::Two);
        let g = r.growth.expect("requested");
        let label = format!("{:?} R1 {g:?}", run.method);
        assert!((g.megno - 2.0).abs() < 0.05, "{label}");
        assert!((g.megno_mean - 2.0).abs() < 0.1, "{label}");
        // Samples at 10^k steps of 0.05, and the end.
        let gain = fli_at(&r, 1e4) - fli_at(&r, 500.0);
        assert!(
            (gain - 20f64.ln()).abs() < 0.5,
            "{label}: FLI gained {gain}"
        );
        config.deviation = Deviation::Axes;
        let r = run_henon_heiles(&run, ENERGY, c1(), &config, &requests, Vectors::Two);
        let g = r.growth.expect("requested");
        let label = format!("{:?} C1 {g:?} mLE {}", run.method, r.mle);
        let half_lambda_t = r.mle * 1e4 / 2.0;
        assert!((g.megno_mean / half_lambda_t - 1.0).abs() < 0.1, "{label}");
        assert!(r.mle > 0.04, "{label}");
        let slope = (fli_at(&r, 1e4) - fli_at(&r, 5e3)) / 5e3;
        assert!(
            (slope / r.mle - 1.0).abs() < 0.15,
            "{label}: FLI slope {slope}"
        );
    }
}

/// Hénon–Heiles known only by its derivatives: a [`Hamiltonian`] with no Taylor recursion and
/// none of the built-in's fused forms.
struct DerivativesOnly;

impl Hamiltonian<2> for DerivativesOnly {
    fn name(&self) -> &'static str {
        "derivatives-only"
    }
    fn potential<T: salient_core::arith::real::Real>(&self, q: &[T; 2]) -> T {
        HenonHeiles.potential(q)
    }
    fn grad<T: salient_core::arith::real::Real>(&self, q: &[T; 2]) -> [T; 2] {
        HenonHeiles.grad(q)
    }
    fn hess_vec<T: salient_core::arith::real::Real>(&self, q: &[T; 2], u: &[T; 2]) -> [T; 2] {
        HenonHeiles.hess_vec(q, u)
    }
    fn third_vec<T: salient_core::arith::real::Real>(
        &self,
        q: &[T; 2],
        w: &[T; 2],
        u: &[T; 2],
    ) -> [T; 2] {
        HenonHeiles.third_vec(q, w, u)
    }
}

/// The tangent-map methods and DOP853 run on a system known only by its derivatives and
/// agree with the built-in Hénon–Heiles; the Taylor methods are refused with the reason.
#[test]
fn tangent_maps_and_dop853_need_only_the_hamiltonian() {
    use salient_core::adaptive::driver::Protocol;
    use salient_core::run::{run_orbit, run_orbit_on_derivatives, MethodRun};
    use salient_core::Method;
    let config = OrbitConfig::new(0.05, 200.0);
    let requests = Requests::default();
    for (name, delta) in [
        ("tm-sbab2c", None),
        ("tm-srkn14a", None),
        ("dop853", Some(1e-12)),
    ] {
        let run = MethodRun {
            method: Method::parse(name).unwrap(),
            delta,
            protocol: Protocol::Restart,
        };
        for (q, p) in [r1(), c1()] {
            let own = run_orbit::<_, 2, 2>(&HenonHeiles, &run, ENERGY, q, p, &config, &requests);
            let bare = run_orbit_on_derivatives::<_, 2, 2>(
                &DerivativesOnly,
                &run,
                (q, p),
                &config,
                &requests,
            )
            .unwrap();
            assert_eq!(own.class, bare.class, "{name}");
            assert_eq!(own.steps, bare.steps, "{name}");
            for i in 0..2 {
                assert!(
                    (own.q_end[i] - bare.q_end[i]).abs() < 1e-8,
                    "{name}: {own:?} {bare:?}"
                );
                assert!(
                    (own.p_end[i] - bare.p_end[i]).abs() < 1e-8,
                    "{name}: {own:?} {bare:?}"
                );
            }
        }
    }
    for name in ["taylor", "taylor-dd"] {
        let run = MethodRun {
            method: Method::parse(name).unwrap(),
            delta: Some(1e-10),
            protocol: Protocol::Restart,
        };
        let (q, p) = r1();
        let e =
            run_orbit_on_derivatives::<_, 2, 2>(&DerivativesOnly, &run, (q, p), &config, &requests)
                .unwrap_err();
        assert!(e.contains(name) && e.contains("TaylorSeries"), "{e}");
    }
}
