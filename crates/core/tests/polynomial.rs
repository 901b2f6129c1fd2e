//! Systems of polynomial potentials given as text: Hénon–Heiles through the polynomial path
//! gives the built-in's orbits to rounding, and on another potential the tangent map is the
//! Jacobian of the numerical step and symplectic, correctors included.

use crate::common::{c1, r1, ENERGY};
use crate::integrators::assert_jacobian_and_symplectic;
use salient_core::orbit::{integrate, Class, OrbitConfig, Requests};
use salient_core::polynomial::{Polynomial, PolynomialSystem};
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
