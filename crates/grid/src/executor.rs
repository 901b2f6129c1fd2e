//! The tile executor: integrates a list of cells (a tile's unmarked cells, or the next cells of
//! the embedded frontier) on the current rayon pool and turns each orbit into an [`Outcome`].
//! Tangent-map methods run [`lanes`] orbits at a time in the batched stepper; adaptive methods
//! one orbit per task. An outcome depends only on its cell, never on scheduling, so any
//! partition of the work gives the same bits.

use crate::geometry::Grid;
use crate::ledger::{Ledger, Mode, Outcome};
use rayon::prelude::*;
use salient_core::batch::{integrate_feed, BatchFeed, Feed, Isa};
use salient_core::method::Method;
use salient_core::orbit::{
    sample_steps, steps_to, Class, OrbitConfig, OrbitResult, Requests, Status,
};
use salient_core::run::{run_orbit, MethodRun};
use salient_core::section::on_section;
use salient_core::section::Crossing;
use salient_core::{HenonHeiles, TangentMap};
use std::sync::atomic::{AtomicBool, AtomicU32, AtomicU64, AtomicUsize, Ordering};
use std::sync::Mutex;

/// Orbits advanced together in one batched stepper on the pinned target level, and the unit
/// in which schedulers size their batches (see [`lanes`] for what runs).
pub const LANES: usize = 4;

/// Below this step, fast PSS also takes the host's lane count.
const WIDE_FAST_PSS_BELOW_TAU: f64 = 0.02;

/// Orbits advanced together in one batched stepper in `mode` at step `tau`. Full mode takes
/// what suits the host ([`Isa::lanes`]: 8 with AVX-512). In fast PSS the lanes in flight bound
/// the speculation: 8 lanes step faster (3.8 instead of 6.7 ns per orbit-step) but drop
/// 35–50 % more steps, which pays only where the steps outweigh the per-crossing work, i.e.
/// at small τ. 400×400, t = 1e4, 2 threads, 4 against 8 lanes (2026-11-24, AVX-512 host):
/// τ = 0.01 4.27 vs 3.6–3.8 s, 0.02 2.29 vs 2.33 s, 0.05 1.06 vs 1.08 s, 0.1 0.67 vs 0.78 s,
/// 0.5 0.32 vs 0.44 s.
pub fn lanes(mode: Mode, tau: f64) -> usize {
    match mode {
        Mode::FastPss if tau >= WIDE_FAST_PSS_BELOW_TAU => LANES,
        _ => Isa::detect().lanes(),
    }
}

