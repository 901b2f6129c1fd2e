//! Per-step cost of the Taylor integrator on R1 with 2 deviation vectors (12 ODEs), natural
//! steps to t = 1e4, for side-by-side runs with heyoka (`scripts/bench-heyoka.sh`).
//! Usage: taylor_steps [DELTA]

use salient_core::adaptive::taylor::Taylor;
use salient_core::orbit::initial_vectors;
use salient_core::phase::Phase;
use salient_core::section::on_section;
use salient_core::{Deviation, Hamiltonian, HenonHeiles};
use std::time::Instant;

fn main() {
    let delta: f64 = std::env::args()
        .nth(1)
        .map_or(1e-15, |s| s.parse().expect("DELTA"));
    let (q, p) = on_section(&HenonHeiles, 0.125, &[0.558], &[0.0]).unwrap();
    let (dq, dp) = initial_vectors::<2, 2>(Deviation::Axes);
    let mut best = f64::INFINITY;
    let mut steps = 0;
    let mut energy = 0.0;
    for _ in 0..5 {
        let mut t = Taylor::new(&HenonHeiles, delta, 0.0, Phase { q, p, dq, dp });
        let start = Instant::now();
        while t.t() < 1e4 {
            t.step(1e4).unwrap();
        }
        best = best.min(start.elapsed().as_secs_f64());
        steps = t.steps;
        energy = ((HenonHeiles.energy(&t.y.q, &t.y.p) - 0.125) / 0.125).abs();
    }
    println!(
        "salient taylor  tol {delta:e} order {:>2}  steps {steps}  {:.3} ms  {:.0} ns/step  |dH/H| {energy:.1e}",
        salient_core::adaptive::taylor::order_for(delta),
        best * 1e3,
        best * 1e9 / steps as f64
    );
}
