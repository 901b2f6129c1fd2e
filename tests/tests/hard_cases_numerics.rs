//! Numerical hard cases (notes and measured numbers: docs/hard-cases.md).
//!
//! 1. The sticky orbit C2: regular-looking for a million time units, chaotic by 1e7.
//! 2. The seed paper's Fig. 8: loose tolerances of the adaptive methods drift in energy and
//!    slowly misclassify the regular orbit R1; the symplectic tangent map and tight
//!    tolerances do not.
//! 3. Initial conditions on the section's boundary (p1 → 0): no NaN, crossings located.
//! 4. 1e8 steps: exact time, exact step count, no secular energy drift.
//! 5. Large renormalisation intervals τ for the adaptive methods: finite deviation vectors
//!    and the right Lyapunov exponent — and where the `restart` protocol runs out of range.
//!
//! The quick tests run with `cargo test --release -p salient-tests --test integration
//! hard_cases_numerics::`; the long ones are `#[ignore]`d and run by `scripts/stability.sh`,
//! which prints what they measured. Every test prints its measurements (`--nocapture` shows
//! them).

#![allow(clippy::excessive_precision)]

use crate::common::{c1, ic, r1, ENERGY};
use salient_core::adaptive::driver::Protocol;
use salient_core::method::Method;
use salient_core::orbit::{Class, OrbitConfig, OrbitResult, Requests, Status};
use salient_core::run::{run_henon_heiles, MethodRun, Vectors};
use salient_core::section::{on_section, p1_squared, SectionError};
use salient_core::{Hamiltonian, HenonHeiles};
use std::time::Instant;

/// The sticky orbit C2 of the seed paper.
const C2: (f64, f64) = (0.335036, -0.385631);

/// The Lyapunov exponent of the chaotic sea at H = 1/8 (SRKN14a τ = 0.1, t = 1e7).
const MLE_SEA: f64 = 0.045;

/// Runs `method` (a CLI name) on the orbit through `x` and returns the result with the wall
/// time in seconds.
fn run(
    method: &str,
    delta: Option<f64>,
    protocol: Protocol,
    x: ([f64; 2], [f64; 2]),
    cfg: &OrbitConfig,
    req: &Requests,
) -> (OrbitResult<2>, f64) {
    let run = MethodRun {
        method: Method::parse(method).unwrap(),
        delta,
        protocol,
    };
    let start = Instant::now();
    let res = run_henon_heiles(&run, ENERGY, x, cfg, req, Vectors::Two);
    let wall = start.elapsed().as_secs_f64();
    println!(
        "{method:>9} δ={:<7} {:<7} τ={:<6} t_final={:.0e}: {:<18} t={:<12} steps={:<10} \
         SALI={:.3e} mLE={:.4e} max|ΔH/H|={} wall={wall:.2}s",
        delta.map_or("-".to_string(), |d| format!("{d:e}")),
        if method.starts_with("tm-") {
            "-"
        } else {
            protocol.as_str()
        },
        cfg.tau,
        cfg.t_final,
        res.status.as_str(),
        res.t_reached,
        res.steps,
        res.sali,
        res.mle,
        res.energy_error_max
            .map_or("-".to_string(), |e| format!("{e:.3e}")),
    );
    (res, wall)
}

/// A configuration that measures rather than judges the energy: the `energy-drift` status
/// is switched off so that a drifting run goes on to show what the drift does to SALI.
fn measuring(tau: f64, t_final: f64) -> OrbitConfig {
    let mut cfg = OrbitConfig::new(tau, t_final);
    cfg.thresholds.energy_drift = f64::INFINITY;
    cfg
}

fn energy_and_samples(per_decade: u32) -> Requests {
    Requests {
        energy: true,
        samples_per_decade: per_decade,
        ..Requests::default()
    }
}

/// The sample nearest to time `t`.
fn sample_at(res: &OrbitResult<2>, t: f64) -> &salient_core::orbit::Sample {
    res.series
        .iter()
        .min_by(|a, b| (a.t - t).abs().total_cmp(&(b.t - t).abs()))
        .expect("samples were requested")
}

// ---------------------------------------------------------------------------------------------
// 1. The sticky orbit C2.
// ---------------------------------------------------------------------------------------------

