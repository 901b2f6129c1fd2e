//! The tile executor: integrates a list of cells (a tile's unmarked cells, or the next cells of
//! the embedded frontier) on the current rayon pool and turns each orbit into an [`Outcome`].
//! Tangent-map methods run `LANES` orbits at a time in the batched stepper; adaptive methods
//! one orbit per task. An outcome depends only on its cell, never on scheduling, so any
//! partition of the work gives the same bits.

use crate::geometry::Grid;
use crate::ledger::{Ledger, Mode, Outcome};
use rayon::prelude::*;
use salient_core::batch::{integrate_batch, integrate_batch_with, BatchHooks};
use salient_core::method::Method;
use salient_core::orbit::{
    sample_steps, steps_to, Class, OrbitConfig, OrbitResult, Requests, Status,
};
use salient_core::run::{run_orbit, MethodRun};
use salient_core::section::on_section;
use salient_core::section::Crossing;
use salient_core::{HenonHeiles, TangentMap};
use std::collections::HashSet;
use std::sync::atomic::{AtomicBool, AtomicU64, AtomicUsize, Ordering};
use std::sync::Mutex;

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
        t_end: r.t_reached,
        checkpoints: classes,
    }
}

/// What the fast-PSS engine knows for certain while orbits run: cells already labelled, and
/// cells crossed by the frontier orbit — the first cell the ledger still needs, whose orbit is
/// certain to commit, so every cell it crosses is certain to be labelled by it. Orbits started
/// from such cells are abandoned at once instead of being integrated to the end and dropped.
pub struct Claims {
    frontier: AtomicUsize,
    position: Vec<u32>,
    claimed: Vec<AtomicBool>,
    abandoned: AtomicU64,
    abandoned_steps: AtomicU64,
}

impl Claims {
    pub fn new(grid: &Grid) -> Self {
        Claims {
            frontier: AtomicUsize::new(0),
            position: (0..grid.cells() as u32)
                .map(|c| grid.position(c).map_or(u32::MAX, |p| p as u32))
                .collect(),
            claimed: (0..grid.cells()).map(|_| AtomicBool::new(false)).collect(),
            abandoned: AtomicU64::new(0),
            abandoned_steps: AtomicU64::new(0),
        }
    }

    /// Claims with no frontier orbit: cells are claimed only through [`Claims::claim`] (a
    /// worker learning from its coordinator that a cell no longer needs an orbit).
    pub fn external(grid: &Grid) -> Self {
        let c = Claims::new(grid);
        c.frontier.store(usize::MAX, Ordering::Relaxed);
        c
    }

    /// Marks a cell as labelled by another orbit: its orbit, if running, is abandoned.
    pub fn claim(&self, cell: u32) {
        if let Some(c) = self.claimed.get(cell as usize) {
            c.store(true, Ordering::Relaxed);
        }
    }

    /// Withdraws a claim: the cell needs its orbit after all (its claimer was dropped).
    pub fn unclaim(&self, cell: u32) {
        if let Some(c) = self.claimed.get(cell as usize) {
            c.store(false, Ordering::Relaxed);
        }
    }

    /// Brings the claims up to date with the ledger (call with the ledger locked).
    pub fn sync(&self, ledger: &mut Ledger) {
        for c in ledger.take_newly_labelled() {
            self.claimed[c as usize].store(true, Ordering::Relaxed);
        }
        self.frontier.store(ledger.frontier(), Ordering::Relaxed);
    }

    fn is_frontier(&self, cell: u32) -> bool {
        self.position[cell as usize] as usize == self.frontier.load(Ordering::Relaxed)
    }

    /// Whether the cell is certain to be labelled by another orbit.
    pub fn is_claimed(&self, cell: u32) -> bool {
        self.claimed[cell as usize].load(Ordering::Relaxed) && !self.is_frontier(cell)
    }

    /// Orbits abandoned and the steps they had taken.
    pub fn abandoned(&self) -> (u64, u64) {
        (
            self.abandoned.load(Ordering::Relaxed),
            self.abandoned_steps.load(Ordering::Relaxed),
        )
    }
}

struct ChunkHooks<'a> {
    grid: &'a Grid,
    chunk: &'a [u32],
    claims: &'a Claims,
}

