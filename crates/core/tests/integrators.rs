//! Accuracy of the tangent-map integrators: convergence orders, tangent maps against finite
//! differences, symplecticity, energy conservation and an exact periodic orbit.

#![allow(clippy::needless_range_loop, clippy::excessive_precision)]

use crate::common::{dist, ic, r1};
use salient_core::orbit::{integrate, OrbitConfig, Requests};
use salient_core::phase::Phase;
use salient_core::tangent_map::map::Stepping;
use salient_core::{Hamiltonian, HenonHeiles, Scheme, TangentMap};

/// The orbit alone advanced to `t` with steps τ through the production (merged) stepping loop.
fn orbit_at(scheme: &Scheme, tau: f64, t: f64, x0: ([f64; 2], [f64; 2])) -> ([f64; 2], [f64; 2]) {
    let ham = HenonHeiles;
    let map = TangentMap::new(&ham, scheme, tau);
    let mut s = Stepping::new(
        &map,
        Phase::<f64, 2, 0> {
            q: x0.0,
            p: x0.1,
            dq: [],
            dp: [],
        },
    );
    for _ in 0..(t / tau).round() as u64 {
        s.advance();
    }
    (s.x.q, s.x.p)
}

/// Observed order from runs at τ and τ/2 against a reference run of SRKN14a at τ = 1e-3.
fn observed_order(scheme: &Scheme, tau: f64) -> f64 {
    let reference = orbit_at(&Scheme::by_name("srkn14a").unwrap(), 1e-3, 10.0, r1());
    let e1 = dist(&orbit_at(scheme, tau, 10.0, r1()), &reference);
    let e2 = dist(&orbit_at(scheme, tau / 2.0, 10.0, r1()), &reference);
    (e1 / e2).log2()
}

#[test]
fn convergence_orders_on_r1_match_theory() {
    for scheme in Scheme::all() {
        // Steps where the error is far above round-off and in the asymptotic regime.
        let tau = match scheme.order {
            6 => 0.3125,
            4 if scheme.name == "aba864" => 0.25,
            _ => 0.1,
        };
        let order = observed_order(&scheme, tau);
        eprintln!("{:>8}: observed order {order:.3}", scheme.name);
        assert!(
            (order - scheme.order as f64).abs() <= 0.2,
            "{}: observed order {order:.3}, expected {}",
            scheme.name,
            scheme.order
        );
    }
}

#[test]
fn a_corrector_with_the_wrong_sign_is_caught_by_the_order_test() {
    for name in ["sbab2c", "saba2c", "sbab3c", "saba4c"] {
        let good = Scheme::by_name(name).unwrap();
        let bad = good.with_corrector(-good.corrector);
        let order = observed_order(&bad, 0.1);
        assert!(
            (order - 4.0).abs() > 0.2,
            "{name} with the wrong corrector sign still shows order {order:.3}"
        );
        assert!(
            (order - 2.0).abs() < 0.3,
            "{name}: wrong sign gives order {order:.3}"
        );
    }
}

/// The one-step tangent matrix M (column k = the image of the k-th phase-space axis, rows
/// q then p) at x, one deviation vector per axis.
fn tangent_matrix<H: Hamiltonian<N>, const N: usize>(
    map: &TangentMap<'_, H>,
    x: ([f64; N], [f64; N]),
    h: f64,
) -> Vec<Vec<f64>> {
    let mut m = vec![vec![0.0; 2 * N]; 2 * N];
    for k in 0..2 * N {
        let mut ph: Phase<f64, N, 1> = Phase::zero();
        ph.q = x.0;
        ph.p = x.1;
        if k < N {
            ph.dq[0][k] = 1.0;
        } else {
            ph.dp[0][k - N] = 1.0;
        }
        map.step(&mut ph, h);
        for i in 0..N {
            m[i][k] = ph.dq[0][i];
            m[i + N][k] = ph.dp[0][i];
        }
    }
    m
}

