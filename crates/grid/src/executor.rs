//! The tile executor: integrates cells on the current rayon pool — a fixed list
//! ([`integrate_cells`]), a worker's stream of leased cells ([`integrate_stream`]), or the cells
//! the embedded ledger needs next ([`run_embedded`]) — and turns each orbit into an [`Outcome`].
//! Tangent-map methods run [`lanes`] orbits at a time in the batched stepper; adaptive methods
//! one orbit per task. An outcome depends only on its cell, never on scheduling, so any
//! partition of the work gives the same bits.

use crate::geometry::Grid;
use crate::ledger::{Forecast, Ledger, Mode, Outcome};
use crate::pages::owned;
use rayon::prelude::*;
use salient_core::batch::{BatchFeed, Feed, Isa};
use salient_core::method::Method;
use salient_core::orbit::{
    sample_steps, steps_to, Class, OrbitConfig, OrbitResult, Requests, Status,
};
use salient_core::run::{
    adaptive_orbits_per_thread, integrate_feed_adaptive_henon_heiles, integrate_feed_henon_heiles,
    MethodRun,
};
use salient_core::section::on_section;
use salient_core::section::{CellLattice, Crossing};
use salient_core::{HenonHeiles, TangentMap};
use std::sync::atomic::{AtomicBool, AtomicU32, AtomicU64, AtomicUsize, Ordering};
use std::sync::{Mutex, MutexGuard, TryLockError};

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
    }
}

/// Running orbits remembered per cell as having crossed it (see [`Claims::running_crosser`]).
const CROSSERS: usize = 4;

/// What the fast-PSS engine knows for certain while orbits run: cells already labelled, and
/// cells crossed by the frontier orbit — the first cell the ledger still needs, whose orbit is
/// certain to commit, so every cell it crosses is certain to be labelled by it. Orbits started
/// from such cells are abandoned at once instead of being integrated to the end and dropped.
pub struct Claims {
    frontier: AtomicUsize,
    position: Vec<u32>,
    /// Certain: labelled by a commit, or crossed by the frontier orbit.
    claimed: Vec<AtomicBool>,
    /// On the coordinator's word ([`Claims::claim`]): the cell no longer needed an orbit when
    /// it said so, which a later lease of the cell withdraws ([`Claims::unclaim`]). Kept apart
    /// from `claimed` so that withdrawing never undoes a certain claim.
    told: Vec<AtomicBool>,
    /// Per cell, the canonical positions of up to [`CROSSERS`] orbits before it that crossed
    /// it while running: if one of them still runs and commits, the cell is labelled by it, so
    /// integrating the cell now is probably wasted. Slots of orbits that stopped are reused.
    crossed_by: Vec<[AtomicU32; CROSSERS]>,
    /// Per cell, whether its orbit is running in some lane.
    running: Vec<AtomicBool>,
    /// Per cell, whether a pending outcome before it in canonical order crossed it: the
    /// ledger's [`Ledger::is_claimed`], mirrored at every [`Claims::sync`] so that running
    /// orbits can ask without the lock (the embedded engine only).
    pending_claimed: Vec<AtomicBool>,
    /// Bumped whenever an orbit stops running (finished or abandoned): only then can a cell
    /// that a search for work skipped become available, so an idle lane searches again only
    /// after a bump.
    stopped: AtomicU64,
    abandoned: AtomicU64,
    abandoned_steps: AtomicU64,
}