/// Runs the batched driver with [`lanes`] lanes.
fn drive(
    map: &TangentMap<'_, HenonHeiles>,
    config: &OrbitConfig,
    requests: &Requests,
    mode: Mode,
    feed: &mut impl BatchFeed<2>,
) {
    match lanes(mode, map.tau()) {
        8 => integrate_feed::<_, 2, 2, 8>(map, config, requests, feed),
        _ => integrate_feed::<_, 2, 2, LANES>(map, config, requests, feed),
    }
}

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
    /// Per cell, the lowest canonical position of a running orbit that crossed it: if that
    /// orbit commits, the cell is labelled by it, so integrating the cell now is probably
    /// wasted (a hint for choosing work, never a reason to abandon an orbit).
    crossed_by: Vec<AtomicU32>,
    /// Per cell, whether its orbit is running in some lane.
    running: Vec<AtomicBool>,
    /// Bumped whenever an orbit stops running (finished or abandoned): only then can a cell
    /// that a search for work skipped become available, so an idle lane searches again only
    /// after a bump.
    stopped: AtomicU64,
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
            crossed_by: (0..grid.cells())
                .map(|_| AtomicU32::new(u32::MAX))
                .collect(),
            running: (0..grid.cells()).map(|_| AtomicBool::new(false)).collect(),
            stopped: AtomicU64::new(0),
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

    /// The running orbit of cell `from` crossed `cell`.
    /// Returns false when this orbit had already noted the cell. Read before writing: a regular
    /// orbit crosses the same few dozen cells a thousand times, and a read-modify-write on a
    /// cache line the other threads read costs more than the rest of the bookkeeping.
    fn note_crossed(&self, from: u32, cell: u32) -> bool {
        let pos = self.position[from as usize];
        let by = &self.crossed_by[cell as usize];
        let seen = by.load(Ordering::Relaxed);
        if seen > pos {
            by.fetch_min(pos, Ordering::Relaxed);
        }
        seen != pos
    }

    /// Marks a cell as certain to be labelled (read first, for the reason given at
    /// [`Claims::note_crossed`]).
    fn claim_crossed(&self, cell: u32) {
        let c = &self.claimed[cell as usize];
        if !c.load(Ordering::Relaxed) {
            c.store(true, Ordering::Relaxed);
        }
    }

    /// The cell of the earliest orbit seen crossing `cell` while running, if it lies before the
    /// cell in canonical order and still runs.
    fn running_crosser(&self, grid: &Grid, cell: u32) -> Option<u32> {
        let by = self.crossed_by[cell as usize].load(Ordering::Relaxed);
        if by >= self.position[cell as usize] {
            return None;
        }
        let from = grid.canonical()[by as usize];
        self.is_running(from).then_some(from)
    }

    /// Whether the orbit of `cell` is probably wasted: a running orbit before it crossed it,
    /// and that orbit is itself neither claimed nor crossed by an earlier running one, so it
    /// will very likely commit and label the cell. (If it does not, the cell is integrated
    /// again later: abandoning costs the steps done so far, running on costs the rest.)
    fn probably_labelled(&self, grid: &Grid, cell: u32) -> bool {
        self.running_crosser(grid, cell).is_some_and(|from| {
            !self.claimed[from as usize].load(Ordering::Relaxed)
                && self.running_crosser(grid, from).is_none()
        })
    }

    /// Whether the cell's orbit runs in some lane.
    fn is_running(&self, cell: u32) -> bool {
        self.running[cell as usize].load(Ordering::Relaxed)
    }

    fn set_running(&self, cell: u32, running: bool) {
        self.running[cell as usize].store(running, Ordering::Relaxed);
        if !running {
            // Release, paired with the Acquire in `LedgerFeed::next`: a driver that sees the
            // new count also sees the cell stopped (`abandoned` stores without the lock).
            self.stopped.fetch_add(1, Ordering::Release);
        }
    }

    fn record_abandoned(&self, steps: u64) {
        self.abandoned.fetch_add(1, Ordering::Relaxed);
        self.abandoned_steps.fetch_add(steps, Ordering::Relaxed);
    }

    /// Orbits abandoned and the steps they had taken.
    pub fn abandoned(&self) -> (u64, u64) {
        (
            self.abandoned.load(Ordering::Relaxed),
            self.abandoned_steps.load(Ordering::Relaxed),
        )
    }
}

/// The feed of a fixed list of cells shared by several batched drivers: each free lane takes
/// the next cell of the list, so lanes stay full until the list runs out.
struct CellsFeed<'a> {
    grid: &'a Grid,
    cell_run: &'a CellRun,
    checkpoints: &'a [u64],
    cells: &'a [u32],
    cursor: &'a AtomicUsize,
    claims: Option<&'a Claims>,
    /// (position in `cells`, outcome) of the orbits this driver finished.
    done: Vec<(usize, Outcome)>,
}

impl BatchFeed<2> for CellsFeed<'_> {
    fn next(&mut self, _all_idle: bool) -> Feed<2> {
        loop {
            let i = self.cursor.fetch_add(1, Ordering::Relaxed);
            let Some(&cell) = self.cells.get(i) else {
                return Feed::Done;
            };
            if let Some(claims) = self.claims {
                // Certain or probable to be labelled by another orbit: left without an outcome,
                // so the ledger's owner integrates it later if it still needs it.
                if claims.is_claimed(cell) || claims.running_crosser(self.grid, cell).is_some() {
                    continue;
                }
                claims.set_running(cell, true);
            }
            let (q, p) = initial_point(self.grid, cell);
            return Feed::Orbit(i, q, p);
        }
    }
    fn finished(&mut self, i: usize, r: OrbitResult<2>) {
        if let Some(claims) = self.claims {
            claims.set_running(self.cells[i], false);
        }
        let o = outcome(
            self.grid,
            self.cell_run,
            self.checkpoints,
            self.cells[i],
            &r,
        );
        self.done.push((i, o));
    }
    fn on_crossing(&mut self, i: usize, c: &Crossing<2>) {
        let (Some(claims), Some(to)) = (self.claims, self.grid.cell_of(c.q[1], c.p[1])) else {
            return;
        };
        let from = self.cells[i];
        if claims.is_frontier(from) {
            claims.claim_crossed(to);
        }
        claims.note_crossed(from, to);
    }
    fn cancelled(&mut self, i: usize) -> bool {
        self.claims.is_some_and(|c| {
            c.is_claimed(self.cells[i]) || c.probably_labelled(self.grid, self.cells[i])
        })
    }
    fn abandoned(&mut self, i: usize, steps: u64) {
        if let Some(claims) = self.claims {
            claims.set_running(self.cells[i], false);
            claims.record_abandoned(steps);
        }
    }
}