/// The tangent map of one step τ at x equals central differences of the orbit-only step, and
/// is symplectic (MᵀJM = J); `label` names the case in failures.
pub fn assert_jacobian_and_symplectic<H: Hamiltonian<N>, const N: usize>(
    map: &TangentMap<'_, H>,
    x: ([f64; N], [f64; N]),
    tau: f64,
    label: &str,
) {
    let m = tangent_matrix(map, x, tau);
    let e = 1e-5;
    let component = |y: &([f64; N], [f64; N]), i: usize| if i < N { y.0[i] } else { y.1[i - N] };
    for k in 0..2 * N {
        let mut xp = x;
        let mut xm = x;
        if k < N {
            xp.0[k] += e;
            xm.0[k] -= e;
        } else {
            xp.1[k - N] += e;
            xm.1[k - N] -= e;
        }
        map.orbit_step(&mut xp.0, &mut xp.1, tau);
        map.orbit_step(&mut xm.0, &mut xm.1, tau);
        for i in 0..2 * N {
            let fd = (component(&xp, i) - component(&xm, i)) / (2.0 * e);
            let scale = m[i][k].abs().max(1.0);
            assert!(
                (fd - m[i][k]).abs() <= 1e-7 * scale,
                "{label}: M[{i}][{k}] = {} but finite differences give {fd}",
                m[i][k]
            );
        }
    }
    // MᵀJM = J with J = [[0, I], [−I, 0]].
    let j = |r: usize, c: usize| {
        if c == r + N {
            1.0
        } else if r == c + N {
            -1.0
        } else {
            0.0
        }
    };
    for r in 0..2 * N {
        for c in 0..2 * N {
            let mut s = 0.0;
            for a in 0..2 * N {
                for b in 0..2 * N {
                    s += m[a][r] * j(a, b) * m[b][c];
                }
            }
            assert!(
                (s - j(r, c)).abs() <= 1e-12,
                "{label}: (MᵀJM)[{r}][{c}] = {s}"
            );
        }
    }
}

#[test]
fn tangent_map_is_the_jacobian_of_the_numerical_step_and_symplectic() {
    let ham = HenonHeiles;
    let points = [r1(), ic(-0.25, 0.0), ic(0.1, 0.3), ic(0.335036, -0.385631)];
    for scheme in Scheme::all() {
        for tau in [0.05, 0.5] {
            let map = TangentMap::new(&ham, &scheme, tau);
            for x in points {
                assert_jacobian_and_symplectic(&map, x, tau, &format!("{} τ={tau}", scheme.name));
            }
        }
    }
}

#[test]
fn sbab2c_conserves_r1_energy_without_secular_growth() {
    let ham = HenonHeiles;
    let scheme = Scheme::by_name("sbab2c").unwrap();
    let tau = 0.05;
    let map = TangentMap::new(&ham, &scheme, tau);
    let x0 = r1();
    let h0 = ham.energy(&x0.0, &x0.1);
    let mut s = Stepping::new(
        &map,
        Phase::<f64, 2, 0> {
            q: x0.0,
            p: x0.1,
            dq: [],
            dp: [],
        },
    );
    let n = (1e5 / tau) as u64;
    let (mut first_half, mut second_half) = (0.0f64, 0.0f64);
    for i in 1..=n {
        s.advance();
        let e = ((ham.energy(&s.x.q, &s.x.p) - h0) / h0).abs();
        if i <= n / 2 {
            first_half = first_half.max(e);
        } else {
            second_half = second_half.max(e);
        }
    }
    assert!(
        first_half.max(second_half) < 5e-7,
        "max |ΔH/H| = {}",
        first_half.max(second_half)
    );
    // A bounded oscillation has the same envelope in both halves; drift would grow it.
    assert!(
        second_half < 1.25 * first_half,
        "envelope grew: {first_half:e} → {second_half:e}"
    );
}

#[test]
fn straight_line_periodic_orbit_returns_after_its_exact_period() {
    // Through (q2, p2) = (0, ±1/4): period 7.5432594126750786 (computed with mpmath).
    const PERIOD: f64 = 7.543_259_412_675_078_6;
    let ham = HenonHeiles;
    let map = TangentMap::new(&ham, &Scheme::by_name("srkn14a").unwrap(), 1e-3);
    for p2 in [0.25, -0.25] {
        let x0 = ic(0.0, p2);
        assert!((x0.1[0] - 3f64.sqrt() / 4.0).abs() < 1e-16);
        let cfg = OrbitConfig::new(1e-3, 8.0);
        let req = Requests {
            crossings: true,
            ..Requests::default()
        };
        let res = integrate::<_, 2, 2>(&map, x0.0, x0.1, &cfg, &req);
        assert_eq!(res.crossings.len(), 1, "one return within t = 8");
        let c = res.crossings[0];
        assert!(
            (c.t - PERIOD).abs() < 1e-8,
            "return time {} vs {PERIOD}",
            c.t
        );
        assert!(c.q[1].abs() < 1e-9 && (c.p[1] - p2).abs() < 1e-9, "{c:?}");
        assert!(c.q[0].abs() < 1e-12 && c.p[0] > 0.0);
    }
}