impl Claims {
    pub fn new(grid: &Grid) -> Self {
        let unset = || {
            owned(
                (0..grid.cells()).map(|_| AtomicBool::new(false)).collect(),
                || AtomicBool::new(false),
            )
        };
        Claims {
            frontier: AtomicUsize::new(0),
            position: grid.positions().to_vec(),
            claimed: unset(),
            told: unset(),
            crossed_by: (0..grid.cells())
                .map(|_| core::array::from_fn(|_| AtomicU32::new(u32::MAX)))
                .collect(),
            running: unset(),
            pending_claimed: unset(),
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

    /// Marks a cell as labelled by another orbit on the coordinator's word: its orbit, if
    /// running, is abandoned.
    pub fn claim(&self, cell: u32) {
        if let Some(c) = self.told.get(cell as usize) {
            c.store(true, Ordering::Relaxed);
        }
    }

    /// Withdraws [`Claims::claim`]: the cell needs its orbit after all (its claimer was
    /// dropped). Certain claims stay.
    pub fn unclaim(&self, cell: u32) {
        if let Some(c) = self.told.get(cell as usize) {
            c.store(false, Ordering::Relaxed);
        }
    }

    fn claimed_any(&self, cell: u32) -> bool {
        self.claimed[cell as usize].load(Ordering::Relaxed)
            || self.told[cell as usize].load(Ordering::Relaxed)
    }

    /// Brings the claims up to date with the ledger (call with the ledger locked).
    pub fn sync(&self, ledger: &mut Ledger) {
        for c in ledger.take_newly_labelled() {
            self.claimed[c as usize].store(true, Ordering::Relaxed);
        }
        ledger.drain_claim_changes(|c, claimed| {
            self.pending_claimed[c as usize].store(claimed, Ordering::Relaxed);
        });
        self.frontier.store(ledger.frontier(), Ordering::Relaxed);
    }

    fn is_frontier(&self, cell: u32) -> bool {
        self.position[cell as usize] as usize == self.frontier.load(Ordering::Relaxed)
    }

    /// Whether the cell is certain to be labelled by another orbit.
    /// (The coordinator's word holds even at this side's frontier, which may lag behind the
    /// coordinator's.)
    pub fn is_claimed(&self, cell: u32) -> bool {
        (self.claimed[cell as usize].load(Ordering::Relaxed) && !self.is_frontier(cell))
            || self.told[cell as usize].load(Ordering::Relaxed)
    }

    /// The running orbit of cell `from` crossed `cell`: noted if `from` comes before `cell` in
    /// canonical order, in a free slot or one whose orbit has stopped. Read before writing: a
    /// read-modify-write on a cache line the other threads read costs more than the rest of
    /// the bookkeeping.
    fn note_crossed(&self, grid: &Grid, from: u32, cell: u32) {
        // A cell certain to be labelled is never started, so who crossed it does not matter;
        // most crossings in the chaotic sea fall in such cells, and this byte per cell stays
        // in cache where the slots do not.
        if self.claimed[cell as usize].load(Ordering::Relaxed) {
            return;
        }
        let pos = self.position[from as usize];
        if pos >= self.position[cell as usize] {
            return;
        }
        let slots = &self.crossed_by[cell as usize];
        let seen: [u32; CROSSERS] = core::array::from_fn(|k| slots[k].load(Ordering::Relaxed));
        if seen.contains(&pos) {
            return;
        }
        let canonical = grid.canonical();
        let free = (0..CROSSERS)
            .find(|&k| seen[k] == u32::MAX)
            .or_else(|| (0..CROSSERS).find(|&k| !self.is_running(canonical[seen[k] as usize])));
        // A plain store: when two threads race for a slot one hint is lost, never a label, and
        // a locked compare-exchange stalls the thread on every note (figures:
        // docs/performance.md).
        if let Some(k) = free {
            slots[k].store(pos, Ordering::Relaxed);
        }
    }

    /// Marks a cell as certain to be labelled (read first, for the reason given at
    /// [`Claims::note_crossed`]).
    fn claim_crossed(&self, cell: u32) {
        let c = &self.claimed[cell as usize];
        if !c.load(Ordering::Relaxed) {
            c.store(true, Ordering::Relaxed);
        }
    }

    /// The cell of the earliest orbit before `cell` in canonical order that crossed it while
    /// running and still runs.
    ///
    /// Up to [`CROSSERS`] per cell: with the earliest crosser alone, once that orbit is
    /// abandoned a running later one that crossed the cell too is forgotten, and the cell's
    /// orbit is started and abandoned when the other crosses it again (figures:
    /// docs/performance.md).
    fn running_crosser(&self, grid: &Grid, cell: u32) -> Option<u32> {
        let canonical = grid.canonical();
        self.crossed_by[cell as usize]
            .iter()
            .map(|s| s.load(Ordering::Relaxed))
            .filter(|&pos| pos != u32::MAX)
            .map(|pos| (pos, canonical[pos as usize]))
            .filter(|&(_, from)| self.is_running(from))
            .min()
            .map(|(_, from)| from)
    }

    /// Whether the orbit of `cell` is probably wasted: a pending outcome before it crossed it,
    /// or a running orbit before it did and that orbit is itself neither claimed nor crossed
    /// by an earlier running one, so it will very likely commit and label the cell. (If it
    /// does not, the cell is integrated again later: abandoning costs the steps done so far,
    /// running on costs the rest.)
    ///
    /// The pending outcomes matter because [`Claims::running_crosser`] knows only orbits that
    /// still run: once an orbit that crossed the cell has ended, only its pending outcome
    /// tells, and without it the cell's orbit would run to its end and be dropped (figures:
    /// docs/performance.md).
    fn probably_labelled(&self, grid: &Grid, cell: u32) -> bool {
        if self.is_pending_claimed(cell) {
            return true;
        }
        self.running_crosser(grid, cell).is_some_and(|from| {
            !self.claimed_any(from) && self.running_crosser(grid, from).is_none()
        })
    }

    /// Whether a pending outcome before the cell in canonical order crossed it (see
    /// [`Claims::probably_labelled`]).
    fn is_pending_claimed(&self, cell: u32) -> bool {
        self.pending_claimed[cell as usize].load(Ordering::Relaxed) && !self.is_frontier(cell)
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

/// A worker's own ledger of a run: the outcomes of its orbits and those its coordinator relays
/// from other workers, committed as the coordinator commits them, and the [`Claims`] its
/// streams read. Every outcome is the same wherever its orbit ran, and a commit needs every
/// earlier cell settled, so the commits of a ledger that has seen some of the outcomes are a
/// prefix of the coordinator's: its labels are certain and its frontier is at or before the
/// coordinator's (a cell there is the frontier, or committed with its own orbit), and the
/// streams use them as the embedded engine does — the frontier orbit's crossings claim cells
/// at once, and orbits crossed by a pending outcome are abandoned — instead of waiting for
/// the coordinator's skips. Full mode labels no crossed cell, so there it keeps only the
/// coordinator's claims.
pub struct LocalLedger {
    grid: Grid,
    ledger: Option<Mutex<Ledger>>,
    claims: Claims,
    offers: AtomicU64,
}

impl LocalLedger {
    pub fn new(grid: &Grid, mode: Mode) -> Self {
        match mode {
            Mode::FastPss => {
                let mut ledger = Ledger::new(grid, mode);
                ledger.track_claim_changes();
                LocalLedger {
                    grid: grid.clone(),
                    ledger: Some(Mutex::new(ledger)),
                    claims: Claims::new(grid),
                    offers: AtomicU64::new(0),
                }
            }
            Mode::Full => LocalLedger {
                grid: grid.clone(),
                ledger: None,
                claims: Claims::external(grid),
                offers: AtomicU64::new(0),
            },
        }
    }

    /// An outcome known here: this worker's, or one relayed by the coordinator (repeats are
    /// harmless: the ledger drops them).
    pub fn offer(&self, outcome: Outcome) {
        if let Some(ledger) = &self.ledger {
            let mut ledger = ledger.lock().expect("local ledger");
            ledger.offer(outcome);
            self.claims.sync(&mut ledger);
            self.offers.fetch_add(1, Ordering::Release);
        }
    }

    /// Outcomes offered so far (grows whenever the claims may have changed).
    pub fn offers(&self) -> u64 {
        self.offers.load(Ordering::Acquire)
    }

    pub fn grid(&self) -> &Grid {
        &self.grid
    }

    pub fn claims(&self) -> &Claims {
        &self.claims
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
    /// (position in `cells`, outcome) of the orbits this driver finished.
    done: Vec<(usize, Outcome)>,
}

impl BatchFeed<2> for CellsFeed<'_> {
    fn next(&mut self, _all_idle: bool) -> Feed<2> {
        let i = self.cursor.fetch_add(1, Ordering::Relaxed);
        match self.cells.get(i) {
            Some(&cell) => {
                let (q, p) = initial_point(self.grid, cell);
                Feed::Orbit(i, q, p)
            }
            None => Feed::Done,
        }
    }
    fn finished(&mut self, i: usize, r: OrbitResult<2>) {
        let visited = crossed_cells(self.grid, &r.crossings);
        let o = outcome(self.cell_run, self.checkpoints, self.cells[i], &r, visited);
        self.done.push((i, o));
    }
    fn books_by_cell(&self) -> Option<CellLattice> {
        Some(self.grid.lattice())
    }
}

fn initial_point(grid: &Grid, cell: u32) -> ([f64; 2], [f64; 2]) {
    let (q2, p2) = grid.centre(cell);
    on_section(&HenonHeiles, grid.energy, &[q2], &[p2])
        .expect("compatible cells lie on the section")
}

/// Integrates `cells` (compatible cells of `grid`) and returns their outcomes in the same order.
pub fn integrate_cells(grid: &Grid, cell_run: &CellRun, mode: Mode, cells: &[u32]) -> Vec<Outcome> {
    let requests = requests_for(cell_run, mode);
    let checkpoints = cell_run.checkpoint_steps();
    let map = tangent_map(cell_run);
    // A batched driver fills `lanes` orbits at a time; an adaptive one runs one or a few.
    let per_driver = map.as_ref().map_or_else(
        || {
            let c = &cell_run.config;
            adaptive_orbits_per_thread(&cell_run.run.method, c.tau, c.t_final)
        },
        |_| lanes(mode),
    );
    let cursor = AtomicUsize::new(0);
    let drivers = rayon::current_num_threads().min(cells.len().div_ceil(per_driver));
    let finished: Vec<(usize, Outcome)> = (0..drivers)
        .into_par_iter()
        .flat_map_iter(|_| {
            let mut feed = CellsFeed {
                grid,
                cell_run,
                checkpoints: &checkpoints,
                cells,
                cursor: &cursor,
                done: Vec::new(),
            };
            drive_feed(grid, cell_run, mode, map.as_ref(), &requests, &mut feed);
            feed.done
        })
        .collect();
    let mut out: Vec<Option<Outcome>> = vec![None; cells.len()];
    for (i, o) in finished {
        out[i] = Some(o);
    }
    out.into_iter()
        .map(|o| o.expect("every listed cell is integrated"))
        .collect()
}

fn requests_for(cell_run: &CellRun, mode: Mode) -> Requests {
    Requests {
        crossings: mode == Mode::FastPss,
        samples_per_decade: cell_run.checkpoints_per_decade,
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

/// Where [`integrate_stream`] gets its cells and sends their results: a worker's leases,
/// which arrive while earlier ones still run.
pub trait CellSource: Sync {
    /// The first waiting cell, in the source's order, that `judge` lets go; cells it drops
    /// end at once without an outcome (`ended` with `None` and 0 steps), cells it defers stay
    /// for a later call. `all_idle`: no lane of the asking driver has work (the source may
    /// block a moment before it answers [`Take::Wait`]).
    fn take(&self, all_idle: bool, judge: &dyn Fn(u32) -> Verdict) -> Take;
    /// The orbit of an entry [`Take::Cell`] gave ended: its outcome, or `None` when it was
    /// skipped (`steps` = 0) or abandoned after `steps` steps.
    fn ended(&self, entry: u64, outcome: Option<Outcome>, steps: u64);
}

/// What a stream makes of a waiting cell.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Verdict {
    /// Integrate it now.
    Go,
    /// An orbit that runs or waits for commit here probably labels it: ask again later (as the
    /// embedded engine takes other cells first).
    Later,
    /// Certain to be labelled by another orbit, or its own orbit runs or ran: no outcome.
    Drop,
}

/// A [`CellSource`]'s answer.
pub enum Take {
    /// An entry: the cell in the low 32 bits, the rest the source's own (the same cell may
    /// come again, in another lease, while its earlier orbit still runs).
    Cell(u64),
    /// An entry the judge deferred, handed out because nothing on this side can settle it (no
    /// orbit runs and none other waits). Its orbit is abandoned only once its cell is claimed
    /// for certain, never on a probable label: the source asked for it knowing more than this
    /// side may (a worker's ledger can lack outcomes its coordinator has), and a probable label
    /// that never comes true would abandon it at every try.
    Insist(u64),
    /// Nothing to integrate now; ask again.
    Wait,
    /// Nothing more will come.
    Done,
}

/// The tile executor over a stream of cells: every thread of the current rayon pool drives
/// its lanes from `source` until it says [`Take::Done`], so lanes freed by an orbit that ended
/// take the next cell whatever lease it came in (a lease run on its own leaves lanes idle
/// until its longest orbit ends). Every outcome goes to `local` as its orbit ends. A cell
/// claimed is skipped without an outcome; one crossed by an orbit running here or by a pending
/// outcome of `local` waits while later cells go first; an orbit is abandoned once its cell is
/// claimed or probably labelled.
pub fn integrate_stream(
    grid: &Grid,
    cell_run: &CellRun,
    mode: Mode,
    local: &LocalLedger,
    source: &dyn CellSource,
) {
    let requests = requests_for(cell_run, mode);
    let checkpoints = cell_run.checkpoint_steps();
    let map = tangent_map(cell_run);
    rayon::broadcast(|_| {
        let mut feed = StreamFeed {
            grid,
            cell_run,
            checkpoints: &checkpoints,
            local,
            claims: local.claims(),
            source,
            insisted: Vec::new(),
        };
        drive_feed(grid, cell_run, mode, map.as_ref(), &requests, &mut feed);
    });
}

/// A driver's feed from a [`CellSource`]; orbits are known by their entry.
struct StreamFeed<'a> {
    grid: &'a Grid,
    cell_run: &'a CellRun,
    checkpoints: &'a [u64],
    local: &'a LocalLedger,
    claims: &'a Claims,
    source: &'a dyn CellSource,
    /// Entries of this driver's lanes handed out as [`Take::Insist`].
    insisted: Vec<usize>,
}

impl BatchFeed<2> for StreamFeed<'_> {
    fn next(&mut self, all_idle: bool) -> Feed<2> {
        let (claims, grid) = (self.claims, self.grid);
        // Dropped cells are left without an outcome: the coordinator leases them again if it
        // still needs them.
        let judge = |cell: u32| {
            if claims.is_claimed(cell) || claims.is_running(cell) {
                Verdict::Drop
            } else if claims.is_pending_claimed(cell)
                || claims.running_crosser(grid, cell).is_some()
            {
                Verdict::Later
            } else {
                Verdict::Go
            }
        };
        let take = self.source.take(all_idle, &judge);
        if let Take::Insist(entry) = take {
            self.insisted.push(entry as usize);
        }
        match take {
            Take::Cell(entry) | Take::Insist(entry) => {
                let cell = entry as u32;
                claims.set_running(cell, true);
                let (q, p) = initial_point(grid, cell);
                Feed::Orbit(entry as usize, q, p)
            }
            Take::Wait => Feed::Wait,
            Take::Done => Feed::Done,
        }
    }
    fn finished(&mut self, id: usize, r: OrbitResult<2>) {
        let cell = id as u32;
        self.claims.set_running(cell, false);
        self.insisted.retain(|&e| e != id);
        let visited = crossed_cells(self.grid, &r.crossings);
        let o = outcome(self.cell_run, self.checkpoints, cell, &r, visited);
        self.local.offer(o.clone());
        self.source.ended(id as u64, Some(o), r.steps);
    }
    fn books_by_cell(&self) -> Option<CellLattice> {
        Some(self.grid.lattice())
    }
    fn on_crossing(&mut self, id: usize, c: &Crossing<2>) {
        if let Some(to) = self.grid.cell_of(c.q[1], c.p[1]) {
            let from = id as u32;
            if self.claims.is_frontier(from) {
                self.claims.claim_crossed(to);
            }
            self.claims.note_crossed(self.grid, from, to);
        }
    }
    fn cancelled(&mut self, id: usize) -> bool {
        let cell = id as u32;
        self.claims.is_claimed(cell)
            || (!self.insisted.contains(&id) && self.claims.probably_labelled(self.grid, cell))
    }
    fn abandoned(&mut self, id: usize, steps: u64) {
        let cell = id as u32;
        self.claims.set_running(cell, false);
        self.insisted.retain(|&e| e != id);
        self.claims.record_abandoned(steps);
        self.source.ended(id as u64, None, steps);
    }
}

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
        // A cell crossed by an earlier running orbit or an earlier pending outcome will be
        // labelled by it unless that orbit is dropped: take other cells first. The frontier
        // cell is never skipped (nothing before it runs), so this cannot stall.
        let busy = |c: u32| {
            claims.is_running(c)
                || claims.is_claimed(c)
                || ledger.is_claimed(c)
                || claims.running_crosser(grid, c).is_some()
        };
        // Cells a forecast says an orbit not yet committed will label come last, but after
        // FORECAST_PATIENCE of them the first is taken: a poor forecast (another τ's labels,
        // say) would otherwise send the lanes ever further ahead of the frontier while the
        // cells it needs wait.
        let frontier = ledger.frontier();
        let defers = |c: u32| self.forecast.is_some_and(|f| f.defers(c, frontier));
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
    mut progress: impl FnMut(&Ledger) + Send,
) -> Ledger {
    run_embedded_with(grid, cell_run, mode, window, forecast, &mut progress)
}

/// [`run_embedded_forecast`] for any progress callback: the engines are compiled once, here,
/// rather than once per caller's closure in every crate that runs a grid.
fn run_embedded_with(
    grid: &Grid,
    cell_run: &CellRun,
    mode: Mode,
    window: usize,
    forecast: Option<&Forecast>,
    progress: &mut (dyn FnMut(&Ledger) + Send),
) -> Ledger {
    let streaming = mode == Mode::FastPss && cell_run.checkpoints_per_decade == 0;
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
    // Both are a few MB of per-cell arrays written before any orbit runs, so they are built
    // side by side (figures: docs/performance.md).
    let (claims, mut ledger) = rayon::join(|| Claims::new(grid), || Ledger::new(grid, mode));
    ledger.track_claim_changes();
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
    let Method::TangentMap(scheme) = &cell_run.run.method else {
        rayon::broadcast(|_| {
            let _guard = FailOnPanic(&engine.failed);
            let mut feed = LedgerFeed {
                engine: &engine,
                book: CrossingBook::default(),
                dry_since: None,
            };
            drive_adaptive(
                grid,
                cell_run,
                &requests,
                engine.forecast.is_some(),
                &mut feed,
            );
        });
        return finish(shared, &claims);
    };
    let ham = HenonHeiles;
    let map = TangentMap::new(&ham, scheme, cell_run.config.tau);
    rayon::broadcast(|_| {
        let _guard = FailOnPanic(&engine.failed);
        let mut feed = LedgerFeed {
            engine: &engine,
            book: CrossingBook::default(),
            dry_since: None,
        };
        drive(&map, &cell_run.config, &requests, mode, &mut feed);
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
/// `SALIENT_FORECAST=0`. An adaptive method one orbit at a time drops little, and there a
/// forecast only sends it further ahead and slows the run, while lanes gain from a good one
/// (figures: docs/performance.md).
pub fn takes_forecast(cell_run: &CellRun, mode: Mode) -> bool {
    let (method, config) = (&cell_run.run.method, &cell_run.config);
    let several_in_flight = matches!(method, Method::TangentMap(_))
        || adaptive_orbits_per_thread(method, config.tau, config.t_final) > 1;
    mode == Mode::FastPss
        && cell_run.checkpoints_per_decade == 0
        && several_in_flight
        && std::env::var("SALIENT_FORECAST").map_or(true, |v| v != "0")
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