/// C2 with TM-SBAB2C, τ = 0.05 (2e6 steps): at t = 1e5 it looks regular, and did so all along.
#[test]
fn sticky_c2_looks_regular_at_1e5() {
    let (res, _) = run(
        "tm-sbab2c",
        None,
        Protocol::Restart,
        ic(C2.0, C2.1),
        &OrbitConfig::new(0.05, 1e5),
        &energy_and_samples(10),
    );
    assert_eq!(res.status, Status::Ok);
    assert_eq!(res.t_reached, 1e5);
    assert_eq!(res.steps, 2_000_000);
    assert_eq!(res.class, Some(Class::Regular));
    // Measured 0.284.
    assert!(res.sali > 1e-2, "SALI(1e5) = {:e}", res.sali);
    // Regular-looking throughout, not just at the end: the smallest sampled SALI after the
    // transient is 0.137 (t ≈ 4e3).
    let min = res
        .series
        .iter()
        .filter(|s| s.t >= 100.0)
        .map(|s| s.sali)
        .fold(f64::INFINITY, f64::min);
    println!("C2 min SALI over samples in [1e2, 1e5]: {min:.3e}");
    assert!(min > 1e-2, "min SALI over [1e2, 1e5] = {min:e}");
    // Its finite-time mLE decays like a regular orbit's (measured 3.4e-5).
    assert!(res.mle < 1e-3, "mLE(1e5) = {:e}", res.mle);
    // max |ΔH/H| measured 1.8e-7.
    assert!(res.energy_error_max.unwrap() < 1e-6);
}

/// C2 to t = 1e7 with the early stop: it stays regular-looking past 1e6 and then becomes
/// chaotic. Measured: SALI < 1e-8 first at t = 5 211 397.6 (1.04e8 steps).
#[test]
#[ignore = "long: C2 to t = 1e7 (≈ 1e8 steps); run by scripts/stability.sh"]
fn sticky_c2_becomes_chaotic_by_1e7() {
    let (res, wall) = run(
        "tm-sbab2c",
        None,
        Protocol::Restart,
        ic(C2.0, C2.1),
        &OrbitConfig::new(0.05, 1e7),
        &energy_and_samples(10),
    );
    println!(
        "C2: SALI < 1e-8 first at t = {} after {} steps, wall {wall:.2} s",
        res.t_reached, res.steps
    );
    for s in res.series.iter().filter(|s| s.t >= 1e5) {
        println!("  t = {:.4e}: SALI {:.3e}, mLE {:.3e}", s.t, s.sali, s.mle);
    }
    assert_eq!(res.status, Status::ChaoticEarlyStop);
    assert_eq!(res.class, Some(Class::Chaotic));
    assert!(res.sali < 1e-8);
    assert!(
        res.t_reached > 1e6 && res.t_reached < 1e7,
        "chaotic onset at t = {}",
        res.t_reached
    );
    // Regular-looking (SALI ≥ 1e-4) at every sample up to t = 1e6.
    for s in res.series.iter().filter(|s| s.t >= 100.0 && s.t <= 1e6) {
        assert!(s.sali > 1e-4, "t = {}: SALI {:e}", s.t, s.sali);
    }
    assert!(res.energy_error_max.unwrap() < 1e-6);
}

// ---------------------------------------------------------------------------------------------
// 2. The seed paper's Fig. 8 effect on R1.
// ---------------------------------------------------------------------------------------------

/// DOP853 and Taylor at δ = 1e-5 (restart, τ = 0.5) lose energy linearly in t, and by t = 1e6
/// their error is larger than the bounded error of TM-SBAB2C at τ = 0.5, although that step is
/// ten times the one usually used. R1 is still classified regular at 1e6 by all three: the
/// misclassification needs longer (see the ignored test below).
#[test]
fn fig8_loose_tolerances_drift_in_energy_the_tangent_map_does_not() {
    let req = energy_and_samples(1);
    let (tm_short, _) = run(
        "tm-sbab2c",
        None,
        Protocol::Restart,
        r1(),
        &measuring(0.5, 1e4),
        &req,
    );
    let (tm, _) = run(
        "tm-sbab2c",
        None,
        Protocol::Restart,
        r1(),
        &measuring(0.5, 1e6),
        &req,
    );
    let tm_max = tm.energy_error_max.unwrap();
    // Bounded: the maximum over 1e6 is the maximum over the first 1e4 (measured 2.3577e-3
    // both, ratio 1.0001).
    assert!(
        tm_max < 1.05 * tm_short.energy_error_max.unwrap(),
        "TM-SBAB2C max |ΔH/H|: {:e} to 1e4, {tm_max:e} to 1e6",
        tm_short.energy_error_max.unwrap()
    );
    assert!(tm_max < 5e-3);
    assert_eq!(tm.class, Some(Class::Regular));

    for method in ["dop853", "taylor"] {
        let (res, _) = run(
            method,
            Some(1e-5),
            Protocol::Restart,
            r1(),
            &measuring(0.5, 1e6),
            &req,
        );
        assert_eq!(res.status, Status::Ok, "{method}");
        // Linear growth: ×10 per decade (measured 3.40e-5, 3.40e-4, 3.39e-3 at t = 5e3,
        // 5e4, 5e5 for DOP853; 2.80e-5, 2.94e-4, 3.16e-3 for Taylor).
        let e = |t: f64| sample_at(&res, t).energy_error;
        for (a, b) in [(5e3, 5e4), (5e4, 5e5)] {
            let ratio = e(b) / e(a);
            println!(
                "{method} δ=1e-5: |ΔH/H| {:.3e} at {a:e}, {:.3e} at {b:e}",
                e(a),
                e(b)
            );
            assert!(
                (5.0..20.0).contains(&ratio),
                "{method}: |ΔH/H| grows ×{ratio} from t = {a:e} to {b:e}, expected ≈ ×10"
            );
        }
        // Measured 6.80e-3 (DOP853) and 6.29e-3 (Taylor) against TM-SBAB2C's 2.36e-3.
        let max = res.energy_error_max.unwrap();
        assert!(
            max > 2.0 * tm_max,
            "{method} δ=1e-5 max |ΔH/H| {max:e} vs TM-SBAB2C τ=0.5 {tm_max:e}"
        );
        assert_eq!(res.class, Some(Class::Regular), "{method} at 1e6");
    }
}