#[test]
fn time_is_exact_after_many_steps() {
    let ham = HenonHeiles;
    let map = TangentMap::new(&ham, &Scheme::by_name("sbab2c").unwrap(), 0.1);
    let x0 = r1();
    let res = integrate::<_, 2, 2>(
        &map,
        x0.0,
        x0.1,
        &OrbitConfig::new(0.1, 1e5),
        &Requests::default(),
    );
    assert_eq!(res.steps, 1_000_000);
    assert_eq!(res.t_reached, 1e5);
}

/// An anisotropic 3-D harmonic oscillator, V = ½ Σ ω_i² q_i²: nothing in the integrators may
/// assume Hénon–Heiles or two degrees of freedom, and this system has an exact solution.
struct Oscillator3 {
    omega: [f64; 3],
}

impl Hamiltonian<3> for Oscillator3 {
    fn name(&self) -> &'static str {
        "oscillator-3"
    }
    fn potential<T: salient_core::arith::real::Real>(&self, q: &[T; 3]) -> T {
        let mut v = T::splat(0.0);
        for i in 0..3 {
            v += T::splat(0.5 * self.omega[i] * self.omega[i]) * q[i] * q[i];
        }
        v
    }
    fn grad<T: salient_core::arith::real::Real>(&self, q: &[T; 3]) -> [T; 3] {
        core::array::from_fn(|i| T::splat(self.omega[i] * self.omega[i]) * q[i])
    }
    fn hess_vec<T: salient_core::arith::real::Real>(&self, _q: &[T; 3], u: &[T; 3]) -> [T; 3] {
        core::array::from_fn(|i| T::splat(self.omega[i] * self.omega[i]) * u[i])
    }
    fn third_vec<T: salient_core::arith::real::Real>(
        &self,
        _q: &[T; 3],
        _w: &[T; 3],
        _u: &[T; 3],
    ) -> [T; 3] {
        [T::splat(0.0); 3]
    }
}

#[test]
fn integrators_are_generic_in_the_number_of_degrees_of_freedom() {
    let ham = Oscillator3 {
        omega: [1.0, 2f64.sqrt(), 0.7],
    };
    let (q0, p0) = ([0.3, -0.2, 0.5], [0.1, 0.4, -0.3]);
    let exact = |t: f64| -> ([f64; 3], [f64; 3]) {
        let mut q = [0.0; 3];
        let mut p = [0.0; 3];
        for i in 0..3 {
            let w = ham.omega[i];
            q[i] = q0[i] * (w * t).cos() + p0[i] / w * (w * t).sin();
            p[i] = -q0[i] * w * (w * t).sin() + p0[i] * (w * t).cos();
        }
        (q, p)
    };
    let err = |scheme: &Scheme, tau: f64| {
        let map = TangentMap::new(&ham, scheme, tau);
        let mut s = Stepping::new(
            &map,
            Phase::<f64, 3, 2> {
                q: q0,
                p: p0,
                dq: [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]],
                dp: [[0.0; 3]; 2],
            },
        );
        for _ in 0..(10.0 / tau).round() as u64 {
            s.advance();
        }
        let (q, p) = exact(10.0);
        // For a linear system the tangent map is the map itself: δq of the first vector is the
        // solution started from (e1, 0).
        let dq_exact = (10.0 * ham.omega[0]).cos();
        (0..3)
            .map(|i| (s.x.q[i] - q[i]).abs().max((s.x.p[i] - p[i]).abs()))
            .fold((s.x.dq[0][0] - dq_exact).abs(), f64::max)
    };
    for (name, order) in [
        ("sbab2c", 4.0),
        ("saba3c", 4.0),
        ("srkn14a", 6.0),
        ("sbab3", 2.0),
    ] {
        let scheme = Scheme::by_name(name).unwrap();
        let tau = if order == 6.0 { 0.3125 } else { 0.1 };
        let observed = (err(&scheme, tau) / err(&scheme, tau / 2.0)).log2();
        assert!(
            (observed - order).abs() < 0.25,
            "{name} on a 3-D oscillator: order {observed:.3}"
        );
    }
}
