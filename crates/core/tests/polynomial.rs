//! Systems of polynomial potentials given as text: Hénon–Heiles through the polynomial path
//! gives the built-in's orbits to rounding, and on another potential the tangent map is the
//! Jacobian of the numerical step and symplectic, correctors included.

use crate::common::{c1, r1, ENERGY};
use crate::integrators::assert_jacobian_and_symplectic;
use proptest::prelude::*;
use salient_core::adaptive::dop853::{Dop853, Dop853Config};
use salient_core::adaptive::driver::Protocol;
use salient_core::adaptive::taylor::Taylor;
use salient_core::arith::dd::DoubleDouble;
use salient_core::arith::real::Real;
use salient_core::orbit::{initial_vectors, integrate, Class, OrbitConfig, OrbitResult, Requests};
use salient_core::run::{run_orbit, MethodRun, PolynomialRun, Vectors};
use salient_core::systems::polynomial::{named, Polynomial, PolynomialSystem};
use salient_core::systems::series::{Series, TaylorSeries, P_MAX};
use salient_core::{Deviation, Hamiltonian, HenonHeiles, Method, Phase, Scheme, TangentMap};
use std::f64::consts::PI;

fn system(text: &str) -> PolynomialSystem<2> {
    PolynomialSystem::new(Polynomial::parse(text, 2).unwrap())
}

#[test]
fn henon_heiles_as_text_runs_r1_and_c1_as_the_built_in() {
    let text = system("(q1^2 + q2^2)/2 + q1^2*q2 - q2^3/3");
    let scheme = Scheme::by_name("sbab2c").unwrap();
    let config = OrbitConfig::new(0.05, 1e3);
    for (name, x) in [("R1", r1()), ("C1", c1())] {
        let built_in = TangentMap::new(&HenonHeiles, &scheme, 0.05);
        let from_text = TangentMap::new(&text, &scheme, 0.05);
        let a = integrate::<_, 2, 2>(&built_in, x.0, x.1, &config, &Requests::default());
        let b = integrate::<_, 2, 2>(&from_text, x.0, x.1, &config, &Requests::default());
        assert_eq!(a.class, b.class, "{name}");
        assert_eq!(a.status, b.status, "{name}");
        if a.class == Some(Class::Regular) {
            assert!(
                (a.sali - b.sali).abs() < 1e-10,
                "{name}: {} {}",
                a.sali,
                b.sali
            );
        }
        assert!(
            (HenonHeiles.energy(&x.0, &x.1) - ENERGY).abs() < 1e-15
                && (text.energy(&x.0, &x.1) - ENERGY).abs() < 1e-15
        );
    }
}

/// Every scheme's tangent map (correctors use the third derivatives) is the Jacobian of its
/// step and symplectic on a quartic potential that is not Hénon–Heiles.
#[test]
fn the_tangent_map_of_another_potential_is_the_jacobian_and_symplectic() {
    let ham = system("q1^2/2 + 0.7*q2^2 + 0.3*q1^4 - q1*q2^3/5 + q2^2*q1 - 0.1*q1^3*q2");
    for scheme in Scheme::all() {
        for tau in [0.05, 0.1] {
            let map = TangentMap::new(&ham, &scheme, tau);
            let label = format!("{} τ={tau}", scheme.name);
            assert_jacobian_and_symplectic(&map, ([0.2, -0.15], [0.3, 0.25]), tau, &label);
        }
    }
}

/// Draws uniform in [0, 1) from a xorshift generator seeded with `seed` (reproducible cases
/// without a dependency).
fn uniform_draws(seed: u64) -> impl FnMut() -> f64 {
    let mut state = seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) | 1;
    move || {
        state ^= state << 13;
        state ^= state >> 7;
        state ^= state << 17;
        (state >> 11) as f64 / (1u64 << 53) as f64
    }
}

