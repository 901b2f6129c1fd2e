//! The tile executor: integrates cells on the current rayon pool — a fixed list
//! ([`integrate_cells`]), a worker's stream of leased cells ([`integrate_stream`]), or the cells
//! the embedded ledger needs next ([`run_embedded`]) — and turns each orbit into an [`Outcome`].
//! Tangent-map methods run [`lanes`] orbits at a time in the batched stepper; adaptive methods
//! one orbit per task. An outcome depends only on its cell, never on scheduling, so any
//! partition of the work gives the same bits. One module per engine (cells, stream, embedded),
//! over the claims they share; this module turns an orbit into an outcome.

mod cells;
mod claims;
mod embedded;
mod stream;

pub use cells::{integrate_cells, trace_cells, OrbitTrace};
pub use claims::{Claims, LocalLedger};
pub use embedded::{run_embedded, run_embedded_forecast, run_embedded_resumed, takes_forecast};
pub use stream::{integrate_stream, tells_crossings, CellSource, Take, Verdict};

use crate::geometry::Grid;
use crate::ledger::{CellIndicators, Mode, Outcome};
use salient_core::batch::{BatchFeed, Isa};
use salient_core::method::Method;
use salient_core::orbit::{
    sample_steps, steps_to, Class, OrbitConfig, OrbitResult, Requests, Status,
};
use salient_core::run::{
    integrate_feed_adaptive_henon_heiles, integrate_feed_henon_heiles, MethodRun,
};
use salient_core::section::on_section;
use salient_core::section::Crossing;
use salient_core::{HenonHeiles, TangentMap};

/// Orbits advanced together in one batched stepper on the pinned target level, and the unit
/// in which schedulers size their batches (see [`lanes`] for what runs).
pub const LANES: usize = 4;

/// Orbits advanced together in one batched stepper in `mode`. Full mode takes what suits the
/// host ([`Isa::lanes`]: 8 with AVX-512). In fast PSS the lanes in flight bound the
/// speculation, so it takes [`LANES`] (4) on every host: 8 lanes step faster per orbit-step
/// but drop more steps, and 4 lanes run in the AVX-512 copy too, so 4 win at small τ as well
/// (figures: docs/performance.md).
pub fn lanes(mode: Mode) -> usize {
    match mode {
        Mode::FastPss => LANES,
        Mode::Full => Isa::detect().lanes(),
    }
}

/// Runs the batched driver with [`lanes`] lanes (the copy compiled in salient-core: every
/// feed drives it as a `dyn BatchFeed`, a call per orbit or crossing that costs nothing beside
/// a step).
fn drive(
    map: &TangentMap<'_, HenonHeiles>,
    config: &OrbitConfig,
    requests: &Requests,
    mode: Mode,
    feed: &mut dyn BatchFeed<2>,
) {
    integrate_feed_henon_heiles(Isa::detect(), lanes(mode), map, config, requests, feed)
}

/// How every cell's orbit is integrated.
#[derive(Clone, Debug, PartialEq)]
pub struct CellRun {
    /// The method with its settings.
    pub run: MethodRun,
    /// What to integrate (τ, t_final, thresholds, deviation vectors).
    pub config: OrbitConfig,
    /// Log-spaced checkpoints per decade at which full-mode orbits are also classified (0: none).
    pub checkpoints_per_decade: u32,
    /// The finite-time mLE, MEGNO and FLI of every orbit (full mode only).
    pub indicators: bool,
}

impl CellRun {
    /// Steps (multiples of τ) of the checkpoints.
    pub fn checkpoint_steps(&self) -> Vec<u64> {
        sample_steps(
            self.checkpoints_per_decade,
            steps_to(self.config.t_final, self.config.tau),
        )
    }
}

/// The compatible cells of `crossings`, in crossing order, repeats included.
fn crossed_cells(grid: &Grid, crossings: &[Crossing<2>]) -> Vec<u32> {
    crossings
        .iter()
        .filter_map(|c| grid.cell_of(c.q[1], c.p[1]))
        .filter(|&c| grid.is_compatible(c))
        .collect()
}

/// The outcome of orbit `r` of `cell`, whose crossings fell in the compatible cells `visited`
/// (any order, repeats allowed).
fn outcome(
    cell_run: &CellRun,
    checkpoints: &[u64],
    cell: u32,
    r: &OrbitResult<2>,
    mut visited: Vec<u32>,
) -> Outcome {
    visited.sort_unstable();
    visited.dedup();
    let tau = cell_run.config.tau;
    let th = cell_run.config.thresholds;
    let classes = checkpoints
        .iter()
        .map(|&n| {
            let t = n as f64 * tau;
            match r.series.iter().find(|s| s.t == t) {
                Some(s) => Some(th.classify(s.sali)),
                // Past an early stop the orbit stays chaotic; past an escape or a failure it has
                // no class.
                None => (r.status == Status::ChaoticEarlyStop).then_some(Class::Chaotic),
            }
        })
        .collect();
    Outcome {
        cell,
        class: r.class,
        status: r.status,
        sali: r.sali,
        visited,
        steps: r.steps,
        t_end: r.t_reached,
        checkpoints: classes,
        indicators: r.growth.map(|g| CellIndicators {
            mle: r.mle,
            megno: g.megno,
            megno_mean: g.megno_mean,
            fli: g.fli,
        }),
    }
}
fn initial_point(grid: &Grid, cell: u32) -> ([f64; 2], [f64; 2]) {
    let (q2, p2) = grid.centre(cell);
    on_section(&HenonHeiles, grid.energy, &[q2], &[p2])
        .expect("compatible cells lie on the section")
}

fn requests_for(cell_run: &CellRun, mode: Mode) -> Requests {
    Requests {
        crossings: mode == Mode::FastPss,
        samples_per_decade: cell_run.checkpoints_per_decade,
        growth: cell_run.indicators && mode == Mode::Full,
        ..Requests::default()
    }
}

/// The tangent map of a tangent-map method; `None` for the adaptive ones.
fn tangent_map(cell_run: &CellRun) -> Option<TangentMap<'static, HenonHeiles>> {
    match &cell_run.run.method {
        Method::TangentMap(scheme) => {
            Some(TangentMap::new(&HenonHeiles, scheme, cell_run.config.tau))
        }
        _ => None,
    }
}

/// Runs `feed` to its end: in the batched stepper with `map`, else in the adaptive driver.
fn drive_feed(
    grid: &Grid,
    cell_run: &CellRun,
    mode: Mode,
    map: Option<&TangentMap<'_, HenonHeiles>>,
    requests: &Requests,
    feed: &mut dyn BatchFeed<2>,
) {
    match map {
        Some(map) => drive(map, &cell_run.config, requests, mode, feed),
        None => drive_adaptive(grid, cell_run, requests, false, feed),
    }
}

/// The adaptive methods' driver over a [`BatchFeed`]: orbits in SIMD lanes or one at a time
/// ([`salient_core::run::feed_orbits_per_thread`]; `guided`: the feed follows a forecast),
/// each crossing reported as it is located, abandonment polled every few steps.
fn drive_adaptive(
    grid: &Grid,
    cell_run: &CellRun,
    requests: &Requests,
    guided: bool,
    feed: &mut dyn BatchFeed<2>,
) {
    integrate_feed_adaptive_henon_heiles(
        &cell_run.run,
        grid.energy,
        &cell_run.config,
        requests,
        guided,
        feed,
    );
}
