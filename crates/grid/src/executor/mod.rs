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
use crate::surface::Compiled;
use salient_core::orbit::{
    sample_steps, steps_to, Class, OrbitConfig, OrbitResult, Requests, Status,
};
use salient_core::run::{FeedDrivers, MethodRun};
use salient_core::section::Crossing;
use salient_core::tangent_map::batch::{BatchFeed, Isa};

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
fn crossed_cells<const N: usize>(grid: &Grid, crossings: &[Crossing<N>]) -> Vec<u32> {
    crossings
        .iter()
        .filter_map(|c| grid.cell_of(c.q[1], c.p[1]))
        .filter(|&c| grid.is_compatible(c))
        .collect()
}

/// The outcome of orbit `r` of `cell`, whose crossings fell in the compatible cells `visited`
/// (any order, repeats allowed).
fn outcome<const N: usize>(
    cell_run: &CellRun,
    checkpoints: &[u64],
    cell: u32,
    r: &OrbitResult<N>,
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
/// The phase-space point `cell`'s orbit starts from.
fn initial_point<const N: usize>(grid: &Grid, cell: u32) -> ([f64; N], [f64; N]) {
    grid.start(cell)
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

/// Runs `feed` to its end on the grid's system: tangent-map methods in the batched stepper
/// with [`lanes`] lanes, adaptive ones in their driver ([`FeedDrivers`]; `guided`: the feed
/// follows a forecast, see [`salient_core::run::integrate_feed_adaptive`]). Each driver is a
/// `dyn BatchFeed`, a call per orbit or crossing that costs nothing beside a step.
fn drive_feed<F: BatchFeed<2> + BatchFeed<3>>(
    grid: &Grid,
    cell_run: &CellRun,
    mode: Mode,
    requests: &Requests,
    guided: bool,
    feed: &mut F,
) {
    match grid.surface.compiled() {
        Compiled::Space(s) => drive_on::<_, 3>(s, grid, cell_run, mode, requests, guided, feed),
        _ => drive_plane(grid, cell_run, mode, requests, guided, feed),
    }
}

/// [`drive_feed`] on a system of 2 degrees of freedom, the only ones fast PSS runs in.
fn drive_plane(
    grid: &Grid,
    cell_run: &CellRun,
    mode: Mode,
    requests: &Requests,
    guided: bool,
    feed: &mut dyn BatchFeed<2>,
) {
    match grid.surface.compiled() {
        Compiled::HenonHeiles(h) => drive_on(h, grid, cell_run, mode, requests, guided, feed),
        Compiled::Plane(s) => drive_on(s, grid, cell_run, mode, requests, guided, feed),
        Compiled::Space(_) => {
            panic!("a 3-dof system has no 2-dof driver (the spec refuses fast PSS in 3 dof)")
        }
    }
}

/// [`drive_feed`] on `system`.
fn drive_on<S: FeedDrivers<N>, const N: usize>(
    system: &S,
    grid: &Grid,
    cell_run: &CellRun,
    mode: Mode,
    requests: &Requests,
    guided: bool,
    feed: &mut dyn BatchFeed<N>,
) {
    system.integrate_feed_run(
        &cell_run.run,
        grid.energy,
        &cell_run.config,
        requests,
        (lanes(mode), guided),
        feed,
    )
}
