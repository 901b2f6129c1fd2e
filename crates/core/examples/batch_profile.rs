//! Profiling target for the batched stepper (`perf record ./target/release/examples/batch_profile`):
//! 64 regular orbits, SBAB2C τ = 0.05, t = 1e4; prints ns per orbit-step for 4 lanes on the
//! pinned target level and 8 lanes in the copy compiled for the host's widest vectors
//! (`Isa::detect`: AVX-512 where the CPU has it). An argument `4` or `8` runs only that one.

use salient_core::batch::{integrate_feed_on, BatchFeed, Feed, Isa};
use salient_core::orbit::{OrbitConfig, OrbitResult, Requests};
use salient_core::section::on_section;
use salient_core::{HenonHeiles, Scheme, TangentMap};

struct Sum<'a> {
    ics: &'a [([f64; 2], [f64; 2])],
    next: usize,
    sali: f64,
}

impl BatchFeed<2> for Sum<'_> {
    fn next(&mut self, _all_idle: bool) -> Feed<2> {
        let Some(&(q, p)) = self.ics.get(self.next) else {
            return Feed::Done;
        };
        self.next += 1;
        Feed::Orbit(self.next - 1, q, p)
    }
    fn finished(&mut self, _id: usize, result: OrbitResult<2>) {
        self.sali += result.sali;
    }
}

fn run<const L: usize>(isa: Isa) {
    let ham = HenonHeiles;
    let map = TangentMap::new(&ham, &Scheme::by_name("sbab2c").unwrap(), 0.05);
    let ics: Vec<_> = (0..64)
        .map(|i| on_section(&ham, 0.125, &[0.55 + 0.0005 * i as f64], &[0.0]).unwrap())
        .collect();
    let cfg = OrbitConfig::new(0.05, 1e4);
    let mut feed = Sum {
        ics: &ics,
        next: 0,
        sali: 0.0,
    };
    let t = std::time::Instant::now();
    integrate_feed_on::<_, 2, 2, L>(isa, &map, &cfg, &Requests::default(), &mut feed);
    let el = t.elapsed().as_secs_f64();
    println!(
        "lanes {L} {isa:?}: {:.2} ns/orbit-step (sum of SALI {})",
        el * 1e9 / (64.0 * 2e5),
        feed.sali
    );
}

fn main() {
    let only = std::env::args().nth(1);
    if only.as_deref() != Some("8") {
        run::<4>(Isa::Pinned);
    }
    if only.as_deref() != Some("4") {
        run::<8>(Isa::detect());
    }
}
