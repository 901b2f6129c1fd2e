//! Systems of polynomial potentials given as text: Hénon–Heiles through the polynomial path
//! gives the built-in's orbits to rounding, and on another potential the tangent map is the
//! Jacobian of the numerical step and symplectic, correctors included.

use crate::common::{c1, r1, ENERGY};
use salient_core::orbit::{integrate, Class, OrbitConfig, Requests};
use salient_core::polynomial::{Polynomial, PolynomialSystem};
use salient_core::tangent::Phase;
use salient_core::{Hamiltonian, HenonHeiles, Scheme, TangentMap};

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

/// Central differences of the orbit-only step against the tangent map, and MᵀJM = J, for
/// every scheme (correctors use the third derivatives) on a quartic potential that is not
/// Hénon–Heiles.
#[test]
fn the_tangent_map_of_another_potential_is_the_jacobian_and_symplectic() {
    let ham = system("q1^2/2 + 0.7*q2^2 + 0.3*q1^4 - q1*q2^3/5 + q2^2*q1 - 0.1*q1^3*q2");
    let x = ([0.2, -0.15], [0.3, 0.25]);
    for scheme in Scheme::all() {
        let tau = 0.1;
        let map = TangentMap::new(&ham, &scheme, tau);
        let mut ph: Phase<f64, 2, 4> = Phase::zero();
        (ph.q, ph.p) = x;
        for k in 0..4 {
            if k < 2 {
                ph.dq[k][k] = 1.0;
            } else {
                ph.dp[k][k - 2] = 1.0;
            }
        }
        map.step(&mut ph, tau);
        let m = |i: usize, k: usize| if i < 2 { ph.dq[k][i] } else { ph.dp[k][i - 2] };
        let e = 1e-5;
        for k in 0..4 {
            let (mut xp, mut xm) = (x, x);
            if k < 2 {
                xp.0[k] += e;
                xm.0[k] -= e;
            } else {
                xp.1[k - 2] += e;
                xm.1[k - 2] -= e;
            }
            map.orbit_step(&mut xp.0, &mut xp.1, tau);
            map.orbit_step(&mut xm.0, &mut xm.1, tau);
            for i in 0..4 {
                let (a, b) = if i < 2 {
                    (xp.0[i], xm.0[i])
                } else {
                    (xp.1[i - 2], xm.1[i - 2])
                };
                let fd = (a - b) / (2.0 * e);
                assert!(
                    (fd - m(i, k)).abs() <= 1e-7 * m(i, k).abs().max(1.0),
                    "{}: M[{i}][{k}] = {} but finite differences give {fd}",
                    scheme.name,
                    m(i, k)
                );
            }
        }
        // MᵀJM = J with J = [[0, I], [−I, 0]].
        let j = |r: usize, c: usize| match (r, c) {
            (0, 2) | (1, 3) => 1.0,
            (2, 0) | (3, 1) => -1.0,
            _ => 0.0,
        };
        for r in 0..4 {
            for c in 0..4 {
                let mut v = 0.0;
                for a in 0..4 {
                    for b in 0..4 {
                        v += m(a, r) * j(a, b) * m(b, c);
                    }
                }
                assert!(
                    (v - j(r, c)).abs() < 1e-12,
                    "{}: (MᵀJM)[{r}][{c}] = {v}",
                    scheme.name
                );
            }
        }
    }
}