/// A bounded random potential in `N` coordinates: ½ Σ ω_i q_i² + ¼ Σ q_i⁴ plus random cubic
/// and quartic couplings with coefficients in [−0.2, 0.2].
fn random_system<const N: usize>(seed: u64) -> PolynomialSystem<N> {
    let mut next = uniform_draws(seed);
    let mut text = String::new();
    for i in 1..=N {
        text += &format!("+ {}*q{i}^2/2 + q{i}^4/4 ", 0.6 + next());
    }
    for _ in 0..6 {
        let c = 0.4 * next() - 0.2;
        let (i, j) = (
            1 + (next() * N as f64) as usize,
            1 + (next() * N as f64) as usize,
        );
        let (a, b) = (1 + (next() * 2.0) as u32, 1 + (next() * 2.0) as u32);
        text += &format!("+ ({c})*q{i}^{a}*q{j}^{b} ");
    }
    PolynomialSystem::new(Polynomial::parse(&text, N).unwrap())
}

/// Max-norm distance between two phase points with their deviation vectors, relative to the
/// larger component.
fn phase_distance<const N: usize, const K: usize>(
    a: &Phase<f64, N, K>,
    b: &Phase<f64, N, K>,
) -> f64 {
    let (mut d, mut size) = (0.0f64, 1.0f64);
    a.zip_for_each(b, |x, y| {
        d = d.max((x - y).abs());
        size = size.max(x.abs());
    });
    d / size
}

/// A random cubic potential in 2 dof: a well with small cubic terms (the Taylor recursion's
/// fixed-size path).
fn random_cubic(seed: u64) -> PolynomialSystem<2> {
    let mut next = uniform_draws(seed);
    let mut text = format!(
        "{}*q1^2/2 + {}*q2^2/2 + {}*q1*q2",
        0.6 + next(),
        0.6 + next(),
        0.2 * next()
    );
    for (a, b) in [(3, 0), (2, 1), (1, 2), (0, 3), (1, 0)] {
        text += &format!(" + ({})*q1^{a}*q2^{b}", 0.6 * next() - 0.3);
    }
    PolynomialSystem::new(Polynomial::parse(&text, 2).unwrap())
}

/// The Taylor recursion generated from a random polynomial (Cauchy products planned from its
/// monomials, or the fixed-size recursion of a cubic in 2 dof) integrates the orbit and its
/// deviation vectors as DOP853 does at a tight tolerance, in 2 and 3 degrees of freedom, in f64
/// and in double-double.
#[test]
fn taylor_series_of_a_random_polynomial_agree_with_dop853() {
    fn check<const N: usize>(ham: PolynomialSystem<N>, seed: u64) {
        let (dq, dp) = initial_vectors::<N, 2>(Deviation::Axes);
        let q = core::array::from_fn(|i| 0.3 - 0.1 * i as f64);
        let p = core::array::from_fn(|i| 0.2 + 0.05 * i as f64);
        let y = Phase { q, p, dq, dp };
        let t_end = 20.0;
        let mut dop = Dop853::new(&ham, Dop853Config::with_delta(1e-13), 0.0, y);
        while dop.t < t_end {
            dop.step(t_end, None).unwrap();
        }
        let mut taylor = Taylor::new(&ham, 1e-15, 0.0, y);
        while taylor.t() < t_end {
            taylor.step(t_end).unwrap();
        }
        let d = phase_distance(&taylor.interpolate(t_end), &dop.y);
        assert!(
            d < 1e-9,
            "{N} dof, seed {seed}: Taylor against DOP853 {d:e}"
        );
        let ydd = Phase {
            q: q.map(DoubleDouble::from_f64),
            p: p.map(DoubleDouble::from_f64),
            dq: dq.map(|v| v.map(DoubleDouble::from_f64)),
            dp: dp.map(|v| v.map(DoubleDouble::from_f64)),
        };
        let mut dd = Taylor::new(&ham, 1e-15, 0.0, ydd);
        while dd.t() < t_end {
            dd.step(t_end).unwrap();
        }
        let end = dd.interpolate(t_end);
        let end = Phase {
            q: end.q.map(|x| x.to_f64()),
            p: end.p.map(|x| x.to_f64()),
            dq: end.dq.map(|v| v.map(|x| x.to_f64())),
            dp: end.dp.map(|v| v.map(|x| x.to_f64())),
        };
        let d = phase_distance(&end, &dop.y);
        assert!(
            d < 1e-9,
            "{N} dof, seed {seed}: taylor-dd against DOP853 {d:e}"
        );
    }
    for seed in [1, 2, 3] {
        check::<2>(random_system(seed), seed);
        check::<3>(random_system(seed + 10), seed + 10);
        check::<2>(random_cubic(seed + 20), seed + 20);
    }
}

