//! Profiling target for the batched stepper (`perf record
//! ./target/release/examples/batch_profile`): 64 regular orbits, SBAB2C τ = 0.05, t = 1e4; prints
//! ns per orbit-step for 4 lanes on the pinned target level and 8 lanes in the copy compiled for
//! the host's widest vectors (`Isa::detect`: AVX-512 where the CPU has it). An argument `4` or `8`
//! runs only that one.

use salient_core::orbit::{OrbitConfig, Requests};
use salient_core::section::on_section;
use salient_core::tangent_map::batch::{integrate_batch_on, Isa};
use salient_core::{HenonHeiles, Scheme, TangentMap};

fn run<const L: usize>(isa: Isa) {
    let ham = HenonHeiles;
    let map = TangentMap::new(&ham, &Scheme::by_name("sbab2c").unwrap(), 0.05);
    let ics: Vec<_> = (0..64)
        .map(|i| on_section(&ham, 0.125, &[0.55 + 0.0005 * i as f64], &[0.0]).unwrap())
        .collect();
    let cfg = OrbitConfig::new(0.05, 1e4);
    let mut sali = 0.0;
    let t = std::time::Instant::now();
    integrate_batch_on::<_, 2, 2, L>(isa, &map, &ics, &cfg, &Requests::default(), |_, r| {
        sali += r.sali
    });
    let el = t.elapsed().as_secs_f64();
    println!(
        "lanes {L} {isa:?}: {:.2} ns/orbit-step (sum of SALI {})",
        el * 1e9 / (64.0 * 2e5),
        sali
    );
}

fn main() {
    let only = std::env::args().nth(1);
    if only.as_deref() != Some("8") {
        run::<4>(Isa::Pinned);
        run::<4>(Isa::detect());
    }
    if only.as_deref() != Some("4") {
        run::<8>(Isa::detect());
    }
}
