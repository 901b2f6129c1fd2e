//! The tile executor: integrates a list of cells (a tile's unmarked cells, or the next cells of
//! the embedded frontier) on the current rayon pool and turns each orbit into an [`Outcome`].
//! Tangent-map methods run `LANES` orbits at a time in the batched stepper; adaptive methods
//! one orbit per task. An outcome depends only on its cell, never on scheduling, so any
//! partition of the work gives the same bits.

use crate::geometry::Grid;
use crate::ledger::{Ledger, Mode, Outcome};
use rayon::prelude::*;
use salient_core::batch::integrate_batch;
use salient_core::method::Method;
use salient_core::orbit::{
    sample_steps, steps_to, Class, OrbitConfig, OrbitResult, Requests, Status,
};
use salient_core::run::{run_orbit, MethodRun};
use salient_core::section::on_section;
use salient_core::{HenonHeiles, TangentMap};

/// Orbits advanced together in one batched stepper.
pub const LANES: usize = 4;

/// How every cell's orbit is integrated.
#[derive(Clone, Debug, PartialEq)]
pub struct CellRun {
    pub run: MethodRun,
    pub config: OrbitConfig,
    /// Log-spaced checkpoints per decade at which full-mode orbits are also classified (0: none).
    pub checkpoints_per_decade: u32,
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

fn outcome(
    grid: &Grid,
    cell_run: &CellRun,
    checkpoints: &[u64],
    cell: u32,
    r: &OrbitResult<2>,
) -> Outcome {
    let mut visited: Vec<u32> = r
        .crossings
        .iter()
        .filter_map(|c| grid.cell_of(c.q[1], c.p[1]))
        .filter(|&c| grid.is_compatible(c))
        .collect();
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
        checkpoints: classes,
    }
}

/// Integrates `cells` (compatible cells of `grid`) and returns their outcomes in the same order.
pub fn integrate_cells(grid: &Grid, cell_run: &CellRun, mode: Mode, cells: &[u32]) -> Vec<Outcome> {
    let ham = HenonHeiles;
    let requests = Requests {
        crossings: mode == Mode::FastPss,
        samples_per_decade: cell_run.checkpoints_per_decade,
        ..Requests::default()
    };
    let checkpoints = cell_run.checkpoint_steps();
    let ic = |cell: u32| {
        let (q2, p2) = grid.centre(cell);
        on_section(&ham, grid.energy, &[q2], &[p2]).expect("compatible cells lie on the section")
    };
    match &cell_run.run.method {
        Method::TangentMap(scheme) if requests.samples_per_decade == 0 => {
            let map = TangentMap::new(&ham, scheme, cell_run.config.tau);
            cells
                .par_chunks(LANES)
                .flat_map_iter(|chunk| {
                    let ics: Vec<_> = chunk.iter().map(|&c| ic(c)).collect();
                    let mut out: Vec<Option<Outcome>> = vec![None; chunk.len()];
                    integrate_batch::<_, 2, 2, LANES>(
                        &map,
                        &ics,
                        &cell_run.config,
                        &requests,
                        |i, r| {
                            out[i] = Some(outcome(grid, cell_run, &checkpoints, chunk[i], &r));
                        },
                    );
                    out.into_iter().map(|o| o.expect("every orbit reported"))
                })
                .collect()
        }
        _ => cells
            .par_iter()
            .map(|&cell| {
                let (q, p) = ic(cell);
                let r = run_orbit::<_, 2, 2>(
                    &ham,
                    &cell_run.run,
                    grid.energy,
                    q,
                    p,
                    &cell_run.config,
                    &requests,
                );
                outcome(grid, cell_run, &checkpoints, cell, &r)
            })
            .collect(),
    }
}

/// Runs a whole grid in this process: repeatedly integrates the next `window` cells the ledger
/// needs (in parallel on the current rayon pool) and offers their outcomes, until every
/// compatible cell is labelled. The window bounds the speculative work that commits may drop.
pub fn run_embedded(
    grid: &Grid,
    cell_run: &CellRun,
    mode: Mode,
    window: usize,
    mut progress: impl FnMut(&Ledger),
) -> Ledger {
    let mut ledger = Ledger::new(grid, mode);
    while !ledger.done() {
        let cells = ledger.needed(window.max(1), &|_| false);
        for o in integrate_cells(grid, cell_run, mode, &cells) {
            ledger.offer(o);
        }
        progress(&ledger);
    }
    ledger
}