/// Hénon–Heiles as text runs R1 and C1 with DOP853, f64 Taylor and taylor-dd as the built-in
/// does: the same classes and statuses, R1's SALI within 1e-10.
#[test]
fn henon_heiles_as_text_runs_every_adaptive_method_as_the_built_in() {
    let text = system("(q1^2 + q2^2)/2 + q1^2*q2 - q2^3/3");
    let config = OrbitConfig::new(0.05, 1e3);
    for method in [Method::Dop853, Method::Taylor, Method::TaylorDd] {
        let run = MethodRun {
            method: method.clone(),
            delta: Some(1e-10),
            protocol: Protocol::Restart,
        };
        for (name, x) in [("R1", r1()), ("C1", c1())] {
            let requests = Requests::default();
            let a: OrbitResult<2> =
                run_orbit::<_, 2, 2>(&HenonHeiles, &run, ENERGY, x.0, x.1, &config, &requests);
            let b = run_orbit::<_, 2, 2>(&text, &run, ENERGY, x.0, x.1, &config, &requests);
            let label = format!("{method:?} {name}");
            assert_eq!((a.class, a.status), (b.class, b.status), "{label}");
            if a.class == Some(Class::Regular) {
                assert!(
                    (a.sali - b.sali).abs() < 1e-10,
                    "{label}: {} {}",
                    a.sali,
                    b.sali
                );
            }
        }
    }
}

/// The Hénon–Heiles text's planned Taylor coefficients equal the built-in's hand-written
/// recursion to rounding, order by order, for arbitrary series.
#[test]
fn planned_taylor_coefficients_equal_the_hand_written_ones() {
    let text = system("(q1^2 + q2^2)/2 + q1^2*q2 - q2^3/3");
    let mut x = 0.3f64;
    let mut next = || {
        x = (x * 3.7 + 0.19).fract();
        2.0 * x - 1.0
    };
    let q: [Series<f64>; 2] = core::array::from_fn(|_| core::array::from_fn(|_| next()));
    let u: [[Series<f64>; 2]; 3] =
        core::array::from_fn(|_| core::array::from_fn(|_| core::array::from_fn(|_| next())));
    let mut mine = vec![[0.0; P_MAX + 1]; HenonHeiles.derived_series()];
    let mut theirs = vec![[0.0; P_MAX + 1]; text.derived_series()];
    for k in 0..20 {
        let (g, h) = HenonHeiles.all_coeffs(&q, &u, &mut mine, k);
        let (gt, ht) = text.all_coeffs(&q, &u, &mut theirs, k);
        let close = |a: f64, b: f64| (a - b).abs() <= 1e-13 * (1.0 + a.abs());
        for i in 0..2 {
            assert!(close(g[i], gt[i]), "k {k} ∇V_{i}: {} {}", g[i], gt[i]);
            for v in 0..3 {
                assert!(close(h[v][i], ht[v][i]), "k {k} vector {v} row {i}");
            }
        }
    }
}