/// At δ = 1e-14 DOP853 and Taylor conserve the energy to ~1e-11 over 1e5 and agree with each
/// other on SALI and on the end point; the δ = 1e-5 runs have wandered away from both.
#[test]
fn fig8_tight_tolerances_conserve_energy_and_agree() {
    let req = energy_and_samples(0);
    let cfg = measuring(0.5, 1e5);
    let (d14, _) = run("dop853", Some(1e-14), Protocol::Restart, r1(), &cfg, &req);
    let (t14, _) = run("taylor", Some(1e-14), Protocol::Restart, r1(), &cfg, &req);
    let (d5, _) = run("dop853", Some(1e-5), Protocol::Restart, r1(), &cfg, &req);
    let (t5, _) = run("taylor", Some(1e-5), Protocol::Restart, r1(), &cfg, &req);
    for r in [&d14, &t14, &d5, &t5] {
        assert_eq!(r.status, Status::Ok);
        assert_eq!(r.class, Some(Class::Regular));
    }
    // DOP853's error still grows linearly, ~3.5e-16 per unit time; Taylor's is round-off.
    let (ed, et) = (d14.energy_error_max.unwrap(), t14.energy_error_max.unwrap());
    assert!(ed < 1e-10, "dop853 δ=1e-14: max |ΔH/H| = {ed:e}");
    assert!(et < 1e-12, "taylor δ=1e-14: max |ΔH/H| = {et:e}");
    let end = |a: &OrbitResult<2>, b: &OrbitResult<2>| crate::common::end_distance(a, b);
    let (tight, loose_d, loose_t) = (end(&d14, &t14), end(&d5, &d14), end(&t5, &d14));
    println!(
        "R1 t = 1e5 end-point distances: dop853/taylor δ=1e-14 {tight:.2e}; δ=1e-5 from \
         δ=1e-14: dop853 {loose_d:.2e}, taylor {loose_t:.2e}; SALI δ=1e-14 {:.6} / {:.6}",
        d14.sali, t14.sali
    );
    // A regular orbit's phase error grows linearly: measured 1.4e-7 at 1e5.
    assert!(tight < 1e-6, "δ=1e-14 runs end {tight:e} apart");
    assert!((d14.sali - t14.sali).abs() < 1e-5);
    // Measured 8.2e-2 (DOP853) and 0.59 (Taylor): the phase along the torus is lost.
    assert!(loose_d > 1e-2 && loose_t > 1e-2, "{loose_d:e} {loose_t:e}");
}

