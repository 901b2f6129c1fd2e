//! The embedded fast-PSS engine ([`run_embedded`]): every thread's lanes take the next cell the
//! one ledger needs, and each outcome goes to it as its orbit ends.

use super::initial_point;
use super::{drive_plane, integrate_cells, outcome, requests_for, CellRun, Claims};
use crate::geometry::Grid;
use crate::ledger::{Forecast, Ledger, Mode, Outcome};
use salient_core::orbit::OrbitResult;
use salient_core::run::adaptive_orbits_per_thread;
use salient_core::section::{CellLattice, Crossing};
use salient_core::tangent_map::batch::{BatchFeed, Feed};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Mutex, MutexGuard, TryLockError};

/// What the embedded fast-PSS engine shares between its drivers.
struct Shared<'p> {
    ledger: Ledger,
    progress: &'p mut (dyn FnMut(&Ledger) + Send + 'p),
}

/// What every thread of the embedded fast-PSS engine works against.
struct Engine<'a, 'p> {
    grid: &'a Grid,
    cell_run: &'a CellRun,
    checkpoints: &'a [u64],
    claims: &'a Claims,
    shared: &'a Mutex<Shared<'p>>,
    /// Who labelled each cell in a similar run: cells forecast to be labelled by an orbit not
    /// yet committed are taken last.
    forecast: Option<&'a Forecast>,
    /// Set when a thread of the run panicked: its cell stays marked running, so the others
    /// would wait for it forever; they stop instead, and the panic surfaces.
    failed: AtomicBool,
    /// Attempts [`Engine::lock_ledger`] makes before it sleeps on the lock.
    spins: u32,
}

/// Marks the engine failed if the thread holding it unwinds.
struct FailOnPanic<'a>(&'a AtomicBool);

impl Drop for FailOnPanic<'_> {
    fn drop(&mut self) {
        if std::thread::panicking() {
            self.0.store(true, Ordering::Relaxed);
        }
    }
}

/// How many cells a [`Forecast`] defers [`Engine::take_needed`] passes over, looking for one
/// it does not, before it takes the first of them: bounded, so that a poor forecast holds
/// back few cells, while a good one does as well with it (figures: docs/performance.md).
const FORECAST_PATIENCE: usize = 256;

/// What a lane asking for work gets from [`Engine::take_needed`].
enum Needed {
    Cell(u32),
    NotNow,
    Done,
}

/// How many times a thread tries the ledger lock before it sleeps on it, when every thread
/// of the pool has a core. The lock is held for microseconds, while a thread put to sleep on
/// it waits far longer for its wake-up; spinning first saves most futex calls and context
/// switches (figures: docs/performance.md).
const LEDGER_SPINS: u32 = 20_000;

/// [`LEDGER_SPINS`] when the current pool has a core per thread, else 0: a thread spinning
/// while the holder waits for its core only delays it.
fn ledger_spins() -> u32 {
    let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
    if rayon::current_num_threads() <= cores {
        LEDGER_SPINS
    } else {
        0
    }
}

impl<'p> Engine<'_, 'p> {
    /// The ledger, locked: tried [`Engine::spins`] times before the thread sleeps on it.
    fn lock_ledger(&self) -> MutexGuard<'_, Shared<'p>> {
        for _ in 0..self.spins {
            match self.shared.try_lock() {
                Ok(g) => return g,
                Err(TryLockError::WouldBlock) => std::hint::spin_loop(),
                Err(TryLockError::Poisoned(_)) => break,
            }
        }
        self.shared.lock().expect("ledger lock")
    }
}