fn initial_point(grid: &Grid, cell: u32) -> ([f64; 2], [f64; 2]) {
    let (q2, p2) = grid.centre(cell);
    on_section(&HenonHeiles, grid.energy, &[q2], &[p2])
        .expect("compatible cells lie on the section")
}

/// Integrates `cells` (compatible cells of `grid`) and returns their outcomes in the same order.
pub fn integrate_cells(grid: &Grid, cell_run: &CellRun, mode: Mode, cells: &[u32]) -> Vec<Outcome> {
    integrate_cells_with(grid, cell_run, mode, cells, None)
}

fn requests_for(cell_run: &CellRun, mode: Mode) -> Requests {
    Requests {
        crossings: mode == Mode::FastPss,
        samples_per_decade: cell_run.checkpoints_per_decade,
        ..Requests::default()
    }
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
    let requests = requests_for(cell_run, mode);
    let checkpoints = cell_run.checkpoint_steps();
    match &cell_run.run.method {
        Method::TangentMap(scheme) => {
            let map = TangentMap::new(&ham, scheme, cell_run.config.tau);
            let cursor = AtomicUsize::new(0);
            let drivers = rayon::current_num_threads()
                .min(cells.len().div_ceil(lanes(mode, cell_run.config.tau)));
            let finished: Vec<(usize, Outcome)> = (0..drivers)
                .into_par_iter()
                .flat_map_iter(|_| {
                    let mut feed = CellsFeed {
                        grid,
                        cell_run,
                        checkpoints: &checkpoints,
                        cells,
                        cursor: &cursor,
                        claims,
                        done: Vec::new(),
                    };
                    drive(&map, &cell_run.config, &requests, mode, &mut feed);
                    feed.done
                })
                .collect();
            let mut out: Vec<Option<Outcome>> = vec![None; cells.len()];
            for (i, o) in finished {
                out[i] = Some(o);
            }
            // Abandoned orbits report nothing.
            out.into_iter().flatten().collect()
        }
        _ => cells
            .par_iter()
            .map(|&cell| {
                let (q, p) = initial_point(grid, cell);
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

/// What the embedded fast-PSS engine shares between its drivers.
struct Shared<P> {
    ledger: Ledger,
    progress: P,
}

/// The embedded engine's feed: a free lane takes the next cell the ledger needs (skipping
/// cells in flight or certain to be labelled), and a finished orbit goes to the ledger at once.
struct LedgerFeed<'a, P> {
    grid: &'a Grid,
    cell_run: &'a CellRun,
    checkpoints: &'a [u64],
    claims: &'a Claims,
    shared: &'a Mutex<Shared<P>>,
    /// The cells each of this driver's running orbits has crossed while not the frontier
    /// orbit: claimed as soon as it becomes the frontier (None after that: it claims directly).
    crossed: Vec<Crossed>,
    /// [`Claims::stopped`] when a search for work last found none. A fruitless search walks
    /// the whole rest of the grid (a quarter of a millisecond at 400×400), and idle lanes ask
    /// at every poll: without this, 8-lane drivers spent 44 % of a τ = 0.01 run searching.
    dry_since: Option<u64>,
}

/// What one running orbit of a [`LedgerFeed`] has crossed.
struct Crossed {
    cell: u32,
    /// Cells crossed while not the frontier orbit (None once it is).
    cells: Option<Vec<u32>>,
    /// Cells already handled, direct-mapped: a regular orbit crosses the same few dozen
    /// cells a thousand times, and each skipped repeat saves reads of shared arrays.
    recent: [u32; 64],
}

impl<P> LedgerFeed<'_, P> {
    fn forget(&mut self, cell: u32) {
        self.crossed.retain(|c| c.cell != cell);
    }
}

impl<P: FnMut(&Ledger)> BatchFeed<2> for LedgerFeed<'_, P> {
    fn next(&mut self, all_idle: bool) -> Feed<2> {
        let stopped = self.claims.stopped.load(Ordering::Acquire);
        let cell = if self.dry_since == Some(stopped) {
            None
        } else {
            let g = self.shared.lock().expect("ledger lock");
            let ledger = &g.ledger;
            if ledger.done() {
                return Feed::Done;
            }
            let (claims, grid) = (self.claims, self.grid);
            // A cell crossed by an earlier running orbit or an earlier pending outcome will be
            // labelled by it unless that orbit is dropped: take other cells first. The frontier
            // cell is never skipped (nothing before it runs), so this cannot stall.
            let cell = ledger
                .needed(1, &|c| {
                    claims.is_running(c)
                        || claims.is_claimed(c)
                        || ledger.is_claimed(c)
                        || claims.running_crosser(grid, c).is_some()
                })
                .first()
                .copied();
            if let Some(c) = cell {
                // Under the lock, so no other lane takes the cell too.
                claims.set_running(c, true);
            }
            self.dry_since = cell.is_none().then_some(stopped);
            cell
        };
        if let Some(c) = cell {
            self.crossed.push(Crossed {
                cell: c,
                cells: Some(Vec::new()),
                recent: [u32::MAX; 64],
            });
        }
        match cell {
            Some(c) => {
                let (q, p) = initial_point(self.grid, c);
                Feed::Orbit(c as usize, q, p)
            }
            None => {
                if all_idle {
                    // Everything still needed is in flight elsewhere.
                    std::thread::sleep(std::time::Duration::from_micros(50));
                }
                Feed::Wait
            }
        }
    }
    fn finished(&mut self, cell: usize, r: OrbitResult<2>) {
        let cell = cell as u32;
        self.forget(cell);
        let o = outcome(self.grid, self.cell_run, self.checkpoints, cell, &r);
        let mut g = self.shared.lock().expect("ledger lock");
        let Shared { ledger, progress } = &mut *g;
        ledger.offer(o);
        // Under the lock: the cell is either running or has its outcome in the ledger.
        self.claims.set_running(cell, false);
        self.claims.sync(ledger);
        progress(ledger);
    }
    fn on_crossing(&mut self, cell: usize, c: &Crossing<2>) {
        let from = cell as u32;
        let Some(to) = self.grid.cell_of(c.q[1], c.p[1]) else {
            return;
        };
        let claims = self.claims;
        let Some(orbit) = self.crossed.iter_mut().find(|c| c.cell == from) else {
            return;
        };
        let frontier = claims.is_frontier(from);
        let slot = &mut orbit.recent[to as usize % 64];
        // A repeat needs nothing, unless the orbit has just become the frontier and has its
        // earlier crossings to claim.
        if *slot == to && (orbit.cells.is_none() || !frontier) {
            return;
        }
        *slot = to;
        if frontier {
            for v in orbit.cells.take().into_iter().flatten().chain([to]) {
                claims.claim_crossed(v);
            }
        } else if let Some(list) = &mut orbit.cells {
            if claims.note_crossed(from, to) && !list.contains(&to) {
                list.push(to);
            }
        }
    }
    fn cancelled(&mut self, cell: usize) -> bool {
        self.claims.is_claimed(cell as u32) || self.claims.probably_labelled(self.grid, cell as u32)
    }
    fn abandoned(&mut self, cell: usize, steps: u64) {
        self.forget(cell as u32);
        self.claims.set_running(cell as u32, false);
        self.claims.record_abandoned(steps);
    }
}

/// Runs a whole grid in this process on the current rayon pool and returns the finished
/// ledger. Fast PSS with a tangent-map method streams: every thread runs a batched stepper
/// whose free lanes take the next cell the ledger needs (skipping cells in flight or certain
/// to be labelled) and offer each outcome the moment its orbit ends; orbits whose cell the
/// frontier orbit crosses are abandoned. Speculation is bounded by the lanes in flight.
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
    let streaming = mode == Mode::FastPss
        && cell_run.checkpoints_per_decade == 0
        && matches!(cell_run.run.method, Method::TangentMap(_));
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
    let shared = Mutex::new(Shared {
        ledger: Ledger::new(grid, mode),
        progress,
    });
    let Method::TangentMap(scheme) = &cell_run.run.method else {
        unreachable!("streaming runs tangent-map methods")
    };
    let ham = HenonHeiles;
    let map = TangentMap::new(&ham, scheme, cell_run.config.tau);
    let requests = requests_for(cell_run, mode);
    let checkpoints = cell_run.checkpoint_steps();
    rayon::broadcast(|_| {
        let mut feed = LedgerFeed {
            grid,
            cell_run,
            checkpoints: &checkpoints,
            claims: &claims,
            shared: &shared,
            crossed: Vec::new(),
            dry_since: None,
        };
        drive(&map, &cell_run.config, &requests, mode, &mut feed);
    });
    let Shared { mut ledger, .. } = shared.into_inner().expect("ledger lock");
    let (n, steps) = claims.abandoned();
    ledger.record_abandoned(n, steps);
    ledger
}