/// In the `free` protocol the step is not capped by τ, so DOP853 at δ = 1e-5 takes its natural
/// steps (≈ 1 time unit) and drifts ~450 times faster than under `restart` with τ = 0.5: it
/// misclassifies R1 as chaotic before t = 1e5 (measured t = 72 993.5, |ΔH/H| = 0.19). The
/// `energy-drift` status catches it first.
#[test]
fn fig8_free_protocol_at_loose_tolerance_misclassifies_r1_unless_the_energy_is_checked() {
    let req = energy_and_samples(0);
    let (res, _) = run(
        "dop853",
        Some(1e-5),
        Protocol::Free,
        r1(),
        &measuring(0.5, 1e6),
        &req,
    );
    assert_eq!(res.status, Status::ChaoticEarlyStop);
    assert_eq!(res.class, Some(Class::Chaotic));
    assert!(
        res.t_reached > 1e4 && res.t_reached < 1e6,
        "R1 misclassified at t = {}",
        res.t_reached
    );
    assert!(res.energy_error_max.unwrap() > 0.05);

    // With the energy checked (|ΔH/H| ≤ 1e-2, the default) the orbit stops with no class.
    let mut cfg = OrbitConfig::new(0.5, 1e6);
    cfg.thresholds.energy_drift = 1e-2;
    let (checked, _) = run("dop853", Some(1e-5), Protocol::Free, r1(), &cfg, &req);
    assert_eq!(checked.status, Status::EnergyDrift);
    assert_eq!(checked.class, None);
    assert!(
        checked.t_reached < 1e4,
        "energy-drift only at t = {}",
        checked.t_reached
    );

    // Taylor at the same δ in the same protocol chooses its step from δ (Jorba–Zou), not from
    // the error estimate, and stays regular with an error like its restart one.
    let (taylor, _) = run(
        "taylor",
        Some(1e-5),
        Protocol::Free,
        r1(),
        &measuring(0.5, 1e5),
        &req,
    );
    assert_eq!(taylor.class, Some(Class::Regular));
    assert!(taylor.energy_error_max.unwrap() < 2e-3);
}

/// The paper's horizon, δ = 1e-5: DOP853 misclassifies R1 as chaotic before 1e7 (measured
/// t = 5 651 332, |ΔH/H| = 3.8e-2) — or, with the energy checked, stops with `energy-drift`
/// (≈ 1.5e6); Taylor ends sticky; TM-SBAB2C at the same τ = 0.5 stays regular.
#[test]
#[ignore = "long: R1 to t = 1e7 at δ = 1e-5 (≈ 17 s); run by scripts/stability.sh"]
fn fig8_long_horizon_loose_tolerances_misclassify_r1() {
    let req = energy_and_samples(2);
    let cfg = measuring(0.5, 1e7);
    let (d5, _) = run("dop853", Some(1e-5), Protocol::Restart, r1(), &cfg, &req);
    let (t5, _) = run("taylor", Some(1e-5), Protocol::Restart, r1(), &cfg, &req);
    let (tm, _) = run("tm-sbab2c", None, Protocol::Restart, r1(), &cfg, &req);
    for (name, r) in [("dop853", &d5), ("taylor", &t5), ("tm-sbab2c", &tm)] {
        for s in r.series.iter().filter(|s| s.t >= 1e5) {
            println!(
                "  {name:>9} t = {:.3e}: SALI {:.3e}, |ΔH/H| {:.2e}",
                s.t, s.sali, s.energy_error
            );
        }
    }
    assert_eq!(d5.status, Status::ChaoticEarlyStop);
    assert!(d5.t_reached > 2e6 && d5.t_reached < 1e7, "{}", d5.t_reached);
    assert!(d5.energy_error_max.unwrap() > 1e-2);
    assert_eq!(t5.status, Status::Ok);
    assert!(t5.sali < 1e-2, "taylor δ=1e-5 SALI(1e7) = {:e}", t5.sali);
    assert!(t5.energy_error_max.unwrap() > 5e-2);
    assert_eq!(tm.class, Some(Class::Regular));
    assert!(tm.sali > 0.1);
    assert!(tm.energy_error_max.unwrap() < 3e-3);
    // Against the regular runs' SALI (≈ 1.1–1.2 at 1e7), the drifting ones are far below.
    assert!(d5.sali < 1e-3 * tm.sali && t5.sali < 1e-2 * tm.sali);

    let mut checked = OrbitConfig::new(0.5, 1e7);
    checked.thresholds.energy_drift = 1e-2;
    let (dc, _) = run(
        "dop853",
        Some(1e-5),
        Protocol::Restart,
        r1(),
        &checked,
        &energy_and_samples(0),
    );
    assert_eq!(dc.status, Status::EnergyDrift);
    assert!(
        dc.t_reached > 1e6 && dc.t_reached < d5.t_reached,
        "energy-drift at t = {}",
        dc.t_reached
    );
}