impl Engine<'_, '_> {
    /// The first cell the ledger needs that no lane runs and no other orbit is certain or
    /// likely to label, marked running. `dry_since` holds [`Claims::stopped`] as of the last
    /// fruitless search: a fruitless search walks the whole rest of the grid, and idle lanes
    /// ask at every poll, so repeated searches would take a large share of a run (figures:
    /// docs/performance.md); it is repeated only after an orbit stops.
    fn take_needed(&self, dry_since: &mut Option<u64>) -> Needed {
        if self.failed.load(Ordering::Relaxed) {
            return Needed::Done;
        }
        let stopped = self.claims.stopped.load(Ordering::Acquire);
        if *dry_since == Some(stopped) {
            return Needed::NotNow;
        }
        let g = self.lock_ledger();
        let ledger = &g.ledger;
        if ledger.done() {
            return Needed::Done;
        }
        let (claims, grid) = (self.claims, self.grid);
        // A cell crossed by an earlier running orbit or an earlier live pending outcome will be
        // labelled by it unless that orbit is dropped: take other cells first. The frontier
        // cell is never skipped (nothing before it runs), so this cannot stall.
        let busy = |c: u32| {
            claims.is_running(c)
                || claims.is_claimed(c)
                || ledger.is_claimed(c)
                || claims.running_crosser(grid, c).is_some()
        };
        // Cells a forecast says another orbit will label come last while that orbit may still
        // need its own run (`Forecast::defers`), but after FORECAST_PATIENCE of them the first
        // is taken: a poor forecast (another τ's labels, say) would otherwise send the lanes
        // ever further ahead of the frontier while the cells it needs wait.
        let defers = |c: u32| self.forecast.is_some_and(|f| f.defers(c, ledger));
        let (mut cell, mut fallback, mut deferred) = (None, None, 0);
        ledger.scan_needed(|c| {
            if defers(c) {
                if fallback.is_none() && !busy(c) {
                    fallback = Some(c);
                }
                deferred += 1;
                return deferred > FORECAST_PATIENCE && fallback.is_some();
            }
            if busy(c) {
                return false;
            }
            cell = Some(c);
            true
        });
        let cell = cell.or(fallback);
        *dry_since = cell.is_none().then_some(stopped);
        match cell {
            Some(c) => {
                // Under the lock, so no other lane takes the cell too.
                claims.set_running(c, true);
                Needed::Cell(c)
            }
            None => Needed::NotNow,
        }
    }

    /// The batched driver's answer to `next` for a [`Engine::take_needed`] result.
    fn feed(&self, needed: Needed, all_idle: bool) -> Feed<2> {
        match needed {
            Needed::Cell(c) => {
                let (q, p) = initial_point(self.grid, c);
                Feed::Orbit(c as usize, q, p)
            }
            Needed::NotNow => {
                if all_idle {
                    // Everything still needed is in flight elsewhere.
                    std::thread::sleep(std::time::Duration::from_micros(50));
                }
                Feed::Wait
            }
            Needed::Done => Feed::Done,
        }
    }

    /// Hands the finished orbit of `cell`, whose crossings fell in `visited`, to the ledger.
    fn commit(&self, cell: u32, r: &OrbitResult<2>, visited: Vec<u32>) {
        let o = outcome(self.cell_run, self.checkpoints, cell, r, visited);
        let mut g = self.lock_ledger();
        let Shared { ledger, progress } = &mut *g;
        ledger.offer(o);
        // Under the lock: the cell is either running or has its outcome in the ledger.
        self.claims.set_running(cell, false);
        self.claims.sync(ledger);
        progress(ledger);
    }

    fn cancelled(&self, cell: u32) -> bool {
        self.claims.is_claimed(cell) || self.claims.probably_labelled(self.grid, cell)
    }

    fn abandoned(&self, cell: u32, steps: u64) {
        self.claims.set_running(cell, false);
        self.claims.record_abandoned(steps);
    }
}

/// What one running orbit has crossed so far.
struct Crossed {
    cell: u32,
    /// Whether the cells it crossed are claimed: it is the frontier orbit, so every cell it
    /// crosses is certain to be labelled by it.
    claimed: bool,
    /// Every cell crossed, so that each is handled once: a regular orbit crosses the same few
    /// dozen cells a thousand times, and a repeat must not read the shared arrays.
    seen: CellSet,
    /// The compatible cells crossed, in crossing order, each once.
    visited: Vec<u32>,
}

/// The crossings of one thread's running orbits, turned into claims as they are located.
#[derive(Default)]
struct CrossingBook {
    orbits: Vec<Crossed>,
    /// Sets of orbits that stopped, emptied for the next ones.
    spare: Vec<CellSet>,
}

