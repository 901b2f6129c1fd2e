//! A fixed list of cells integrated on the current rayon pool ([`integrate_cells`]).

use super::crossed_cells;
use super::{drive_feed, initial_point, lanes, outcome, requests_for, CellRun};
use crate::geometry::Grid;
use crate::ledger::{Mode, Outcome};
use rayon::prelude::*;
use salient_core::orbit::OrbitResult;
use salient_core::run::adaptive_orbits_per_thread;
use salient_core::section::CellLattice;
use salient_core::tangent_map::batch::{BatchFeed, Feed};
use std::collections::HashSet;
use std::sync::atomic::{AtomicUsize, Ordering};

/// The feed of a fixed list of cells shared by several batched drivers: each free lane takes
/// the next cell of the list, so lanes stay full until the list runs out.
struct CellsFeed<'a> {
    grid: &'a Grid,
    cell_run: &'a CellRun,
    checkpoints: &'a [u64],
    cells: &'a [u32],
    cursor: &'a AtomicUsize,
    /// Whether each orbit's crossings are kept (see [`OrbitTrace`]).
    trace: bool,
    /// (position in `cells`, trace) of the orbits this driver finished.
    done: Vec<(usize, OrbitTrace)>,
}

/// An orbit's outcome and, when traced, when it first crossed each compatible cell: what a
/// stream's claims learn from it while it runs (the scaling simulator replays it in virtual
/// time).
#[derive(Clone, Debug)]
pub struct OrbitTrace {
    /// The orbit's outcome.
    pub outcome: Outcome,
    /// (cell, step of its first crossing), in crossing order; empty unless traced.
    pub crossings: Vec<(u32, u64)>,
}

impl<const N: usize> BatchFeed<N> for CellsFeed<'_> {
    fn next(&mut self, _all_idle: bool) -> Feed<N> {
        let i = self.cursor.fetch_add(1, Ordering::Relaxed);
        match self.cells.get(i) {
            Some(&cell) => {
                let (q, p) = initial_point(self.grid, cell);
                Feed::Orbit(i, q, p)
            }
            None => Feed::Done,
        }
    }
    fn finished(&mut self, i: usize, r: OrbitResult<N>) {
        let visited = crossed_cells(self.grid, &r.crossings);
        let crossings = if self.trace {
            first_crossings(self.grid, &r)
        } else {
            Vec::new()
        };
        let outcome = outcome(self.cell_run, self.checkpoints, self.cells[i], &r, visited);
        self.done.push((i, OrbitTrace { outcome, crossings }));
    }
    fn books_by_cell(&self) -> Option<CellLattice> {
        Some(self.grid.lattice())
    }
}

/// The compatible cells an orbit crossed, each at its first crossing, with the step it came
/// at (steps are uniform in time for tangent maps; for adaptive methods, time's share of the
/// steps).
fn first_crossings<const N: usize>(grid: &Grid, r: &OrbitResult<N>) -> Vec<(u32, u64)> {
    let per_time = if r.t_reached > 0.0 {
        r.steps as f64 / r.t_reached
    } else {
        0.0
    };
    let mut seen = HashSet::new();
    r.crossings
        .iter()
        .filter_map(|c| Some((grid.cell_of(c.q[1], c.p[1])?, c.t)))
        .filter(|&(cell, _)| grid.is_compatible(cell) && seen.insert(cell))
        .map(|(cell, t)| (cell, ((t * per_time).round() as u64).min(r.steps)))
        .collect()
}

/// Integrates `cells` (compatible cells of `grid`) and returns their outcomes in the same order.
pub fn integrate_cells(grid: &Grid, cell_run: &CellRun, mode: Mode, cells: &[u32]) -> Vec<Outcome> {
    integrate_listed(grid, cell_run, mode, cells, false)
        .into_iter()
        .map(|t| t.outcome)
        .collect()
}

/// [`integrate_cells`] with each orbit's first crossings of the cells (in fast PSS: full mode
/// records no crossings).
pub fn trace_cells(grid: &Grid, cell_run: &CellRun, mode: Mode, cells: &[u32]) -> Vec<OrbitTrace> {
    integrate_listed(grid, cell_run, mode, cells, true)
}

fn integrate_listed(
    grid: &Grid,
    cell_run: &CellRun,
    mode: Mode,
    cells: &[u32],
    trace: bool,
) -> Vec<OrbitTrace> {
    let requests = requests_for(cell_run, mode);
    let checkpoints = cell_run.checkpoint_steps();
    // A batched driver fills `lanes` orbits at a time; an adaptive one runs one or a few.
    let c = &cell_run.config;
    let per_driver = if cell_run.run.method.is_adaptive() {
        adaptive_orbits_per_thread(&cell_run.run.method, c.tau, c.t_final)
    } else {
        lanes(mode)
    };
    let cursor = AtomicUsize::new(0);
    let drivers = rayon::current_num_threads().min(cells.len().div_ceil(per_driver));
    let finished: Vec<(usize, OrbitTrace)> = (0..drivers)
        .into_par_iter()
        .flat_map_iter(|_| {
            let mut feed = CellsFeed {
                grid,
                cell_run,
                checkpoints: &checkpoints,
                cells,
                cursor: &cursor,
                trace,
                done: Vec::new(),
            };
            drive_feed(grid, cell_run, mode, &requests, false, &mut feed);
            feed.done
        })
        .collect();
    let mut out: Vec<Option<OrbitTrace>> = vec![None; cells.len()];
    for (i, o) in finished {
        out[i] = Some(o);
    }
    out.into_iter()
        .map(|o| o.expect("every listed cell is integrated"))
        .collect()
}