/// The paper's horizon, δ = 1e-14: both adaptive methods keep R1 regular to t = 1e7.
#[test]
#[ignore = "long: R1 to t = 1e7 at δ = 1e-14 (≈ 65 s); run by scripts/stability.sh"]
fn fig8_long_horizon_tight_tolerances_keep_r1_regular() {
    let req = energy_and_samples(1);
    let cfg = measuring(0.5, 1e7);
    let (d14, _) = run("dop853", Some(1e-14), Protocol::Restart, r1(), &cfg, &req);
    let (t14, _) = run("taylor", Some(1e-14), Protocol::Restart, r1(), &cfg, &req);
    for r in [&d14, &t14] {
        assert_eq!(r.status, Status::Ok);
        assert_eq!(r.class, Some(Class::Regular));
        assert!(r.sali > 0.1, "SALI(1e7) = {:e}", r.sali);
    }
    // Measured 3.5e-9 (DOP853, still linear in t) and 1.2e-11 (Taylor).
    assert!(d14.energy_error_max.unwrap() < 1e-8);
    assert!(t14.energy_error_max.unwrap() < 1e-10);
}

// ---------------------------------------------------------------------------------------------
// 3. The section's boundary: p1 → 0.
// ---------------------------------------------------------------------------------------------

/// 2H − p2² − q2² + ⅔q2³ with q1 = 0: the p1² of a section point.
fn radicand(q2: f64, p2: f64) -> f64 {
    2.0 * ENERGY - p2 * p2 - q2 * q2 + 2.0 / 3.0 * q2 * q2 * q2
}

/// Points (q2, p2) of the section whose p1² is ≈ `eps`: off the p2 = 0 axis at both signs of
/// p2, and the two ends of the section on p2 = 0 (found by Newton on q2).
fn near_boundary(eps: f64) -> Vec<(f64, f64)> {
    let mut v = Vec::new();
    for q2 in [-0.4, -0.25, 0.0, 0.3, 0.6] {
        let p2 = (radicand(q2, 0.0) - eps).sqrt();
        v.push((q2, p2));
        v.push((q2, -p2));
    }
    for start in [-0.44, 0.67] {
        let mut q2: f64 = start;
        for _ in 0..50 {
            // d/dq2 of the radicand at p2 = 0.
            let slope = -2.0 * q2 + 2.0 * q2 * q2;
            q2 -= (radicand(q2, 0.0) - eps) / slope;
        }
        v.push((q2, 0.0));
    }
    v
}

/// Orbits started with p1 as small as 1e-8 (nearly tangent to the section) integrate without
/// NaN in every method, and every crossing they report is on the section, upward and finite.
#[test]
fn section_boundary_initial_conditions_integrate_and_cross_cleanly() {
    let methods: [(&str, Option<f64>, Protocol, f64); 4] = [
        ("tm-sbab2c", None, Protocol::Restart, 1e-6),
        ("dop853", Some(1e-12), Protocol::Restart, 1e-9),
        ("dop853", Some(1e-12), Protocol::Free, 1e-9),
        ("taylor", Some(1e-12), Protocol::Free, 1e-9),
    ];
    let req = Requests {
        crossings: true,
        energy: true,
        ..Requests::default()
    };
    let mut runs = 0;
    let mut crossings = 0usize;
    let mut worst_q1: f64 = 0.0;
    let mut min_p1 = f64::INFINITY;
    for eps in [1e-4, 1e-8, 1e-12, 1e-15] {
        for (q2, p2) in near_boundary(eps) {
            let x = on_section(&HenonHeiles, ENERGY, &[q2], &[p2])
                .unwrap_or_else(|e| panic!("ε = {eps:e}, ({q2}, {p2}): {e}"));
            let r = p1_squared(&HenonHeiles, ENERGY, &x.0, &x.1);
            assert!(
                r > 0.5 * eps && r < 1.5 * eps,
                "ε = {eps:e}: p1² = {r:e} at ({q2}, {p2})"
            );
            for (method, delta, protocol, energy_tol) in methods {
                let cfg = OrbitConfig::new(0.05, 1000.0);
                let res = run_henon_heiles(
                    &MethodRun {
                        method: Method::parse(method).unwrap(),
                        delta,
                        protocol,
                    },
                    ENERGY,
                    x,
                    &cfg,
                    &req,
                    Vectors::Two,
                );
                runs += 1;
                let what = format!("{method} {protocol:?} ε = {eps:e} ({q2}, {p2})");
                assert!(
                    matches!(res.status, Status::Ok | Status::ChaoticEarlyStop),
                    "{what}: {:?}",
                    res.status
                );
                assert!(res.class.is_some(), "{what}");
                assert!(
                    res.sali.is_finite() && (0.0..=2f64.sqrt() + 1e-12).contains(&res.sali),
                    "{what}: SALI {}",
                    res.sali
                );
                assert!(res.mle.is_finite(), "{what}: mLE {}", res.mle);
                assert!(res.energy_error_max.unwrap() < energy_tol, "{what}");
                // ~ one upward crossing per 6.5 time units.
                assert!(
                    res.crossings.len() * 20 > res.t_reached as usize,
                    "{what}: {} crossings by t = {}",
                    res.crossings.len(),
                    res.t_reached
                );
                let mut t_prev = 0.0;
                for c in &res.crossings {
                    assert!(
                        c.q.iter().chain(&c.p).all(|v| v.is_finite()) && c.t.is_finite(),
                        "{what}: {c:?}"
                    );
                    assert!(c.q[0].abs() <= 1e-9, "{what}: q1 = {:e} at {c:?}", c.q[0]);
                    assert!(c.p[0] >= 0.0, "{what}: p1 = {:e} at {c:?}", c.p[0]);
                    assert!(c.t > t_prev && c.t <= res.t_reached, "{what}: {c:?}");
                    let h = HenonHeiles.energy(&c.q, &c.p);
                    assert!(
                        ((h - ENERGY) / ENERGY).abs() < energy_tol,
                        "{what}: H = {h} at {c:?}"
                    );
                    t_prev = c.t;
                    worst_q1 = worst_q1.max(c.q[0].abs());
                    min_p1 = min_p1.min(c.p[0]);
                }
                crossings += res.crossings.len();
            }
        }
    }
    println!(
        "section boundary: {runs} runs, {crossings} crossings, max |q1| {worst_q1:.2e}, \
         min p1 {min_p1:.2e}"
    );
}

