//! ns per step of the tangent-map method: one orbit (latency-bound) and batches of orbits in
//! SIMD lanes (throughput-bound), on the pinned target level and, where the host has it,
//! AVX-512. Throughput is reported per orbit-step. The `polynomial` cases run Hénon–Heiles
//! given as text through the polynomial path, beside the built-in's hand-fused formulas.

use salient_bench::Harness;
use salient_core::orbit::{integrate, OrbitConfig, Requests};
use salient_core::section::on_section;
use salient_core::systems::polynomial::{Polynomial, PolynomialSystem};
use salient_core::tangent_map::batch::{integrate_batch_on, Isa};
use salient_core::{Hamiltonian, HenonHeiles, Scheme, TangentMap};
use std::hint::black_box;

const STEPS: u64 = 20_000;

/// Hénon–Heiles as a polynomial potential given as text.
fn henon_heiles_as_text() -> PolynomialSystem<2> {
    PolynomialSystem::new(Polynomial::parse("(q1^2 + q2^2)/2 + q1^2*q2 - q2^3/3", 2).unwrap())
}

fn single<H: Hamiltonian<2>>(h: &Harness, ham: &H, label: &str) {
    for name in ["sbab2c", "saba2c", "srkn14a"] {
        let tau = 0.05;
        let map = TangentMap::new(ham, &Scheme::by_name(name).unwrap(), tau);
        let (q, p) = on_section(&HenonHeiles, 0.125, &[0.558], &[0.0]).unwrap();
        let cfg = OrbitConfig::new(tau, STEPS as f64 * tau);
        h.case(
            &format!("single-orbit/tm/{name}{label}"),
            STEPS,
            "step",
            || integrate::<_, 2, 2>(&map, black_box(q), black_box(p), &cfg, &Requests::default()),
        );
    }
}

fn regular_ics(n: usize) -> Vec<([f64; 2], [f64; 2])> {
    // Points near R1: regular, so no lane stops early and every lane does STEPS steps.
    (0..n)
        .map(|i| on_section(&HenonHeiles, 0.125, &[0.55 + 0.0005 * i as f64], &[0.0]).unwrap())
        .collect()
}

fn batched<H: Hamiltonian<2>, const L: usize>(h: &Harness, isa: Isa, ham: &H, label: &str) {
    let map = TangentMap::new(ham, &Scheme::by_name("sbab2c").unwrap(), 0.05);
    let ics = regular_ics(32);
    let cfg = OrbitConfig::new(0.05, STEPS as f64 * 0.05);
    let name = match isa {
        Isa::Pinned => "sbab2c-lanes-pinned",
        Isa::Avx512 => "sbab2c-lanes-avx512",
    };
    h.case(
        &format!("batch/{name}/{L}{label}"),
        STEPS * 32,
        "orbit-step",
        || {
            let mut sum = 0.0;
            integrate_batch_on::<_, 2, 2, L>(
                isa,
                &map,
                black_box(&ics),
                &cfg,
                &Requests::default(),
                |_, r| sum += r.sali,
            );
            sum
        },
    );
}

fn main() {
    let h = Harness::from_args();
    let text = henon_heiles_as_text();
    single(&h, &HenonHeiles, "");
    single(&h, &text, "/polynomial");
    batched::<_, 1>(&h, Isa::Pinned, &HenonHeiles, "");
    batched::<_, 4>(&h, Isa::Pinned, &HenonHeiles, "");
    batched::<_, 8>(&h, Isa::Pinned, &HenonHeiles, "");
    batched::<_, 4>(&h, Isa::Pinned, &text, "/polynomial");
    if Isa::Avx512.available() {
        batched::<_, 8>(&h, Isa::Avx512, &HenonHeiles, "");
        batched::<_, 16>(&h, Isa::Avx512, &HenonHeiles, "");
        batched::<_, 8>(&h, Isa::Avx512, &text, "/polynomial");
    }
}
