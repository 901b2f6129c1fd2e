//! Profiling target for the batched stepper (`perf record ./target/release/examples/batch_profile`):
//! 64 regular orbits, SBAB2C τ = 0.05, t = 1e4, 4 lanes; prints ns per orbit-step.

use salient_core::batch::integrate_batch;
use salient_core::orbit::{OrbitConfig, Requests};
use salient_core::section::on_section;
use salient_core::{HenonHeiles, Scheme, TangentMap};
fn main() {
    let ham = HenonHeiles;
    let map = TangentMap::new(&ham, &Scheme::by_name("sbab2c").unwrap(), 0.05);
    let ics: Vec<_> = (0..64)
        .map(|i| on_section(&ham, 0.125, &[0.55 + 0.0005 * i as f64], &[0.0]).unwrap())
        .collect();
    let cfg = OrbitConfig::new(0.05, 1e4);
    let t = std::time::Instant::now();
    let mut s = 0.0;
    integrate_batch::<_, 2, 2, 4>(&map, &ics, &cfg, &Requests::default(), |_, r| s += r.sali);
    let el = t.elapsed().as_secs_f64();
    println!("{s} {:.2} ns/orbit-step", el * 1e9 / (64.0 * 2e5));
}