/// On the boundary itself and beyond it there is no section point: the refusal is explicit.
#[test]
fn section_boundary_points_outside_are_refused() {
    for eps in [-1e-12, -1e-4] {
        for (q2, p2) in near_boundary(eps) {
            match on_section::<_, 2>(&HenonHeiles, ENERGY, &[q2], &[p2]) {
                Err(SectionError::NotOnSection { radicand }) => {
                    assert!(radicand <= 0.0 && radicand > 2.0 * eps, "{radicand:e}")
                }
                other => panic!("ε = {eps:e} ({q2}, {p2}): {other:?}"),
            }
        }
    }
}

/// The first crossings of boundary orbits agree between DOP853 and Taylor (δ = 1e-13, dense
/// output / step polynomial) to the design's 1e-9 in (q2, p2), and TM-SBAB2C at τ = 0.05
/// (Newton on a partial step) to its local error.
#[test]
fn section_boundary_crossings_are_located_consistently_across_methods() {
    let req = Requests {
        crossings: true,
        ..Requests::default()
    };
    let cfg = OrbitConfig::new(0.05, 40.0);
    let mut worst_adaptive: f64 = 0.0;
    let mut worst_tm: f64 = 0.0;
    for eps in [1e-8, 1e-12] {
        for (q2, p2) in near_boundary(eps) {
            let x = on_section(&HenonHeiles, ENERGY, &[q2], &[p2]).unwrap();
            let go = |method: &str, delta: Option<f64>| {
                run_henon_heiles(
                    &MethodRun {
                        method: Method::parse(method).unwrap(),
                        delta,
                        protocol: Protocol::Free,
                    },
                    ENERGY,
                    x,
                    &cfg,
                    &req,
                    Vectors::Two,
                )
            };
            let d = go("dop853", Some(1e-13));
            let t = go("taylor", Some(1e-13));
            let m = go("tm-sbab2c", None);
            assert!(d.crossings.len() >= 3, "({q2}, {p2}): {:?}", d.crossings);
            // A crossing within one step of t_final may be seen by one method only.
            let n = d
                .crossings
                .len()
                .min(t.crossings.len())
                .min(m.crossings.len());
            assert!(n + 1 >= d.crossings.len());
            for i in 0..n {
                let (a, b, c) = (&d.crossings[i], &t.crossings[i], &m.crossings[i]);
                let da = (a.q[1] - b.q[1]).abs().max((a.p[1] - b.p[1]).abs());
                let dm = (a.q[1] - c.q[1]).abs().max((a.p[1] - c.p[1]).abs());
                worst_adaptive = worst_adaptive.max(da);
                worst_tm = worst_tm.max(dm);
                assert!(
                    da < 1e-9,
                    "ε = {eps:e} ({q2}, {p2}) crossing {i}: {a:?} vs {b:?}"
                );
                assert!(
                    dm < 1e-5,
                    "ε = {eps:e} ({q2}, {p2}) crossing {i}: {a:?} vs {c:?}"
                );
            }
        }
    }
    println!(
        "boundary crossings to t = 40: dop853 vs taylor ≤ {worst_adaptive:.2e}, \
         tm-sbab2c τ=0.05 vs dop853 ≤ {worst_tm:.2e}"
    );
}