impl CrossingBook {
    /// The running orbit of `from` crossed `to`.
    fn crossed(&mut self, grid: &Grid, claims: &Claims, from: u32, to: u32) {
        let k = match self.orbits.iter().position(|c| c.cell == from) {
            Some(k) => k,
            None => {
                self.orbits.push(Crossed {
                    cell: from,
                    claimed: false,
                    seen: self.spare.pop().unwrap_or_default(),
                    visited: Vec::new(),
                });
                self.orbits.len() - 1
            }
        };
        let orbit = &mut self.orbits[k];
        let frontier = claims.is_frontier(from);
        let new = orbit.seen.insert(to);
        // A repeat needs nothing, unless the orbit has just become the frontier and has its
        // earlier crossings to claim.
        if !new && (orbit.claimed || !frontier) {
            return;
        }
        let compatible = grid.is_compatible(to);
        if new && compatible {
            orbit.visited.push(to);
        }
        if frontier {
            if !orbit.claimed {
                orbit.claimed = true;
                for &v in &orbit.visited {
                    claims.claim_crossed(v);
                }
            } else if compatible {
                claims.claim_crossed(to);
            }
        } else {
            claims.note_crossed(grid, from, to);
        }
    }

    /// Forgets the orbit of `cell` (it stopped) and returns the cells it crossed.
    fn take(&mut self, cell: u32) -> Vec<u32> {
        match self.orbits.iter().position(|c| c.cell == cell) {
            Some(k) => {
                let mut orbit = self.orbits.swap_remove(k);
                orbit.seen.clear();
                self.spare.push(orbit.seen);
                orbit.visited
            }
            None => Vec::new(),
        }
    }
}

/// A set of cells, open-addressed: after its first orbits a thread's sets have grown to what
/// its orbits need and allocate no more. A set rather than a small direct-mapped cache of
/// recent cells: a cache's misses send a crossing to the shared arrays again, a visible cost
/// once a cell keeps several crossers (figures: docs/performance.md).
#[derive(Default)]
struct CellSet {
    slots: Vec<u32>,
    len: usize,
    /// 64 − log2 of the capacity: the hash keeps the top bits of a multiplicative hash.
    shift: u32,
}

impl CellSet {
    const EMPTY: u32 = u32::MAX;

    /// Adds `cell`; false when it was there.
    fn insert(&mut self, cell: u32) -> bool {
        if 2 * (self.len + 1) > self.slots.len() {
            self.grow();
        }
        let mask = self.slots.len() - 1;
        let mut i = self.home(cell);
        loop {
            match self.slots[i] {
                Self::EMPTY => {
                    self.slots[i] = cell;
                    self.len += 1;
                    return true;
                }
                c if c == cell => return false,
                _ => i = (i + 1) & mask,
            }
        }
    }

    fn home(&self, cell: u32) -> usize {
        ((cell as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15) >> self.shift) as usize
    }

    fn grow(&mut self) {
        let capacity = (2 * self.slots.len()).max(64);
        let old = std::mem::replace(&mut self.slots, vec![Self::EMPTY; capacity]);
        self.shift = 64 - capacity.trailing_zeros();
        self.len = 0;
        for c in old.into_iter().filter(|&c| c != Self::EMPTY) {
            self.insert(c);
        }
    }

    fn clear(&mut self) {
        self.slots.fill(Self::EMPTY);
        self.len = 0;
    }
}

/// Crossings whose cells [`LedgerFeed`] finds together (the batched driver locates 8 at a
/// time).
const CELLS_AT_ONCE: usize = 8;

/// The embedded engine's feed when one thread both steps and locates: a free lane takes the
/// next cell the ledger needs, and a finished orbit goes to the ledger at once.
struct LedgerFeed<'a, 'p> {
    engine: &'a Engine<'a, 'p>,
    book: CrossingBook,
    dry_since: Option<u64>,
}

