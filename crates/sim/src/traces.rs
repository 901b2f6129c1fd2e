//! Orbits as the simulation replays them: every orbit a simulated worker starts is integrated
//! for real once (its outcome, and when it first crossed each cell) and replayed in virtual
//! time from then on, by every simulated worker and every worker count.

use salient_core::engine::thread_cpu_ns;
use salient_grid::executor::{
    integrate_stream, trace_cells, CellSource, LocalLedger, OrbitTrace, Take, Verdict,
};
use salient_grid::{CellRun, Grid, Mode};
use std::collections::VecDeque;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};

/// The traced orbits of one run, integrated as the simulation first needs them.
pub struct Traces {
    grid: Grid,
    cell_run: CellRun,
    mode: Mode,
    orbits: Vec<Option<Arc<OrbitTrace>>>,
    /// Orbits integrated for real so far.
    pub integrated: usize,
}

impl Traces {
    pub fn new(grid: &Grid, cell_run: CellRun, mode: Mode) -> Self {
        Traces {
            orbits: vec![None; grid.cells()],
            grid: grid.clone(),
            cell_run,
            mode,
            integrated: 0,
        }
    }

    /// Integrates those of `cells` not traced yet, together (all the lanes of every thread).
    pub fn ensure(&mut self, cells: &[u32]) {
        let mut missing: Vec<u32> = cells
            .iter()
            .copied()
            .filter(|&c| self.orbits[c as usize].is_none())
            .collect();
        missing.sort_unstable();
        missing.dedup();
        if missing.is_empty() {
            return;
        }
        for t in trace_cells(&self.grid, &self.cell_run, self.mode, &missing) {
            let cell = t.outcome.cell as usize;
            self.orbits[cell] = Some(Arc::new(t));
        }
        self.integrated += missing.len();
    }

    /// The trace of `cell`, integrated now if it was not.
    pub fn get(&mut self, cell: u32) -> Arc<OrbitTrace> {
        if self.orbits[cell as usize].is_none() {
            self.ensure(&[cell]);
        }
        self.orbits[cell as usize].clone().expect("traced")
    }
}

/// Orbit-steps integrated to calibrate the cost of a step, over all passes: enough for a
/// stable figure, a few tenths of a second.
const CALIBRATION_STEPS: u64 = 20_000_000;

/// Passes over the calibration's orbits, each timed alone: the figure is their median, so that
/// a pass slowed by something else on the host (a neighbour on the core's caches, a frequency
/// change, time stolen from a virtual machine) does not set it.
const CALIBRATION_PASSES: u64 = 5;

/// Orbits of the calibration, spread evenly over the grid's compatible cells (regular and
/// chaotic ones cost differently per step: crossings, early stops).
const CALIBRATION_ORBITS: usize = 64;

/// Hands out a fixed list of cells, each once, whatever the claims say (every cell is integrated,
/// so the figure covers whole orbits), and counts the steps integrated.
struct ListSource {
    cells: Mutex<VecDeque<u32>>,
    steps: AtomicU64,
}

impl CellSource for ListSource {
    fn take(&self, _all_idle: bool, _judge: &dyn Fn(u32) -> Verdict) -> Take {
        match self.cells.lock().expect("cells").pop_front() {
            Some(c) => Take::Cell(c as u64),
            None => Take::Done,
        }
    }
    fn ended(&self, _entry: u64, _outcome: Option<salient_grid::Outcome>, steps: u64) {
        self.steps.fetch_add(steps, Ordering::Relaxed);
    }
}

/// The CPU cost of one step of one orbit in a worker thread's full lanes, in nanoseconds:
/// `lanes` × that is the time a lane takes per step. Measured on one thread of the worker's
/// own stream engine (claims, crossings, a local ledger), over orbits spread across the grid,
/// each for at most the run's t_final.
pub fn calibrate_step_ns(grid: &Grid, cell_run: &CellRun, mode: Mode) -> f64 {
    let canonical = grid.canonical();
    let stride = (canonical.len() / CALIBRATION_ORBITS).max(1);
    let cells: VecDeque<u32> = canonical.iter().copied().step_by(stride).collect();
    let mut run = cell_run.clone();
    let per_orbit = (CALIBRATION_STEPS / CALIBRATION_PASSES / cells.len().max(1) as u64).max(1000);
    run.config.t_final = run.config.t_final.min(per_orbit as f64 * run.config.tau);
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(1)
        .build()
        .expect("a one-thread pool");
    let mut passes: Vec<f64> = (0..CALIBRATION_PASSES)
        .map(|_| {
            let source = ListSource {
                cells: Mutex::new(cells.clone()),
                steps: AtomicU64::new(0),
            };
            let local = LocalLedger::new(grid, mode);
            let cpu_ns = pool.install(|| {
                let start = thread_cpu_ns();
                integrate_stream(grid, &run, mode, &local, &source);
                thread_cpu_ns() - start
            });
            cpu_ns as f64 / source.steps.load(Ordering::Relaxed).max(1) as f64
        })
        .collect();
    passes.sort_by(f64::total_cmp);
    passes[passes.len() / 2]
}