/// The compiled corrector terms equal their composition from the gradient, the Hessian and the
/// third derivatives (the trait's defaults), and the derivative bounds hold on a ball: in 3
/// degrees of freedom, on a random system.
#[test]
fn compiled_corrector_terms_and_bounds_hold_on_a_random_system() {
    struct Composed<'a>(&'a PolynomialSystem<3>);
    impl Hamiltonian<3> for Composed<'_> {
        fn name(&self) -> &'static str {
            "composed"
        }
        fn potential<T: Real>(&self, q: &[T; 3]) -> T {
            self.0.potential(q)
        }
        fn grad<T: Real>(&self, q: &[T; 3]) -> [T; 3] {
            self.0.grad(q)
        }
        fn hess_vec<T: Real>(&self, q: &[T; 3], u: &[T; 3]) -> [T; 3] {
            self.0.hess_vec(q, u)
        }
        fn third_vec<T: Real>(&self, q: &[T; 3], w: &[T; 3], u: &[T; 3]) -> [T; 3] {
            self.0.third_vec(q, w, u)
        }
    }
    let ham = random_system::<3>(7);
    let composed = Composed(&ham);
    let norm = |v: [f64; 3]| v.iter().map(|x| x * x).sum::<f64>().sqrt();
    let frobenius = |m: [[f64; 3]; 3]| m.iter().map(|r| norm(*r).powi(2)).sum::<f64>().sqrt();
    let r = 0.8;
    let bounds = ham.derivative_bounds(r).unwrap();
    for i in 0..200 {
        let s = i as f64;
        let dir = [
            (0.7 * s).sin(),
            (1.3 * s + 0.2).cos(),
            (0.37 * s).sin() - 0.3,
        ];
        let scale = r * ((i % 10) as f64 + 1.0) / 10.0 / norm(dir);
        let q = dir.map(|x| x * scale);
        let (gk, hk) = (ham.corrector_grad(&q), ham.corrector_hessian(&q));
        let (gk2, hk2) = (composed.corrector_grad(&q), composed.corrector_hessian(&q));
        for a in 0..3 {
            assert!(
                (gk[a] - gk2[a]).abs() <= 1e-12 * (1.0 + gk2[a].abs()),
                "∇K at {q:?}"
            );
            for b in 0..3 {
                assert!((hk[a][b] - hk2[a][b]).abs() <= 1e-12 * (1.0 + hk2[a][b].abs()));
            }
        }
        // Frobenius norms bound the spectral ones the bounds are for.
        assert!(norm(ham.grad(&q)) <= bounds.grad);
        assert!(frobenius(ham.hessian(&q)) <= bounds.hessian);
        assert!(norm(gk) <= bounds.corrector_grad);
        assert!(frobenius(hk) <= bounds.corrector_hessian);
    }
}

/// GALI_k's laws (Skokos, Bountis & Antonopoulos, Physica D 231, 2007) on three coupled
/// oscillators with frequencies 1, √2, √3 and cubic couplings q1²q2 and q1²q3: on a regular
/// orbit (a 3-torus) GALI_2 and GALI_3 keep their size while GALI_4, GALI_5 and GALI_6 fall
/// as t^−2, t^−4 and t^−6; on a chaotic orbit every GALI_k falls exponentially, so
/// log GALI_k grows in magnitude in proportion to t.
#[test]
fn gali_follows_its_laws_on_a_three_dof_system() {
    let ham: PolynomialSystem<3> = PolynomialSystem::new(
        Polynomial::parse(
            "q1^2/2 + q2^2 + 1.5*q3^2 + 1.189207115*q1^2*q2 + 1.316074013*q1^2*q3",
            3,
        )
        .unwrap(),
    );
    let run = MethodRun {
        method: Method::TangentMap(Scheme::by_name("sbab2c").unwrap()),
        delta: None,
        protocol: Protocol::Restart,
    };
    let requests = Requests {
        gali: true,
        ..Requests::default()
    };
    let gali = |start: ([f64; 3], [f64; 3]), t_final: f64| {
        let mut config = OrbitConfig::new(0.05, t_final);
        config.thresholds.early_stop = false;
        let energy = ham.energy(&start.0, &start.1);
        let r = ham.run(&run, energy, start, &config, &requests, Vectors::All);
        assert_eq!(r.gali.len(), 5, "GALI_2 … GALI_6");
        r.gali.iter().map(|g| g.log10()).collect::<Vec<f64>>()
    };
    let regular = ([0.1, 0.05, -0.05], [0.15, 0.1, 0.05]);
    let (early, late) = (gali(regular, 5e3), gali(regular, 5e4));
    for k in 0..2 {
        assert!(
            early[k] > -1.5 && (late[k] - early[k]).abs() < 0.5,
            "regular GALI_{}: 10^{:.2} → 10^{:.2}",
            k + 2,
            early[k],
            late[k]
        );
    }
    for (k, power) in [(2, -2.0), (3, -4.0), (4, -6.0)] {
        let slope = late[k] - early[k];
        assert!(
            (slope - power).abs() < 0.25 * power.abs(),
            "regular GALI_{}: slope {slope:.2} per decade, law {power}",
            k + 2
        );
    }
    // Until the vectors align to rounding (GALI_2 near 1e-15, about t = 1000 here).
    let chaotic = ([0.0; 3], [0.42, 0.05, 0.05]);
    let (at1, at2) = (gali(chaotic, 250.0), gali(chaotic, 500.0));
    for k in 0..5 {
        assert!(
            at2[k] < -8.0,
            "chaotic GALI_{} only 10^{:.2}",
            k + 2,
            at2[k]
        );
        let ratio = at2[k] / at1[k];
        assert!(
            (1.5..2.5).contains(&ratio),
            "chaotic GALI_{}: 10^{:.2} at t = 250, 10^{:.2} at 500",
            k + 2,
            at1[k],
            at2[k]
        );
    }
}