impl BatchHooks<2> for ChunkHooks<'_> {
    fn on_crossing(&self, ic: usize, c: &Crossing<2>) {
        if self.claims.is_frontier(self.chunk[ic]) {
            if let Some(cell) = self.grid.cell_of(c.q[1], c.p[1]) {
                self.claims.claimed[cell as usize].store(true, Ordering::Relaxed);
            }
        }
    }
    fn cancelled(&self, ic: usize) -> bool {
        self.claims.is_claimed(self.chunk[ic])
    }
    fn abandoned(&self, _ic: usize, steps: u64) {
        self.claims.abandoned.fetch_add(1, Ordering::Relaxed);
        self.claims
            .abandoned_steps
            .fetch_add(steps, Ordering::Relaxed);
    }
}

/// Integrates `cells` (compatible cells of `grid`) and returns their outcomes in the same order.
pub fn integrate_cells(grid: &Grid, cell_run: &CellRun, mode: Mode, cells: &[u32]) -> Vec<Outcome> {
    integrate_cells_with(grid, cell_run, mode, cells, None)
}

/// [`integrate_cells`], abandoning orbits the frontier orbit claims; abandoned cells get no
/// outcome.
pub fn integrate_cells_with(
    grid: &Grid,
    cell_run: &CellRun,
    mode: Mode,
    cells: &[u32],
    claims: Option<&Claims>,
) -> Vec<Outcome> {
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
                    let sink = |i: usize, r: OrbitResult<2>| {
                        out[i] = Some(outcome(grid, cell_run, &checkpoints, chunk[i], &r));
                    };
                    let config = &cell_run.config;
                    match claims {
                        Some(claims) => {
                            let hooks = ChunkHooks {
                                grid,
                                chunk,
                                claims,
                            };
                            integrate_batch_with::<_, 2, 2, LANES>(
                                &map, &ics, config, &requests, &hooks, sink,
                            )
                        }
                        None => {
                            integrate_batch::<_, 2, 2, LANES>(&map, &ics, config, &requests, sink)
                        }
                    }
                    // Abandoned orbits report nothing.
                    out.into_iter().flatten()
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

/// Runs a whole grid in this process on the current rayon pool and returns the finished
/// ledger. Fast PSS with a tangent-map method streams: every worker repeatedly takes the next
/// `LANES` cells the ledger needs (skipping cells in flight or certain to be labelled),
/// integrates them in the batched stepper, where orbits whose cell the frontier orbit crosses
/// are abandoned, and offers the outcomes; speculation is bounded by one batch per worker.
/// Other runs go in rounds of `window` cells: adaptive methods cannot abandon orbits, and
/// streaming them measured slower (more dropped work) than rounds. Either way the labels are
/// those of the sequential rule.
pub fn run_embedded(
    grid: &Grid,
    cell_run: &CellRun,
    mode: Mode,
    window: usize,
    mut progress: impl FnMut(&Ledger) + Send,
) -> Ledger {
    let streaming = mode == Mode::FastPss && matches!(cell_run.run.method, Method::TangentMap(_));
    if !streaming {
        let mut ledger = Ledger::new(grid, mode);
        while !ledger.done() {
            let cells = ledger.needed(window.max(1), &|_| false);
            for o in integrate_cells(grid, cell_run, mode, &cells) {
                ledger.offer(o);
            }
            progress(&ledger);
        }
        return ledger;
    }
    let claims = Claims::new(grid);
    let shared = Mutex::new((Ledger::new(grid, mode), HashSet::<u32>::new(), progress));
    let workers = rayon::current_num_threads();
    rayon::scope(|s| {
        for _ in 0..workers {
            s.spawn(|_| loop {
                let cells = {
                    let mut g = shared.lock().expect("ledger lock");
                    let (ledger, in_flight, _) = &mut *g;
                    if ledger.done() {
                        break;
                    }
                    let cells =
                        ledger.needed(LANES, &|c| in_flight.contains(&c) || claims.is_claimed(c));
                    in_flight.extend(&cells);
                    cells
                };
                if cells.is_empty() {
                    // Everything still needed is in flight elsewhere.
                    std::thread::sleep(std::time::Duration::from_micros(50));
                    continue;
                }
                let outcomes = integrate_cells_with(grid, cell_run, mode, &cells, Some(&claims));
                let mut g = shared.lock().expect("ledger lock");
                let (ledger, in_flight, progress) = &mut *g;
                for o in outcomes {
                    ledger.offer(o);
                }
                for c in &cells {
                    in_flight.remove(c);
                }
                claims.sync(ledger);
                progress(ledger);
            });
        }
    });
    let (mut ledger, _, _) = shared.into_inner().expect("ledger lock");
    let (n, steps) = claims.abandoned();
    ledger.record_abandoned(n, steps);
    ledger
}
