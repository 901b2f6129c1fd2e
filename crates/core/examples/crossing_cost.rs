//! Cost of locating one section crossing, one at a time (`locate_upward`, the one-orbit
//! driver's path) and four at a time in SIMD lanes (`locate_upward_lanes`, full searches to
//! the root), and eight at a time to the cells of a 400×400 grid of (q2, p2)
//! (`locate_upward_lanes_settling`, the batched driver's for fast PSS): the crossing steps of
//! 16 orbits (SBAB2C, τ = 0.5, t = 5e4) located again and again, best of 5.
//!
//! cargo run --release -p salient-core --example crossing_cost

use salient_core::section::{
    locate_upward, locate_upward_lanes, locate_upward_lanes_settling, on_section,
    upward_crossing_steps, Crossing, CrossingStep,
};
use salient_core::{HenonHeiles, Scheme, TangentMap};
use std::hint::black_box;
use std::time::Instant;

fn main() {
    let ham = HenonHeiles;
    let tau = 0.5;
    let map = TangentMap::new(&ham, &Scheme::by_name("sbab2c").unwrap(), tau);
    let starts: Vec<CrossingStep<2>> = (0..16)
        .flat_map(|i| {
            let (q, p) = on_section(&ham, 0.125, &[0.3 + 0.02 * i as f64], &[0.0]).unwrap();
            upward_crossing_steps(&map, q, p, 100_000)
        })
        .collect();
    let best = |f: &dyn Fn() -> f64| {
        (0..5)
            .map(|_| {
                let t = Instant::now();
                black_box(f());
                t.elapsed().as_secs_f64()
            })
            .fold(f64::INFINITY, f64::min)
    };
    let scalar = best(&|| {
        starts
            .iter()
            .map(|step| locate_upward(&map, step).q[1])
            .sum()
    });
    let lanes = best(&|| {
        starts
            .chunks(4)
            .map(|c| locate_upward_lanes::<_, 2, 4>(&map, c)[0].q[1])
            .sum()
    });
    // The grid's default section bounds at H = 1/8 (`default_bounds`), 400 cells each way.
    let (q2_lo, q2_hi) = (-0.439_692_620_785_908_4, 0.673_648_177_666_930_3);
    let p2_hi = 0.5f64;
    let cell = |x: f64, lo: f64, hi: f64| ((x - lo) / ((hi - lo) / 400.0)).floor();
    let settled = std::cell::Cell::new(0usize);
    let same_cell = |c: &Crossing<2>, r: f64| {
        let ok = cell(c.q[1] - r, q2_lo, q2_hi) == cell(c.q[1] + r, q2_lo, q2_hi)
            && cell(c.p[1] - r, -p2_hi, p2_hi) == cell(c.p[1] + r, -p2_hi, p2_hi);
        settled.set(settled.get() + !ok as usize);
        ok
    };
    let to_cells = best(&|| {
        settled.set(0);
        starts
            .chunks(8)
            .map(|c| locate_upward_lanes_settling::<_, 2, 8>(&map, c, &same_cell)[0].q[1])
            .sum()
    });
    let n = starts.len() as f64;
    println!(
        "{} crossings: {:.1} ns each one at a time, {:.1} ns each four at a time in lanes, \
         {:.1} ns each eight at a time to cells ({:.2} % of the crossings not settled at their first partial step)",
        starts.len(),
        scalar * 1e9 / n,
        lanes * 1e9 / n,
        to_cells * 1e9 / n,
        100.0 * settled.get() as f64 / n
    );
}
