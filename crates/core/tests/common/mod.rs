#![allow(dead_code)]

use salient_core::orbit::{integrate, OrbitConfig, OrbitResult, Requests};
use salient_core::section::on_section;
use salient_core::{HenonHeiles, Scheme, TangentMap};

pub const ENERGY: f64 = 0.125;

/// A Hénon–Heiles point on the section q1 = 0, p1 > 0 at H = 1/8.
pub fn ic(q2: f64, p2: f64) -> ([f64; 2], [f64; 2]) {
    on_section(&HenonHeiles, ENERGY, &[q2], &[p2]).expect("IC on the section")
}

/// The seed paper's named orbits (Gerlach & Skokos, arXiv:1008.1890).
pub fn r1() -> ([f64; 2], [f64; 2]) {
    ic(0.558, 0.0)
}
pub fn c1() -> ([f64; 2], [f64; 2]) {
    ic(-0.25, 0.0)
}

/// Max-norm distance between two phase-space points.
pub fn dist(a: &([f64; 2], [f64; 2]), b: &([f64; 2], [f64; 2])) -> f64 {
    (0..2)
        .map(|i| (a.0[i] - b.0[i]).abs().max((a.1[i] - b.1[i]).abs()))
        .fold(0.0, f64::max)
}

/// R1 by SRKN14a at τ = 1e-3 to `t_final`: the reference the adaptive methods are held to.
pub fn srkn14a_r1(t_final: f64, requests: &Requests) -> OrbitResult<2> {
    let map = TangentMap::new(&HenonHeiles, &Scheme::by_name("srkn14a").unwrap(), 1e-3);
    let x = r1();
    integrate::<_, 2, 2>(&map, x.0, x.1, &OrbitConfig::new(1e-3, t_final), requests)
}

/// Max-norm distance between the end points of two runs.
pub fn end_distance(a: &OrbitResult<2>, b: &OrbitResult<2>) -> f64 {
    dist(&(a.q_end, a.p_end), &(b.q_end, b.p_end))
}
