//! ns per step of the tangent-map method: one orbit (latency-bound) and batches of orbits in
//! SIMD lanes (throughput-bound), on the pinned target level and, where the host has it,
//! AVX-512. Throughput is reported per orbit-step.

use salient_bench::Harness;
use salient_core::batch::{integrate_batch_on, Isa};
use salient_core::orbit::{integrate, OrbitConfig, Requests};
use salient_core::section::on_section;
use salient_core::{HenonHeiles, Scheme, TangentMap};
use std::hint::black_box;

const STEPS: u64 = 20_000;

fn single(h: &Harness) {
    let ham = HenonHeiles;
    for name in ["sbab2c", "saba2c", "srkn14a"] {
        let tau = 0.05;
        let map = TangentMap::new(&ham, &Scheme::by_name(name).unwrap(), tau);
        let (q, p) = on_section(&ham, 0.125, &[0.558], &[0.0]).unwrap();
        let cfg = OrbitConfig::new(tau, STEPS as f64 * tau);
        h.case(&format!("single-orbit/tm/{name}"), STEPS, "step", || {
            integrate::<_, 2, 2>(&map, black_box(q), black_box(p), &cfg, &Requests::default())
        });
    }
}

fn regular_ics(n: usize) -> Vec<([f64; 2], [f64; 2])> {
    // Points near R1: regular, so no lane stops early and every lane does STEPS steps.
    (0..n)
        .map(|i| on_section(&HenonHeiles, 0.125, &[0.55 + 0.0005 * i as f64], &[0.0]).unwrap())
        .collect()
}

fn batched<const L: usize>(h: &Harness, isa: Isa) {
    let ham = HenonHeiles;
    let map = TangentMap::new(&ham, &Scheme::by_name("sbab2c").unwrap(), 0.05);
    let ics = regular_ics(32);
    let cfg = OrbitConfig::new(0.05, STEPS as f64 * 0.05);
    let name = match isa {
        Isa::Pinned => "sbab2c-lanes-pinned",
        Isa::Avx512 => "sbab2c-lanes-avx512",
    };
    h.case(
        &format!("batch/{name}/{L}"),
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
    single(&h);
    batched::<1>(&h, Isa::Pinned);
    batched::<4>(&h, Isa::Pinned);
    batched::<8>(&h, Isa::Pinned);
    if Isa::Avx512.available() {
        batched::<8>(&h, Isa::Avx512);
        batched::<16>(&h, Isa::Avx512);
    }
}