impl BatchFeed<2> for LedgerFeed<'_, '_> {
    fn next(&mut self, all_idle: bool) -> Feed<2> {
        let needed = self.engine.take_needed(&mut self.dry_since);
        self.engine.feed(needed, all_idle)
    }
    fn finished(&mut self, cell: usize, r: OrbitResult<2>) {
        let visited = self.book.take(cell as u32);
        self.engine.commit(cell as u32, &r, visited);
    }
    fn on_crossing(&mut self, cell: usize, c: &Crossing<2>) {
        self.on_crossings(&[cell], core::slice::from_ref(c));
    }
    fn on_crossings(&mut self, cells: &[usize], crossings: &[Crossing<2>]) {
        let e = self.engine;
        for (cells, crossings) in cells
            .chunks(CELLS_AT_ONCE)
            .zip(crossings.chunks(CELLS_AT_ONCE))
        {
            let pick = |k: usize| &crossings[k.min(crossings.len() - 1)];
            let q2: [f64; CELLS_AT_ONCE] = core::array::from_fn(|k| pick(k).q[1]);
            let p2: [f64; CELLS_AT_ONCE] = core::array::from_fn(|k| pick(k).p[1]);
            let to = e.grid.cells_of(&q2, &p2);
            for (&from, to) in cells.iter().zip(to) {
                if let Some(to) = to {
                    self.book.crossed(e.grid, e.claims, from as u32, to);
                }
            }
        }
    }
    fn keeps_crossings(&self) -> bool {
        false
    }
    fn books_by_cell(&self) -> Option<CellLattice> {
        Some(self.engine.grid.lattice())
    }
    fn cancelled(&mut self, cell: usize) -> bool {
        self.engine.cancelled(cell as u32)
    }
    fn abandoned(&mut self, cell: usize, steps: u64) {
        self.book.take(cell as u32);
        self.engine.abandoned(cell as u32, steps);
    }
}

/// Runs a whole grid in this process on the current rayon pool and returns the finished
/// ledger. Fast PSS streams: batched steppers (tangent-map methods; adaptive ones run one
/// scalar orbit per thread through the same feed) whose free lanes take the next cell the
/// ledger needs (skipping cells in flight or certain to be labelled) and offer each outcome
/// the moment its orbit ends; orbits whose cell the frontier orbit crosses are abandoned.
/// Speculation is bounded by the lanes in flight. Each thread steps its lanes and locates
/// and books their crossings itself: with a cell crossed by any running orbit held back, one
/// driver per thread drops little more than threads paired as stepper and locator, and is
/// faster. Adaptive methods stream too: rounds of cells drop far more of their steps than
/// the streaming feed with claims and abandonment (figures: docs/performance.md). Full mode,
/// and fast PSS with checkpoints, go in rounds of `window` cells. Either way the labels are
/// those of the sequential rule.
pub fn run_embedded(
    grid: &Grid,
    cell_run: &CellRun,
    mode: Mode,
    window: usize,
    progress: impl FnMut(&Ledger) + Send,
) -> Ledger {
    run_embedded_forecast(grid, cell_run, mode, window, None, progress)
}

/// [`run_embedded`] with the labellers of a similar finished run ([`Ledger::forecast`]) as a
/// hint for streaming fast PSS: its lanes take last the cells forecast to be labelled by an
/// orbit not yet committed. The labels are the same with any forecast or none; a good one
/// saves most of the speculative work (figures: docs/performance.md). Ignored
/// where [`takes_forecast`] says no, and when it was made on a grid of another size.
pub fn run_embedded_forecast(
    grid: &Grid,
    cell_run: &CellRun,
    mode: Mode,
    window: usize,
    forecast: Option<&Forecast>,
    progress: impl FnMut(&Ledger) + Send,
) -> Ledger {
    run_embedded_resumed(grid, cell_run, mode, window, forecast, Vec::new(), progress)
}

/// [`run_embedded_forecast`] going on from `committed`: outcomes an earlier process committed
/// for this run (its checkpoint), offered to the ledger before any orbit runs. Their cells are
/// never integrated again, and the labels are those of an uninterrupted run. `progress` is
/// called once right after the offers, before any orbit runs.
pub fn run_embedded_resumed(
    grid: &Grid,
    cell_run: &CellRun,
    mode: Mode,
    window: usize,
    forecast: Option<&Forecast>,
    committed: Vec<Outcome>,
    mut progress: impl FnMut(&Ledger) + Send,
) -> Ledger {
    run_embedded_with(
        grid,
        cell_run,
        mode,
        window,
        forecast,
        committed,
        &mut progress,
    )
}