/// The FPU-β chain of 8 particles with fixed ends (q0 = q9 = 0), β = 1, written out as text:
/// V = Σ_{i=0}^{8} [(q_{i+1} − q_i)²/2 + β (q_{i+1} − q_i)⁴/4].
fn fpu_beta_8() -> PolynomialSystem<8> {
    let q = |i: usize| match i {
        0 | 9 => "0".to_string(),
        i => format!("q{i}"),
    };
    let text: Vec<String> = (0..=8)
        .map(|i| {
            let d = format!("({} - {})", q(i + 1), q(i));
            format!("{d}^2/2 + {d}^4/4")
        })
        .collect();
    PolynomialSystem::new(Polynomial::parse(&text.join(" + "), 8).unwrap())
}

/// The chain by name ([`named::fpu_beta`]) is the chain written out by hand.
#[test]
fn the_named_fpu_beta_chain_is_the_written_one() {
    let named = Polynomial::parse(&named::fpu_beta(8, 1.0), 8).unwrap();
    assert_eq!(&named, fpu_beta_8().potential_polynomial());
}

/// The 8-particle FPU-β chain: the tangent map of every scheme is the Jacobian of its step and
/// symplectic in 16 dimensions, and the energy is conserved along an orbit that starts in
/// the lowest normal mode (the tangent map to its order, Taylor to its tolerance).
#[test]
fn an_eight_particle_fpu_beta_chain_runs_and_conserves_energy() {
    let ham = fpu_beta_8();
    // The lowest mode's shape, sin(iπ/9), with amplitude 0.5.
    let q: [f64; 8] = core::array::from_fn(|i| 0.5 * ((i + 1) as f64 * PI / 9.0).sin());
    let p: [f64; 8] = core::array::from_fn(|i| 0.1 * ((i + 1) as f64 * 2.0 * PI / 9.0).sin());
    for name in ["sbab2c", "saba2c", "srkn14a"] {
        let map = TangentMap::new(&ham, &Scheme::by_name(name).unwrap(), 0.05);
        assert_jacobian_and_symplectic(&map, (q, p), 0.05, &format!("FPU-β {name}"));
    }
    let energy = ham.energy(&q, &p);
    let requests = Requests {
        energy: true,
        ..Requests::default()
    };
    let mut config = OrbitConfig::new(0.05, 1e3);
    config.thresholds.early_stop = false;
    for (method, delta, bound) in [
        (
            Method::TangentMap(Scheme::by_name("sbab2c").unwrap()),
            None,
            1e-7,
        ),
        (Method::Taylor, Some(1e-13), 1e-12),
        (Method::Dop853, Some(1e-13), 1e-12),
    ] {
        let run = MethodRun {
            method: method.clone(),
            delta,
            protocol: Protocol::Restart,
        };
        let r = ham.run(&run, energy, (q, p), &config, &requests, Vectors::Two);
        let error = r.energy_error_max.unwrap();
        assert_eq!(r.t_reached, 1e3, "{method:?}: {:?}", r.status);
        assert!(error < bound, "{method:?}: max |ΔH/H| {error:e}");
    }
}

/// The end point of the orbit from `x` after `t` with `scheme` at step `tau`.
fn end_point<H: Hamiltonian<2>>(
    ham: &H,
    scheme: &Scheme,
    tau: f64,
    t: f64,
    x: ([f64; 2], [f64; 2]),
) -> ([f64; 2], [f64; 2]) {
    let map = TangentMap::new(ham, scheme, tau);
    let (mut q, mut p) = x;
    for _ in 0..(t / tau).round() as u64 {
        map.orbit_step(&mut q, &mut p, tau);
    }
    (q, p)
}

