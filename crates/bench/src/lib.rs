//! The numerical core's benchmarks (`benches/`) and their timing harness. Each case runs in
//! samples of a calibrated number of calls, and the median time per element (step, orbit-step
//! or evaluation) is printed with the range of the samples. `cargo bench -p salient-bench
//! --bench NAME [FILTER]` measures the cases whose name contains FILTER; run without
//! `--bench` (as `cargo test --benches` does) every case runs once, as a smoke test.
//!
//! A package of their own so that they compile as the product's loops do (one codegen unit,
//! Cargo.toml) while salient-core's tests, in the same profile, take sixteen.

use std::time::{Duration, Instant};

/// Samples per case and the least time a sample takes: 20 samples of at least 0.15 s keep the
/// median steady to about 1 % on an idle host.
const SAMPLES: usize = 20;
const SAMPLE_TIME: Duration = Duration::from_millis(150);

/// Runs benchmark cases as cargo's arguments ask: measured, or each once as a smoke test.
pub struct Harness {
    measure: bool,
    filter: Option<String>,
}

impl Harness {
    /// Reads cargo's arguments: `--bench` to measure, then an optional name filter.
    pub fn from_args() -> Self {
        let args: Vec<String> = std::env::args().skip(1).collect();
        Harness {
            measure: args.iter().any(|a| a == "--bench"),
            filter: args.into_iter().find(|a| !a.starts_with('-')),
        }
    }

    /// Times `f`, one call of which handles `elements` elements of `unit`, as case `name`.
    pub fn case<R>(&self, name: &str, elements: u64, unit: &str, mut f: impl FnMut() -> R) {
        if self
            .filter
            .as_ref()
            .is_some_and(|w| !name.contains(w.as_str()))
        {
            return;
        }
        if !self.measure {
            std::hint::black_box(f());
            println!("{name}: ran once");
            return;
        }
        // Calls per sample: enough that a sample takes SAMPLE_TIME (warming the caches and the
        // clock on the way).
        let mut calls = 1u64;
        loop {
            let start = Instant::now();
            for _ in 0..calls {
                std::hint::black_box(f());
            }
            if start.elapsed() >= SAMPLE_TIME {
                break;
            }
            calls *= 2;
        }
        let mut per_element: Vec<f64> = (0..SAMPLES)
            .map(|_| {
                let start = Instant::now();
                for _ in 0..calls {
                    std::hint::black_box(f());
                }
                start.elapsed().as_secs_f64() * 1e9 / (calls * elements) as f64
            })
            .collect();
        per_element.sort_by(f64::total_cmp);
        println!(
            "{name:<36} {:>9.2} ns/{unit}   (median of {SAMPLES}; {:.2}–{:.2})",
            per_element[SAMPLES / 2],
            per_element[0],
            per_element[SAMPLES - 1]
        );
    }
}