// ---------------------------------------------------------------------------------------------
// 4. 1e8 steps.
// ---------------------------------------------------------------------------------------------

/// TM-SBAB2C, τ = 0.5, R1 to t = 5e7: exactly 1e8 steps to exactly t = 5e7, and the energy
/// error's envelope over [1e7, 5e7] is the one over [1e6, 5e6] (no secular drift). 1e8 steps
/// take a few seconds, so this is a normal test (figures: docs/performance.md).
#[test]
fn hundred_million_steps_exact_time_and_no_energy_drift() {
    let (res, wall) = run(
        "tm-sbab2c",
        None,
        Protocol::Restart,
        r1(),
        &OrbitConfig::new(0.5, 5e7),
        &energy_and_samples(1000),
    );
    assert_eq!(res.status, Status::Ok);
    assert_eq!(res.t_reached, 5e7);
    assert_eq!(res.steps, 100_000_000);
    assert_eq!(res.class, Some(Class::Regular));
    let envelope = |lo: f64, hi: f64| {
        let v: Vec<f64> = res
            .series
            .iter()
            .filter(|s| s.t >= lo && s.t <= hi)
            .map(|s| s.energy_error)
            .collect();
        let mean = v.iter().sum::<f64>() / v.len() as f64;
        (v.iter().cloned().fold(0.0, f64::max), mean, v.len())
    };
    let (early, early_mean, n_early) = envelope(1e6, 5e6);
    let (late, late_mean, n_late) = envelope(1e7, 5e7);
    println!(
        "1e8 steps in {wall:.2} s ({:.1} ns/step); max |ΔH/H| over [1e6,5e6] {early:.4e} \
         ({n_early} samples, mean {early_mean:.3e}), over [1e7,5e7] {late:.4e} ({n_late} \
         samples, mean {late_mean:.3e}), over every step {:.4e}",
        wall / 1e8 * 1e9,
        res.energy_error_max.unwrap()
    );
    assert!(n_early > 500 && n_late > 500);
    assert!(
        late < 1.05 * early && late > 0.95 * early,
        "envelope {early:e} → {late:e}"
    );
    assert!(late_mean < 1.1 * early_mean && late_mean > 0.9 * early_mean);
    // The per-step maximum over all 1e8 steps is the orbit's bounded oscillation (2.358e-3).
    assert!(res.energy_error_max.unwrap() < 1.05 * early.max(late));
}

// ---------------------------------------------------------------------------------------------
// 5. Large renormalisation intervals.
// ---------------------------------------------------------------------------------------------

fn no_early_stop(tau: f64, t_final: f64) -> OrbitConfig {
    let mut cfg = OrbitConfig::new(tau, t_final);
    cfg.thresholds.early_stop = false;
    cfg
}

const ADAPTIVE: [(&str, Protocol); 4] = [
    ("dop853", Protocol::Restart),
    ("dop853", Protocol::Free),
    ("taylor", Protocol::Restart),
    ("taylor", Protocol::Free),
];

/// τ = 10 and τ = 1000 on C1 with DOP853 and Taylor (δ = 1e-12, both protocols): the vectors
/// grow by up to e^45 between renormalisations and everything stays finite; the finite-time
/// mLE at 2e4 is in the chaotic range (its 10 % convergence needs 1e6, see the ignored test).
#[test]
fn large_tau_keeps_deviation_vectors_finite() {
    let req = Requests::default();
    for tau in [10.0, 1000.0] {
        for (method, protocol) in ADAPTIVE {
            let (res, _) = run(
                method,
                Some(1e-12),
                protocol,
                c1(),
                &no_early_stop(tau, 2e4),
                &req,
            );
            let what = format!("{method} {protocol:?} τ = {tau}");
            assert_eq!(res.status, Status::Ok, "{what}");
            assert_eq!(res.t_reached, 2e4, "{what}");
            assert_eq!(res.class, Some(Class::Chaotic), "{what}");
            assert!(res.sali.is_finite() && res.sali < 1e-8, "{what}");
            // Measured 0.033–0.056 at 2e4 over these eight runs.
            assert!(
                res.mle.is_finite() && res.mle > 0.02 && res.mle < 0.08,
                "{what}: mLE {}",
                res.mle
            );
        }
    }
}

