//! Cost of locating one section crossing: the same orbits integrated with and without
//! crossings requested (SBAB2C, τ = 0.5, t = 1e5, 16 orbits from regular to chaotic).
//!
//! cargo run --release -p salient-core --example crossing_cost

use salient_core::orbit::{integrate, OrbitConfig, Requests};
use salient_core::section::on_section;
use salient_core::{HenonHeiles, Scheme, TangentMap};
use std::time::Instant;

fn main() {
    let ham = HenonHeiles;
    let tau = 0.5;
    let map = TangentMap::new(&ham, &Scheme::by_name("sbab2c").unwrap(), tau);
    let ics: Vec<_> = (0..16)
        .map(|i| on_section(&ham, 0.125, &[0.3 + 0.02 * i as f64], &[0.0]).unwrap())
        .collect();
    let mut cfg = OrbitConfig::new(tau, 1e5);
    cfg.thresholds.early_stop = false;
    let run = |crossings: bool| {
        let requests = Requests {
            crossings,
            ..Requests::default()
        };
        let t = Instant::now();
        let mut n = 0usize;
        for &(q, p) in &ics {
            n += integrate::<_, 2, 2>(&map, q, p, &cfg, &requests)
                .crossings
                .len();
        }
        (t.elapsed().as_secs_f64(), n)
    };
    let best = |crossings: bool| {
        (0..5)
            .map(|_| run(crossings))
            .min_by(|a, b| a.0.total_cmp(&b.0))
            .unwrap()
    };
    let (without, _) = best(false);
    let (with, n) = best(true);
    println!(
        "{n} crossings: {:.1} ns per crossing ({with:.3} s with, {without:.3} s without)",
        (with - without) * 1e9 / n as f64
    );
}