/// [`run_embedded_forecast`] for any progress callback: the engines are compiled once, here,
/// rather than once per caller's closure in every crate that runs a grid.
fn run_embedded_with(
    grid: &Grid,
    cell_run: &CellRun,
    mode: Mode,
    window: usize,
    forecast: Option<&Forecast>,
    committed: Vec<Outcome>,
    progress: &mut (dyn FnMut(&Ledger) + Send),
) -> Ledger {
    let streaming = mode == Mode::FastPss && cell_run.checkpoints_per_decade == 0;
    if !streaming {
        let mut ledger = Ledger::new(grid, mode);
        for o in committed {
            ledger.offer(o);
        }
        progress(&ledger);
        while !ledger.done() {
            let cells = ledger.needed(window.max(1), &|_| false);
            for o in integrate_cells(grid, cell_run, mode, &cells) {
                ledger.offer(o);
            }
            progress(&ledger);
        }
        return ledger;
    }
    // Both are a few MB of per-cell arrays written before any orbit runs, so they are built
    // side by side (figures: docs/performance.md).
    let (claims, mut ledger) = rayon::join(|| Claims::new(grid), || Ledger::new(grid, mode));
    ledger.track_claim_changes();
    for o in committed {
        ledger.offer(o);
    }
    claims.sync(&mut ledger);
    progress(&ledger);
    let shared = Mutex::new(Shared { ledger, progress });
    let requests = requests_for(cell_run, mode);
    let checkpoints = cell_run.checkpoint_steps();
    let engine = Engine {
        grid,
        cell_run,
        checkpoints: &checkpoints,
        claims: &claims,
        shared: &shared,
        forecast: forecast.filter(|f| f.fits(grid.cells()) && takes_forecast(cell_run, mode)),
        failed: AtomicBool::new(false),
        spins: ledger_spins(),
    };
    let guided = engine.forecast.is_some();
    rayon::broadcast(|_| {
        let _guard = FailOnPanic(&engine.failed);
        let mut feed = LedgerFeed {
            engine: &engine,
            book: CrossingBook::default(),
            dry_since: None,
        };
        drive_plane(grid, cell_run, mode, &requests, guided, &mut feed);
    });
    finish(shared, &claims)
}

/// The ledger of a finished streaming run, with the abandoned orbits counted.
fn finish(shared: Mutex<Shared<'_>>, claims: &Claims) -> Ledger {
    let Shared { mut ledger, .. } = shared.into_inner().expect("ledger lock");
    let (n, steps) = claims.abandoned();
    ledger.record_abandoned(n, steps);
    ledger
}

/// Whether [`run_embedded_forecast`] lets a forecast guide this run: streaming fast PSS whose
/// threads keep several orbits in flight (lanes), the speculation a [`Forecast`] guides, unless
/// the engine choices turn forecasts off ([`salient_core::engine::EngineChoices::forecasts`]). An
/// adaptive method one orbit at a time drops little, and there a forecast only sends it further
/// ahead and slows the run, while lanes gain from a good one (figures: docs/performance.md).
pub fn takes_forecast(cell_run: &CellRun, mode: Mode) -> bool {
    let (method, config) = (&cell_run.run.method, &cell_run.config);
    let several_in_flight =
        !method.is_adaptive() || adaptive_orbits_per_thread(method, config.tau, config.t_final) > 1;
    mode == Mode::FastPss
        && cell_run.checkpoints_per_decade == 0
        && several_in_flight
        && salient_core::engine::choices().forecasts
}

#[cfg(test)]
mod tests {
    use super::CellSet;
    use std::collections::HashSet;

    /// The set answers as a `HashSet` through growth, collisions and clearing.
    #[test]
    fn cell_set_agrees_with_a_hash_set() {
        let mut set = CellSet::default();
        let mut reference = HashSet::new();
        for round in 0..3u32 {
            // Cells spaced by the table size collide in the multiplicative hash's low bits.
            for k in 0..5_000u32 {
                let cell = (k * 7_919 + round * 13) % 4_096 * 64;
                assert_eq!(set.insert(cell), reference.insert(cell), "cell {cell}");
            }
            assert_eq!(set.len, reference.len());
            set.clear();
            reference.clear();
            assert!(set.insert(5) && !set.insert(5));
            set.clear();
        }
    }
}