/// Every scheme shows its order (2, 4 or 6) on a quartic potential that is not Hénon–Heiles:
/// runs at τ and τ/2 against SRKN14a at τ = 1e-3, to t = 10.
#[test]
fn convergence_orders_on_another_potential_match_theory() {
    let ham = system("q1^2/2 + 0.7*q2^2 + 0.3*q1^4 - q1*q2^3/5 + q2^2*q1 - 0.1*q1^3*q2");
    let x = ([0.2, -0.15], [0.3, 0.25]);
    let reference = end_point(&ham, &Scheme::by_name("srkn14a").unwrap(), 1e-3, 10.0, x);
    let dist = |a: ([f64; 2], [f64; 2])| {
        (0..2)
            .map(|i| {
                (a.0[i] - reference.0[i])
                    .abs()
                    .max((a.1[i] - reference.1[i]).abs())
            })
            .fold(0.0, f64::max)
    };
    for scheme in Scheme::all() {
        let tau = match scheme.order {
            6 => 0.3125,
            4 if scheme.name == "aba864" => 0.25,
            _ => 0.1,
        };
        let e1 = dist(end_point(&ham, &scheme, tau, 10.0, x));
        let e2 = dist(end_point(&ham, &scheme, tau / 2.0, 10.0, x));
        let order = (e1 / e2).log2();
        assert!(
            (order - scheme.order as f64).abs() <= 0.25,
            "{}: observed order {order:.3}, expected {}",
            scheme.name,
            scheme.order
        );
    }
}

/// Text for the polynomial Σ c_t Π q_i^{e_ti} of `terms` in `dof` coordinates.
fn text_of(terms: &[(f64, Vec<u32>)]) -> String {
    let term = |(c, powers): &(f64, Vec<u32>)| {
        let mut t = format!("({c:e})");
        for (i, e) in powers.iter().enumerate() {
            t += &format!("*q{}^{e}", i + 1);
        }
        t
    };
    terms.iter().map(term).collect::<Vec<_>>().join(" + ")
}

fn polynomial_case(dof: usize) -> impl Strategy<Value = (Vec<(f64, Vec<u32>)>, Vec<f64>)> {
    let term = (-1.0..1.0f64, prop::collection::vec(0u32..4, dof));
    (
        prop::collection::vec(term, 1..8),
        prop::collection::vec(-0.5..0.5f64, dof),
    )
}

/// Exact first and second derivatives of a random polynomial (read from text) against central
/// differences of the polynomial itself; mixed partials equal in either order.
fn derivatives_match_differences(
    terms: &[(f64, Vec<u32>)],
    q: &[f64],
) -> Result<(), TestCaseError> {
    let dof = q.len();
    let v = Polynomial::parse(&text_of(terms), dof).unwrap();
    let h = 1e-5;
    for k in 0..dof {
        let (mut up, mut down) = (q.to_vec(), q.to_vec());
        up[k] += h;
        down[k] -= h;
        let d = v.derivative(k);
        let fd = (v.eval(&up) - v.eval(&down)) / (2.0 * h);
        prop_assert!(
            (d.eval(q) - fd).abs() < 1e-7,
            "∂{k}: {} against {fd}",
            d.eval(q)
        );
        for j in 0..dof {
            let d2 = d.derivative(j);
            // Mixed partials commute exactly.
            prop_assert_eq!(&d2, &v.derivative(j).derivative(k));
            let fd2 = (v.derivative(j).eval(&up) - v.derivative(j).eval(&down)) / (2.0 * h);
            prop_assert!(
                (d2.eval(q) - fd2).abs() < 1e-6,
                "∂{j}∂{k}: {} against {fd2}",
                d2.eval(q)
            );
        }
    }
    Ok(())
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 64, ..ProptestConfig::default() })]

    #[test]
    fn derivatives_of_random_polynomials_in_2_dof((terms, q) in polynomial_case(2)) {
        derivatives_match_differences(&terms, &q)?;
    }

    #[test]
    fn derivatives_of_random_polynomials_in_3_dof((terms, q) in polynomial_case(3)) {
        derivatives_match_differences(&terms, &q)?;
    }

    #[test]
    fn derivatives_of_random_polynomials_in_8_dof((terms, q) in polynomial_case(8)) {
        derivatives_match_differences(&terms, &q)?;
    }
}