/// The renormalisation interval does not change the indicators: at t = 200 (before round-off
/// differences between the step sequences grow to visible size) τ = 10 and τ = 0.5 give the
/// same mLE. In the `free` protocol the steps do not depend on τ at all, so the mLE at t_final
/// is the same bits for τ = 10 and τ = 1e4.
#[test]
fn renormalisation_interval_does_not_change_the_indicators() {
    let req = Requests::default();
    for (method, protocol) in ADAPTIVE {
        let (a, _) = run(
            method,
            Some(1e-12),
            protocol,
            c1(),
            &no_early_stop(0.5, 200.0),
            &req,
        );
        let (b, _) = run(
            method,
            Some(1e-12),
            protocol,
            c1(),
            &no_early_stop(10.0, 200.0),
            &req,
        );
        assert!(
            (a.mle - b.mle).abs() < 1e-6,
            "{method} {protocol:?}: mLE(200) {} (τ = 0.5) vs {} (τ = 10)",
            a.mle,
            b.mle
        );
    }
    for method in ["dop853", "taylor"] {
        let (a, _) = run(
            method,
            Some(1e-12),
            Protocol::Free,
            c1(),
            &no_early_stop(10.0, 2e4),
            &req,
        );
        let (b, _) = run(
            method,
            Some(1e-12),
            Protocol::Free,
            c1(),
            &no_early_stop(1e4, 2e4),
            &req,
        );
        assert_eq!(a.steps, b.steps, "{method}");
        assert_eq!(
            a.mle.to_bits(),
            b.mle.to_bits(),
            "{method}: {} vs {}",
            a.mle,
            b.mle
        );
    }
}

/// Renormalisation intervals far beyond the growth f64 can hold: inside one interval ‖w‖
/// grows by e^(λτ), and ‖w‖² would overflow once ln‖w‖ > ln √(f64::MAX) ≈ 354.9, i.e. for
/// τ ≳ 6 000–8 000 on C1. `restart` renormalises early when a vector leaves the band (without
/// that it would end `non-finite` at t = 6 020 / 7 915); `free` renormalises at every step end.
/// Both stay finite (τ = 1e4 and 1e5 here, where e^(λτ) would overflow f64 itself).
#[test]
fn huge_tau_keeps_deviation_vectors_finite_in_both_protocols() {
    let req = Requests::default();
    for method in ["dop853", "taylor"] {
        let (res, _) = run(
            method,
            Some(1e-12),
            Protocol::Restart,
            c1(),
            &no_early_stop(1e4, 2e4),
            &req,
        );
        // Without renormalising inside the interval the squared norm would overflow at
        // t = 6 020 (DOP853) and 7 915 (Taylor); the restart driver renormalises early when a
        // vector leaves [2^-256, 2^256] in squared norm.
        assert_eq!(res.status, Status::Ok, "{method}");
        assert_eq!(res.t_reached, 2e4);
        assert!(
            res.mle.is_finite() && res.mle > 0.03 && res.mle < 0.06,
            "{method}: mLE {}",
            res.mle
        );

        let (free, _) = run(
            method,
            Some(1e-12),
            Protocol::Free,
            c1(),
            &no_early_stop(1e5, 2e5),
            &req,
        );
        assert_eq!(free.status, Status::Ok, "{method}");
        assert_eq!(free.t_reached, 2e5);
        assert!(
            free.mle.is_finite() && free.mle > 0.03 && free.mle < 0.06,
            "{method}: mLE {}",
            free.mle
        );
    }
}

/// The finite-time mLE of C1 needs t ~ 1e6 to be within 10 % of 0.045 (at 1e5 the eight
/// runs spread over 0.037–0.054); at 1e6 τ = 10, 1000 and 5000 all are.
#[test]
#[ignore = "long: C1 to t = 1e6 eight times (≈ 17 s); run by scripts/stability.sh"]
fn large_tau_mle_converges_to_the_sea_value() {
    let req = Requests::default();
    let mut runs: Vec<(f64, &str, Protocol)> =
        ADAPTIVE.iter().map(|&(m, p)| (10.0, m, p)).collect();
    for tau in [1000.0, 5000.0] {
        runs.push((tau, "dop853", Protocol::Restart));
        runs.push((tau, "taylor", Protocol::Restart));
    }
    for (tau, method, protocol) in runs {
        let (res, _) = run(
            method,
            Some(1e-12),
            protocol,
            c1(),
            &no_early_stop(tau, 1e6),
            &req,
        );
        assert_eq!(res.status, Status::Ok);
        assert!(
            (res.mle - MLE_SEA).abs() < 0.1 * MLE_SEA,
            "{method} {protocol:?} τ = {tau}: mLE(1e6) = {}",
            res.mle
        );
    }
}
