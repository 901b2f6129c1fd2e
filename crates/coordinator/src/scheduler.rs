//! The scheduler state and every transition of it, synchronous and free of networking so it
//! can be driven by the event loop and by tests alike. Outside a group each mutating call has
//! committed its writes when it returns, so the caller may acknowledge afterwards; inside one
//! ([`Scheduler::begin_group`]) the writes are committed by the store thread, which then
//! releases the group's answers.

use crate::writer::{Deferred, StoreThread, Write};
use prost::bytes::Bytes;
use prost::Message;
use salient_grid::spec::{self, JobSpec};
use salient_grid::{takes_forecast, Forecast, Grid, Ledger, OutcomeNews};
use salient_proto::v1;
use salient_proto::{outcome_from_wire, Expected, PROTOCOL_VERSION};
use salient_store::{JobState, Store, StoreError};
use std::cell::RefCell;
use std::collections::{BTreeMap, BTreeSet, HashMap, HashSet};
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};
use tonic::Status;

/// Fast PSS: cells of the canonical order in one lease unit (the coordinator's tile; the
/// spec's tile sizes full-mode leases only). A worker's slot takes the earliest
/// units with wanted cells, and a unit has one lease at a time, so the unit bounds how far
/// past the frontier the next worker must go: with units of a 400-cell spec tile it would
/// start hundreds of cells ahead, where most cells are labelled meanwhile. Fixed, not sized by
/// the workers, so that a restarted coordinator reads the stored attempts of the same units.
/// 16 cells (four batches of AVX2 lanes) ran faster at 4–64 simulated workers than 4, 8
/// or 400 (figures: docs/performance.md).
pub const FAST_PSS_LEASE_CELLS: usize = 16;

/// Fast PSS: cells past the frontier that leases may take: at least [`WINDOW_CELLS_MIN`],
/// and [`WINDOW_CELLS_PER_WORKER`] per worker. Near the frontier every cell is soon leased,
/// has an outcome or is crossed by one while the frontier orbit runs on, and a worker whose
/// lease brought nothing idles (workers skip cells that their own running orbits crossed, so
/// farther cells cost little speculation). The bound keeps an idle worker's poll from scanning
/// the whole grid; a window of [`WINDOW_CELLS_MIN`] runs about as fast as the whole grid
/// (figures: docs/performance.md).
const WINDOW_CELLS_PER_WORKER: usize = 1_600;
const WINDOW_CELLS_MIN: usize = 25_600;

/// The grid run `index`'s leases cut: fast PSS in units of [`FAST_PSS_LEASE_CELLS`], full mode
/// in the spec's tiles (a tile's orbits are independent, and larger units cost fewer round
/// trips).
pub fn lease_grid(spec: &JobSpec, index: usize) -> Grid {
    let grid = spec.grid(index);
    match spec.mode(index) {
        salient_grid::Mode::FastPss => grid.retiled(FAST_PSS_LEASE_CELLS),
        salient_grid::Mode::Full => grid,
    }
}

/// Leases one poll's reply carries at most: a many-threaded worker's batch of fast-PSS
/// cells spans many lease units.
const MAX_POLL_LEASES: usize = 256;

/// Relayed outcomes one poll's reply carries at most (bytes), well below the message limit.
const RELAY_BYTES: usize = 1 << 20;

/// Leases of a run answered in a row without a new outcome while its resolved count stays put
/// that make it stalled (see [`Stall`]). Speculative leases far from the frontier come back
/// empty now and then; dozens in a row with nothing resolving are a worker that cannot settle
/// what it is given.
const STALL_LEASES: u32 = 32;

/// Timing of leases and polls.
#[derive(Clone, Copy, Debug)]
pub struct Config {
    /// A lease lapses this long after the last poll that named it.
    pub lease: Duration,
    /// How often workers poll while busy.
    pub poll: Duration,
    /// A worker that has not polled for this long is taken for dead: its leases go to other
    /// workers at once, without waiting for them to lapse. Many poll intervals, so a busy
    /// host's hiccup is not taken for a death; one that was is harmless (a worker that comes
    /// back registers again and its late reports change nothing committed).
    pub worker_timeout: Duration,
    /// Fast PSS: cells per worker thread in one lease, for tangent-map methods (whose
    /// threads run `executor::LANES` orbits at a time); adaptive methods get it scaled by
    /// the orbits a thread runs at once (`run::adaptive_orbits_per_thread`: one, or the
    /// lanes of a SIMD batch) over [`ADAPTIVE_LEASE_SHARE`], at least 1. Small leases are
    /// judged on fresher claims (less dropped work); large ones cost fewer round trips.
    pub lease_cells_per_thread: usize,
    /// Largest grid (cells in all) a submitted spec may ask for.
    pub max_cells: usize,
    /// Largest cells × runs a submitted spec may ask for: every run of a job keeps its ledger
    /// in memory.
    pub max_cell_runs: usize,
}

/// Default of [`Config::lease_cells_per_thread`]: eight batches of lanes. Every poll costs
/// about 0.7 ms of CPU in the network stacks of the two ends, against 70 µs in the scheduler,
/// and leases of two batches made a tangent-map worker poll more often than the fresher claims
/// saved (figures: docs/performance.md).
pub const LEASE_CELLS_PER_THREAD: usize = 8 * salient_grid::executor::LANES;

/// An adaptive thread's lease is [`Config::lease_cells_per_thread`] × the orbits it runs at
/// once / this: two cells per orbit at the default. Threads of one orbit at a time drop more
/// work with longer leases (figures: docs/performance.md).
pub const ADAPTIVE_LEASE_SHARE: usize = 16;

/// Default of [`Config::max_cell_runs`]: a 4000×4000 grid twice, or the paper's 400×400 Table 2
/// (24 runs) 80 times over; about 0.8 GB of ledgers at most.
pub const MAX_CELL_RUNS: usize = 32_000_000;

/// Default of [`Config::worker_timeout`]: 25 polls of a busy worker.
pub const DEFAULT_WORKER_TIMEOUT: Duration = Duration::from_secs(5);

impl Default for Config {
    fn default() -> Self {
        Config {
            lease: Duration::from_secs(30),
            poll: Duration::from_millis(200),
            worker_timeout: DEFAULT_WORKER_TIMEOUT,
            lease_cells_per_thread: LEASE_CELLS_PER_THREAD,
            max_cells: spec::MAX_CELLS,
            max_cell_runs: MAX_CELL_RUNS,
        }
    }
}

/// A (job, run, tile) lease's work, without the attempt.
type TileKey = (u64, u32, u32);

struct WorkerInfo {
    /// Tells this worker's relayed outcomes from others'.
    serial: u64,
    name: String,
    threads: u32,
    last_seen: Instant,
    leases: BTreeSet<TileKey>,
    /// Answers to reports this worker sent, each with the store group that makes it durable
    /// (see [`Scheduler::poll`]), in the order the reports came: stale ones flagged.
    owed: Vec<(u64, v1::TileRef, bool)>,
}

struct ActiveLease {
    worker: String,
    deadline: Instant,
    cells: Vec<u32>,
    /// Cells the worker was already told to skip.
    skipped: HashSet<u32>,
    /// Fast PSS: cells whose running orbits said what they crossed so far (see
    /// [`Ledger::progress`]); those claims go when the lease ends.
    running: HashSet<u32>,
}

#[derive(Default)]
struct Tile {
    /// The highest attempt that may have been issued (0: never leased); the next lease takes
    /// the number after it.
    attempt: u32,
    /// The attempt whose reports count: the latest issued, or the one a worker held through
    /// a restart and got back. Reports of any other are stale.
    valid: u32,
    /// Loaded from the store and not leased since. Leases are answered before their attempt
    /// is committed, so a crash may have lost the latest one issued: `attempt` is one past
    /// the stored number (never issued twice), and a worker naming either gets its lease
    /// back.
    restored: bool,
    /// The last lease lapsed or its worker was forgotten (it fell silent), and none was
    /// issued since: a worker that comes back naming it gets it back.
    lapsed: bool,
    lease: Option<ActiveLease>,
    /// The run ledger's [`Ledger::reopenings`] when the tile was last found without wanted
    /// cells: while it is unchanged the tile has none, and the lease search passes it by
    /// (scanning the window's cells on every poll would be a large share of the coordinator's
    /// CPU; figures: docs/performance.md).
    drained_at: Option<u64>,
}

/// The progress guarantee of a run: leases finished since its resolved count last moved that
/// brought no new outcome, and who returned them. Once [`STALL_LEASES`] have, the run is
/// stalled: a warning names the tiles and workers, and each of those tiles goes to a worker
/// that has not returned it empty, while there is one. Any movement of the resolved count
/// ends the stall.
#[derive(Default)]
struct Stall {
    resolved: usize,
    empty_leases: u32,
    /// Tile → workers that returned it empty in this stretch.
    involved: BTreeMap<u32, BTreeSet<String>>,
}

impl Stall {
    fn is_stalled(&self) -> bool {
        self.empty_leases >= STALL_LEASES
    }

    /// Whether `worker` should leave tile `t` to one of `others` (the registered workers).
    fn shuns<'a>(
        &self,
        t: u32,
        worker: &str,
        mut others: impl Iterator<Item = &'a String>,
    ) -> bool {
        self.is_stalled()
            && self.involved.get(&t).is_some_and(|ws| {
                ws.contains(worker) && others.any(|o| o != worker && !ws.contains(o))
            })
    }
}

struct Run {
    grid: Grid,
    ledger: Ledger,
    stall: Stall,
    /// Fast PSS: every outcome received that counts, in the order it came to count, with the
    /// serial of the worker that sent it (`u64::MAX`: loaded from the store), relayed to the
    /// other workers of the run ([`v1::Relay`]). Emptied when the run is done. Each outcome as
    /// the store holds it, encoded once: every reply that relays it shares these bytes.
    relay: Vec<(u64, Bytes)>,
    /// Fast PSS: outcomes received that do not count yet (an earlier live outcome crossed
    /// their cell), by cell: relayed once they count ([`OutcomeNews`]), forgotten when
    /// dropped. Workers skip cells by the claims of counting outcomes only, so the others
    /// would cost every worker their bytes for nothing.
    unrelayed: HashMap<u32, (u64, Bytes)>,
    /// Cells whose own outcome is in the store (the ledger forgets a dropped one, and a resent
    /// report must still change nothing).
    stored: Vec<bool>,
    /// What each outcome of the run must carry.
    expected: Expected,
    /// Who is forecast to label each cell (a similar finished run, [`hand_forecast`]): cells
    /// the forecast defers ([`Forecast::defers`]) are leased only once their labeller turns
    /// out not to label them, and the others from anywhere in the grid rather than a window
    /// past the frontier.
    forecast: Option<Forecast>,
    /// The run of the job whose labellers are the forecast (`None`: none, or one given by
    /// [`Scheduler::set_forecast`]).
    forecast_from: Option<usize>,
    /// Orbits a worker thread of an adaptive method runs at once (one, or a few SIMD lanes);
    /// `None` for tangent-map methods, whose threads run a batch of lanes. Fast-PSS leases
    /// are sized by it.
    adaptive_orbits_per_thread: Option<usize>,
    tiles: Vec<Tile>,
    /// Cells said crossed by running orbits (logged when the run is done).
    crossings_said: u64,
    cpu_ns: u64,
    started: Option<Instant>,
    wall_s: f64,
    done: bool,
    extra_dropped_orbits: u64,
    extra_dropped_steps: u64,
}

struct Job {
    id: u64,
    name: String,
    spec: JobSpec,
    spec_json: String,
    state: JobState,
    runs: Vec<Run>,
    stale_reports: u64,
    error: Option<String>,
}

/// What a poll or report produced for the worker.
#[derive(Default)]
struct Replies {
    acknowledged: Vec<v1::TileRef>,
    stale: Vec<v1::TileRef>,
}

/// Fast PSS: gives the labellers of finished run `from` as a forecast ([`Run::forecast`]) to
/// the unfinished runs of the job it resembles, at the same energy (the same grid) and in the
/// same mode (a full-mode run labels every cell itself): the same τ
/// and t_final (another method or δ,
/// as `salient run` does in a sweep: integrators that agree on the orbits agree on the
/// labellers), or the same method and τ to a longer t_final (the same orbits, longer: each
/// crosses again every cell it crossed). Runs whose threads keep one orbit in flight take none
/// (`takes_forecast`), and one given by [`Scheduler::set_forecast`] stays. The last run
/// finished gives the forecast.
fn hand_forecast(spec: &JobSpec, runs: &mut [Run], from: usize) {
    let source = &spec.runs[from];
    let resembles = |target: &spec::RunSpec| {
        source.energy == target.energy
            && source.mode == target.mode
            && source.tau == target.tau
            && (source.t_final == target.t_final
                || (source.method == target.method
                    && source.delta == target.delta
                    && source.t_final < target.t_final))
    };
    let takers: Vec<usize> = (0..runs.len())
        .filter(|&r| {
            r != from
                && !runs[r].done
                && (runs[r].forecast.is_none() || runs[r].forecast_from.is_some())
                && resembles(&spec.runs[r])
                && takes_forecast(&spec.cell_run(r), spec.mode(r))
        })
        .collect();
    if takers.is_empty() {
        return;
    }
    let forecast = runs[from].ledger.forecast();
    for r in takers {
        tracing::debug!(run = r, from, "forecast from a finished run");
        runs[r].forecast = Some(forecast.clone());
        runs[r].forecast_from = Some(from);
    }
}

fn now_ms() -> i64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map_or(0, |d| d.as_millis() as i64)
}

/// A log field as people read it: two decimals.
fn round2(v: f64) -> f64 {
    (v * 100.0).round() / 100.0
}

fn store_err(e: StoreError) -> Status {
    tracing::error!(error = %e, "store failure");
    match e {
        // The message says what is damaged and what to do; it is the client's to read.
        StoreError::Damaged(_) => Status::data_loss(e.to_string()),
        _ => Status::internal(e.to_string()),
    }
}

fn tile_ref(key: TileKey, attempt: u32) -> v1::TileRef {
    v1::TileRef {
        job: key.0,
        run: key.1,
        tile: key.2,
        attempt,
    }
}

/// Counter names of a run's persisted totals.
fn counter(run: usize, what: &str) -> String {
    format!("run{run}.{what}")
}

impl Run {
    fn new(spec: &JobSpec, index: usize) -> Run {
        let grid = lease_grid(spec, index);
        let cell_run = spec.cell_run(index);
        let mut ledger = Ledger::new(&grid, spec.mode(index));
        if spec.mode(index) == salient_grid::Mode::FastPss {
            ledger.watch_outcomes();
        }
        Run {
            ledger,
            stall: Stall::default(),
            relay: Vec::new(),
            unrelayed: HashMap::new(),
            stored: vec![false; grid.cells()],
            forecast: None,
            forecast_from: None,
            expected: Expected::of_run(&cell_run),
            adaptive_orbits_per_thread: cell_run.run.method.is_adaptive().then(|| {
                salient_core::run::adaptive_orbits_per_thread(
                    &cell_run.run.method,
                    cell_run.config.tau,
                    cell_run.config.t_final,
                )
            }),
            tiles: (0..grid.tile_count()).map(|_| Tile::default()).collect(),
            crossings_said: 0,
            grid,
            cpu_ns: 0,
            started: None,
            wall_s: 0.0,
            done: false,
            extra_dropped_orbits: 0,
            extra_dropped_steps: 0,
        }
    }

    /// Ends tile `t`'s lease: the claims of its orbits in progress go.
    fn end_lease(&mut self, t: usize) -> Option<ActiveLease> {
        let lease = self.tiles.get_mut(t)?.lease.take()?;
        for &cell in &lease.running {
            self.ledger.forget_progress(cell);
        }
        self.relay_news();
        Some(lease)
    }

    /// Fast PSS: offers an outcome received from the worker of serial `from` (`u64::MAX`:
    /// loaded from the store) and relays what now counts.
    fn offer(&mut self, from: u64, encoded: Bytes, outcome: salient_grid::Outcome) {
        let cell = outcome.cell;
        self.ledger.offer(outcome);
        if self.ledger.mode() == salient_grid::Mode::FastPss {
            self.unrelayed.insert(cell, (from, encoded));
            self.relay_news();
        }
    }

    /// Moves the outcomes that came to count to the relay log, in the order they did, and
    /// forgets the dropped ones.
    fn relay_news(&mut self) {
        for news in self.ledger.take_outcome_news() {
            match news {
                OutcomeNews::Counts(cell) => {
                    if let Some(o) = self.unrelayed.remove(&cell) {
                        self.relay.push(o);
                    }
                }
                OutcomeNews::Dropped(cell) => {
                    self.unrelayed.remove(&cell);
                }
            }
        }
    }

    /// Fast PSS: what the running orbit of `cell`, leased in `lease` to `worker`, crossed
    /// since it last said (`stopped`: it was abandoned). Ignored unless that lease is out and
    /// holds the cell: a hint only.
    fn progress(&mut self, worker: &str, lease: &v1::TileRef, x: &v1::Crossings) {
        if self.done
            || self.ledger.mode() != salient_grid::Mode::FastPss
            || x.cell as usize >= self.grid.cells()
            || self.grid.tile_of(x.cell) != Some(lease.tile as usize)
        {
            return;
        }
        let Some(tile) = self.tiles.get_mut(lease.tile as usize) else {
            return;
        };
        let valid = tile.valid == lease.attempt;
        let Some(active) = tile.lease.as_mut().filter(|l| valid && l.worker == worker) else {
            return;
        };
        if x.stopped {
            active.running.remove(&x.cell);
            self.ledger.forget_progress(x.cell);
        } else {
            active.running.insert(x.cell);
            self.crossings_said += x.crossed.len() as u64;
            self.ledger.progress(x.cell, &x.crossed);
        }
        self.relay_news();
    }

    /// The cells of tile `t` that need their own orbit now, and whether the forecast held
    /// back others that do.
    fn wanted(&self, t: usize) -> (Vec<u32>, bool) {
        let mut deferred = false;
        let cells = self
            .grid
            .tile_cells(t)
            .iter()
            .copied()
            .filter(|&c| self.ledger.wants(c))
            .filter(|&c| {
                let defers = self
                    .forecast
                    .as_ref()
                    .is_some_and(|f| f.defers(c, &self.ledger));
                deferred |= defers;
                !defers
            })
            .collect();
        (cells, deferred)
    }

    /// Watches progress as a lease of tile `key.2` finishes (`brought`: it carried a new
    /// outcome) and warns once when the run stalls, naming workers by `name_of`.
    fn note_finished(
        &mut self,
        key: TileKey,
        worker: &str,
        brought: bool,
        name_of: impl Fn(&str) -> String,
    ) {
        let resolved = self.ledger.resolved();
        let stall = &mut self.stall;
        if resolved != stall.resolved || brought {
            if stall.is_stalled() {
                tracing::info!(job = key.0, run = key.1, resolved, "run progresses again");
            }
            *stall = Stall {
                resolved,
                ..Stall::default()
            };
            return;
        }
        stall.empty_leases += 1;
        stall
            .involved
            .entry(key.2)
            .or_default()
            .insert(worker.to_string());
        if stall.empty_leases == STALL_LEASES {
            let tiles: Vec<u32> = stall.involved.keys().copied().collect();
            let workers: BTreeSet<String> = stall
                .involved
                .values()
                .flatten()
                .map(|w| format!("{w} ({})", name_of(w)))
                .collect();
            tracing::warn!(
                job = key.0,
                run = key.1,
                resolved,
                leases = stall.empty_leases,
                ?tiles,
                ?workers,
                "run makes no progress: its leases come back without outcomes; \
                 offering its tiles to other workers"
            );
        }
    }

    fn elapsed(&self) -> f64 {
        if self.done {
            self.wall_s
        } else {
            self.started.map_or(0.0, |s| s.elapsed().as_secs_f64())
        }
    }
}

/// Where a job's runs stand, summed over its runs ([`Scheduler::progress`]).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Progress {
    /// Orbits whose outcomes the ledgers committed.
    pub committed_orbits: usize,
    /// Cells labelled.
    pub resolved_cells: usize,
    /// Fast PSS: cells that need their own orbit now (see [`Ledger::wants`]).
    pub wanted_cells: usize,
    /// Cells of the leases out.
    pub leased_cells: usize,
}

/// The cell at a fast-PSS run's frontier when it needs its own orbit: every commit waits for
/// it ([`Scheduler::frontier_cell`]).
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum FrontierCell<'a> {
    /// No lease holds it yet.
    Unleased(u32),
    /// A lease of this worker holds it (queued there, or running).
    Leased {
        /// The cell.
        cell: u32,
        /// Id of the worker whose lease holds it.
        worker: &'a str,
    },
    /// Its tile is leased without it (it was claimed, or skipped, when the lease was made):
    /// it waits for that lease to end.
    Stranded(u32),
}

/// Every job, worker and lease the coordinator knows, with the store behind it.
pub struct Scheduler {
    store: StoreThread,
    instance: String,
    cfg: Config,
    jobs: BTreeMap<u64, Job>,
    workers: HashMap<String, WorkerInfo>,
    next_worker: u64,
    /// Final status of finished jobs no longer held in memory: `status` of every job must not
    /// rebuild each finished job's ledgers from the store (health checks call it often).
    finished: RefCell<HashMap<u64, v1::JobStatus>>,
    /// Distinguishes this process's worker ids from a previous coordinator's on the same store:
    /// a worker still holding an old id must get NOT_FOUND, never another worker's identity.
    epoch: u64,
    /// When [`Scheduler::tick`] last ran.
    last_tick: Instant,
}

impl Scheduler {
    /// Opens the scheduler on a store, resuming every unfinished job from its committed
    /// outcomes (nothing committed is integrated again).
    pub fn new(store: Store, cfg: Config) -> Result<Scheduler, String> {
        let instance = store.instance_id().map_err(|e| e.to_string())?;
        let store =
            StoreThread::new(store).map_err(|e| format!("starting the store thread: {e}"))?;
        let mut s = Scheduler {
            instance,
            store,
            cfg,
            jobs: BTreeMap::new(),
            workers: HashMap::new(),
            finished: RefCell::new(HashMap::new()),
            next_worker: 1,
            epoch: SystemTime::now()
                .duration_since(UNIX_EPOCH)
                .map_or(0, |d| d.as_nanos() as u64),
            last_tick: Instant::now(),
        };
        let rows = s.store.unfinished_jobs().map_err(|e| e.to_string())?;
        for row in rows {
            let job = s.load_job(row.id).map_err(|e| e.message().to_string())?;
            tracing::info!(
                job = row.id,
                name = %job.name,
                resolved = job.runs.iter().map(|r| r.ledger.resolved()).sum::<usize>(),
                "resumed"
            );
            s.jobs.insert(row.id, job);
            // A run whose last outcome was committed but not marked done before a stop.
            s.finish_runs(row.id).map_err(|e| e.message().to_string())?;
        }
        Ok(s)
    }

    /// Rebuilds a job from the store: its runs' ledgers from every stored outcome (the ledger's
    /// result does not depend on arrival order), attempts and totals.
    fn load_job(&self, id: u64) -> Result<Job, Status> {
        let row = self
            .store
            .job(id)
            .map_err(store_err)?
            .ok_or_else(|| Status::not_found(format!("no job {id}")))?;
        let spec = spec::parse(&row.spec, true)
            .map_err(|e| Status::internal(format!("stored spec of job {id}: {e}")))?;
        let counters = self.store.counters(id).map_err(store_err)?;
        let count =
            |run: usize, what: &str| counters.get(&counter(run, what)).copied().unwrap_or(0);
        let mut runs = Vec::new();
        for index in 0..spec.runs.len() {
            let mut run = Run::new(&spec, index);
            for stored in self.store.outcomes(id, index as u32).map_err(store_err)? {
                let wire = v1::Outcome::decode(stored.data.as_slice())
                    .map_err(|e| Status::internal(format!("stored outcome: {e}")))?;
                let encoded = Bytes::from(stored.data);
                let o = outcome_from_wire(&wire, &run.grid, run.expected)
                    .map_err(|e| Status::internal(format!("stored outcome: {e}")))?;
                run.stored[o.cell as usize] = true;
                run.offer(u64::MAX, encoded, o);
            }
            run.cpu_ns = self
                .store
                .run_totals(id, index as u32)
                .map_err(store_err)?
                .cpu_ns;
            run.done = run.ledger.done();
            if run.done {
                run.relay = Vec::new();
                run.unrelayed = HashMap::new();
            }
            run.wall_s = count(index, "wall_ms") as f64 / 1e3;
            run.extra_dropped_orbits = count(index, "extra_dropped_orbits");
            run.extra_dropped_steps = count(index, "extra_dropped_steps");
            runs.push(run);
        }
        for (run, tile, attempt) in self.store.attempts(id).map_err(store_err)? {
            if let Some(t) = runs
                .get_mut(run as usize)
                .and_then(|r| r.tiles.get_mut(tile as usize))
            {
                t.attempt = attempt;
            }
        }
        for from in 0..runs.len() {
            if runs[from].done {
                hand_forecast(&spec, &mut runs, from);
            }
        }
        for t in runs.iter_mut().flat_map(|r| r.tiles.iter_mut()) {
            t.valid = t.attempt;
            t.attempt += 1;
            t.restored = true;
        }
        Ok(Job {
            id,
            name: row.name,
            spec,
            spec_json: row.spec,
            state: row.state,
            runs,
            stale_reports: counters.get("stale_reports").copied().unwrap_or(0),
            error: row.error,
        })
    }

    /// Gives run `run` of job `job` a forecast of its labellers (see `Run::forecast`); one made
    /// on a grid of another size is refused.
    pub fn set_forecast(&mut self, job: u64, run: usize, forecast: Forecast) -> Result<(), Status> {
        let r = self
            .jobs
            .get_mut(&job)
            .and_then(|j| j.runs.get_mut(run))
            .ok_or_else(|| Status::not_found(format!("no run {run} of job {job}")))?;
        if !forecast.fits(r.grid.cells()) {
            return Err(Status::invalid_argument(
                "the forecast was made on a grid of another size",
            ));
        }
        r.forecast = Some(forecast);
        r.forecast_from = None;
        Ok(())
    }

    /// The run of the job whose labellers run `run` takes as its forecast, if one does.
    pub fn forecast_from(&self, job: u64, run: usize) -> Option<usize> {
        self.jobs.get(&job)?.runs.get(run)?.forecast_from
    }

    /// Validates a spec and queues it; returns the job id and the spec's warnings.
    pub fn submit(&mut self, spec_json: &str) -> Result<(u64, Vec<String>), Status> {
        let spec = spec::parse_capped(spec_json, true, self.cfg.max_cells)
            .map_err(|e| Status::invalid_argument(e.0))?;
        let cells = spec.grid.n_q2 * spec.grid.n_p2;
        let cell_runs = cells.saturating_mul(spec.runs.len());
        if cell_runs > self.cfg.max_cell_runs {
            return Err(Status::invalid_argument(format!(
                "grid.cells × runs must be at most {} on this coordinator (got {cells} cells × {} \
                 runs = {cell_runs}; split the sweep into several jobs, or raise --max-cell-runs)",
                self.cfg.max_cell_runs,
                spec.runs.len()
            )));
        }
        let id = self
            .store
            .insert_job(&spec.name, spec_json, now_ms())
            .map_err(store_err)?;
        let runs = (0..spec.runs.len()).map(|i| Run::new(&spec, i)).collect();
        let warnings = spec.warnings.clone();
        tracing::info!(job = id, name = %spec.name, runs = spec.runs.len(), "submitted");
        self.jobs.insert(
            id,
            Job {
                id,
                name: spec.name.clone(),
                spec,
                spec_json: spec_json.to_string(),
                state: JobState::Queued,
                runs,
                stale_reports: 0,
                error: None,
            },
        );
        Ok((id, warnings))
    }

    /// Registers a worker speaking [`PROTOCOL_VERSION`] and gives it an id.
    pub fn register(&mut self, req: &v1::RegisterRequest) -> Result<v1::RegisterReply, Status> {
        if req.protocol_version != PROTOCOL_VERSION {
            return Err(Status::failed_precondition(format!(
                "worker speaks protocol version {}, this coordinator speaks {PROTOCOL_VERSION}; \
                 run the same salient release on both",
                req.protocol_version
            )));
        }
        if req.threads == 0 || req.threads > 4096 {
            return Err(Status::invalid_argument(format!(
                "threads must be in 1..=4096 (got {})",
                req.threads
            )));
        }
        let id = format!("w{}-{:x}", self.next_worker, self.epoch & 0xff_ffff_ffff);
        self.next_worker += 1;
        let name: String = req.name.chars().take(128).collect();
        tracing::info!(worker = %id, name = %name, threads = req.threads, "worker registered");
        self.workers.insert(
            id.clone(),
            WorkerInfo {
                serial: self.next_worker - 1,
                name,
                threads: req.threads,
                last_seen: Instant::now(),
                leases: BTreeSet::new(),
                owed: Vec::new(),
            },
        );
        Ok(v1::RegisterReply {
            worker_id: id,
            lease_ms: self.cfg.lease.as_millis() as u32,
            poll_ms: self.cfg.poll.as_millis() as u32,
            coordinator_id: self.instance.clone(),
        })
    }

    fn known_worker(&mut self, id: &str) -> Result<(), Status> {
        match self.workers.get_mut(id) {
            Some(w) => {
                w.last_seen = Instant::now();
                Ok(())
            }
            None => Err(Status::not_found(format!(
                "unknown worker '{id}'; register again"
            ))),
        }
    }

    /// Checks every report against the state before any of them changes it; returns each
    /// report's outcomes as checked (none for a finished job's).
    fn validate_reports(
        &self,
        reports: &[v1::TileReport],
    ) -> Result<Vec<Vec<salient_grid::Outcome>>, Status> {
        let mut checked_all = Vec::with_capacity(reports.len());
        for r in reports {
            let lease = r
                .lease
                .as_ref()
                .ok_or_else(|| Status::invalid_argument("report.lease is required"))?;
            let Some(job) = self.jobs.get(&lease.job) else {
                if self.store.job(lease.job).map_err(store_err)?.is_some() {
                    checked_all.push(Vec::new());
                    continue; // a finished job: answered, no effect
                }
                return Err(Status::invalid_argument(format!(
                    "report.lease.job {} is not a job",
                    lease.job
                )));
            };
            let run = job.runs.get(lease.run as usize).ok_or_else(|| {
                Status::invalid_argument(format!(
                    "report.lease.run {} out of range 0..{}",
                    lease.run,
                    job.runs.len()
                ))
            })?;
            let tile = run.tiles.get(lease.tile as usize).ok_or_else(|| {
                Status::invalid_argument(format!(
                    "report.lease.tile {} out of range 0..{}",
                    lease.tile,
                    run.tiles.len()
                ))
            })?;
            if lease.attempt == 0 || lease.attempt > tile.attempt {
                return Err(Status::invalid_argument(format!(
                    "report.lease.attempt {} was never issued for {} (latest {})",
                    lease.attempt, lease, tile.attempt
                )));
            }
            let mut checked_report = Vec::with_capacity(r.outcomes.len());
            for o in &r.outcomes {
                let checked = outcome_from_wire(o, &run.grid, run.expected)
                    .map_err(Status::invalid_argument)?;
                if run.grid.tile_of(checked.cell) != Some(lease.tile as usize) {
                    return Err(Status::invalid_argument(format!(
                        "outcome.cell {} is not in tile {}",
                        o.cell, lease.tile
                    )));
                }
                checked_report.push(checked);
            }
            checked_all.push(checked_report);
        }
        Ok(checked_all)
    }

    fn apply_reports(
        &mut self,
        worker: &str,
        reports: &[v1::TileReport],
        out: &mut Replies,
    ) -> Result<(), Status> {
        let checked_all = self.validate_reports(reports)?;
        for (r, checked) in reports.iter().zip(checked_all) {
            let lease = r.lease.expect("validated");
            let key = lease.key();
            let Some(job) = self.jobs.get_mut(&lease.job) else {
                out.acknowledged.push(lease);
                continue;
            };
            let run_index = lease.run as usize;
            let run = &mut job.runs[run_index];
            let tile = &mut run.tiles[lease.tile as usize];
            if lease.attempt != tile.valid || job.state.is_terminal() {
                if lease.attempt != tile.valid {
                    job.stale_reports += 1;
                    run.extra_dropped_orbits += r.outcomes.len() as u64;
                    let steps = r
                        .outcomes
                        .iter()
                        .fold(0u64, |a, o| a.saturating_add(o.steps));
                    run.extra_dropped_steps = run.extra_dropped_steps.saturating_add(steps);
                    self.store
                        .add_counter(job.id, "stale_reports", 1)
                        .map_err(store_err)?;
                    self.store
                        .add_counter(
                            job.id,
                            &counter(run_index, "extra_dropped_orbits"),
                            r.outcomes.len() as u64,
                        )
                        .map_err(store_err)?;
                    self.store
                        .add_counter(job.id, &counter(run_index, "extra_dropped_steps"), steps)
                        .map_err(store_err)?;
                    tracing::debug!(%lease, worker, "stale report dropped");
                    out.stale.push(lease);
                } else {
                    out.acknowledged.push(lease);
                }
                continue;
            }
            // Only outcomes for cells without one change anything; repeats are answered OK.
            let mut seen = HashSet::new();
            let mut brought = false;
            let fresh: Vec<(&v1::Outcome, Bytes, salient_grid::Outcome)> = r
                .outcomes
                .iter()
                .zip(checked)
                .filter(|(o, _)| !run.stored[o.cell as usize] && seen.insert(o.cell))
                .map(|(o, checked)| (o, Bytes::from(o.encode_to_vec()), checked))
                .collect();
            if !fresh.is_empty() {
                brought = true;
                self.store
                    .write(Write::Report {
                        job: lease.job,
                        run: lease.run,
                        tile: lease.tile,
                        attempt: lease.attempt,
                        worker: worker.to_string(),
                        cpu_ns: r.cpu_ns,
                        outcomes: fresh.iter().map(|(o, b, _)| (o.cell, b.clone())).collect(),
                    })
                    .map_err(store_err)?;
                run.cpu_ns = run.cpu_ns.saturating_add(r.cpu_ns);
                let serial = self.workers.get(worker).map_or(u64::MAX, |w| w.serial);
                for (_, encoded, o) in fresh {
                    run.stored[o.cell as usize] = true;
                    run.offer(serial, encoded, o);
                }
            }
            let holds = |l: &ActiveLease| l.worker == worker;
            if r.finished
                && run.tiles[lease.tile as usize]
                    .lease
                    .as_ref()
                    .is_some_and(holds)
            {
                run.end_lease(lease.tile as usize);
                if run.ledger.mode() == salient_grid::Mode::FastPss {
                    let workers = &self.workers;
                    run.note_finished(key, worker, brought, |id| {
                        workers.get(id).map_or_else(String::new, |w| w.name.clone())
                    });
                }
                // Counted once: a repeat of the finishing report finds the lease gone.
                if r.abandoned_orbits > 0 {
                    run.extra_dropped_orbits =
                        run.extra_dropped_orbits.saturating_add(r.abandoned_orbits);
                    run.extra_dropped_steps =
                        run.extra_dropped_steps.saturating_add(r.abandoned_steps);
                    self.store
                        .add_counter(
                            job.id,
                            &counter(run_index, "extra_dropped_orbits"),
                            r.abandoned_orbits,
                        )
                        .map_err(store_err)?;
                    self.store
                        .add_counter(
                            job.id,
                            &counter(run_index, "extra_dropped_steps"),
                            r.abandoned_steps,
                        )
                        .map_err(store_err)?;
                }
                if let Some(w) = self.workers.get_mut(worker) {
                    w.leases.remove(&key);
                }
            }
            out.acknowledged.push(lease);
            self.finish_runs(key.0)?;
        }
        Ok(())
    }

    /// Marks runs whose ledger is done, and the job when all are.
    fn finish_runs(&mut self, id: u64) -> Result<(), Status> {
        let Some(job) = self.jobs.get_mut(&id) else {
            return Ok(());
        };
        let mut finished = Vec::new();
        for (index, run) in job.runs.iter_mut().enumerate() {
            if run.done || !run.ledger.done() {
                continue;
            }
            finished.push(index);
            let wall_s = run.elapsed();
            self.store
                .add_counter(id, &counter(index, "wall_ms"), (wall_s * 1e3) as u64)
                .map_err(store_err)?;
            run.wall_s = wall_s;
            run.done = true;
            run.relay = Vec::new();
            run.unrelayed = HashMap::new();
            // Speculative leases of a finished run are no longer needed.
            for (t, tile) in run.tiles.iter_mut().enumerate() {
                if let Some(l) = tile.lease.take() {
                    if let Some(w) = self.workers.get_mut(&l.worker) {
                        w.leases.remove(&(id, index as u32, t as u32));
                    }
                }
            }
            let c = salient_grid::Counts::of(&run.grid, &run.ledger);
            let (reg, st, ch) = c.percent();
            tracing::info!(
                job = id,
                run = index,
                wall_s = round2(run.wall_s),
                orbits = run.ledger.committed.len(),
                // As run.json's orbits_dropped: the ledger's and those of stale reports.
                dropped = run.ledger.dropped + run.extra_dropped_orbits,
                regular = round2(reg),
                sticky = round2(st),
                chaotic = round2(ch),
                crossings = run.crossings_said,
                "run done"
            );
        }
        for from in finished {
            hand_forecast(&job.spec, &mut job.runs, from);
        }
        if job.runs.iter().all(|r| r.done) && !job.state.is_terminal() {
            job.state = JobState::Done;
            self.store
                .set_job_state(id, JobState::Done, now_ms(), None)
                .map_err(store_err)?;
            tracing::info!(job = id, name = %job.name, "job done");
        }
        Ok(())
    }

    /// The next tile with cells that need an orbit for `worker`, FIFO over jobs and in order
    /// over runs and tiles (from each run's frontier on, a bounded window), and those cells.
    /// A stalled run's tiles that this worker returned empty go to others while there are.
    /// The search starts past tile `after` (the one a poll just leased: nothing changed before
    /// it since).
    fn next_tile(&mut self, worker: &str, after: Option<TileKey>) -> Option<(TileKey, Vec<u32>)> {
        let workers = self.workers.len();
        let registered = &self.workers;
        let from = after.map_or((0, 0, 0), |(j, r, t)| (j, r, t + 1));
        for job in self.jobs.range_mut(from.0..).map(|(_, job)| job) {
            if job.state.is_terminal() {
                continue;
            }
            for (r, run) in job.runs.iter_mut().enumerate() {
                let resumed = (job.id, r as u32) == (from.0, from.1);
                if run.done || (job.id == from.0 && (r as u32) < from.1) {
                    continue;
                }
                // Tiles are runs of the canonical order: the frontier's is this one.
                let size = run.grid.tile_size();
                let first = run.ledger.frontier() / size;
                // Speculation past the frontier is bounded (see WINDOW_CELLS_MIN): further
                // cells are likely to be labelled meanwhile, and scanning the whole grid on
                // every poll of an idle worker costs the coordinator more CPU than the leases
                // themselves. With a forecast, the cells it does not hold back are worth taking
                // from anywhere. (Later runs of the job are scanned next: their frontier is
                // certain work.)
                let ahead = (WINDOW_CELLS_PER_WORKER * workers.max(1)).max(WINDOW_CELLS_MIN);
                let last = if run.forecast.is_some() {
                    run.tiles.len()
                } else {
                    (first + 1 + ahead.div_ceil(size)).min(run.tiles.len())
                };
                let reopenings = run.ledger.reopenings();
                let start = if resumed {
                    first.max(from.2 as usize)
                } else {
                    first
                };
                for t in start..last {
                    let tile = &run.tiles[t];
                    if tile.lease.is_some()
                        || tile.drained_at == Some(reopenings)
                        || run.stall.shuns(t as u32, worker, registered.keys())
                    {
                        continue;
                    }
                    let (cells, deferred) = run.wanted(t);
                    if !cells.is_empty() {
                        return Some(((job.id, r as u32, t as u32), cells));
                    }
                    // Deferred cells come back as the frontier passes their labellers.
                    if !deferred {
                        run.tiles[t].drained_at = Some(reopenings);
                    }
                }
            }
        }
        None
    }

    fn lease(&mut self, worker: &str, key: TileKey, cells: Vec<u32>) -> Result<v1::Lease, Status> {
        let job = self.jobs.get_mut(&key.0).expect("leasable job");
        let run = &mut job.runs[key.1 as usize];
        let tile = &mut run.tiles[key.2 as usize];
        let attempt = tile.attempt + 1;
        self.store
            .record_attempt(key.0, key.1, key.2, attempt, worker)
            .map_err(store_err)?;
        if job.state == JobState::Queued {
            job.state = JobState::Running;
            self.store
                .set_job_state(key.0, JobState::Running, now_ms(), None)
                .map_err(store_err)?;
        }
        run.started.get_or_insert_with(Instant::now);
        tile.attempt = attempt;
        tile.valid = attempt;
        tile.restored = false;
        tile.lapsed = false;
        tile.lease = Some(ActiveLease {
            worker: worker.to_string(),
            deadline: Instant::now() + self.cfg.lease,
            cells: cells.clone(),
            skipped: HashSet::new(),
            running: HashSet::new(),
        });
        if let Some(w) = self.workers.get_mut(worker) {
            w.leases.insert(key);
        }
        tracing::debug!(
            job = key.0,
            run = key.1,
            tile = key.2,
            attempt,
            worker,
            cells = cells.len(),
            "leased"
        );
        Ok(v1::Lease {
            lease: Some(tile_ref(key, attempt)),
            spec_json: job.spec_json.clone(),
            cells,
        })
    }

    /// Renews the leases a worker names; returns those it must stop. A lease the coordinator
    /// lost (after a restart) is adopted again when it is still the tile's latest attempt.
    fn renew(&mut self, worker: &str, held: &[v1::TileRef]) -> Vec<v1::TileRef> {
        let mut revoked = Vec::new();
        let deadline = Instant::now() + self.cfg.lease;
        for h in held {
            let key = h.key();
            let tile = self
                .jobs
                .get_mut(&h.job)
                .filter(|j| !j.state.is_terminal())
                .and_then(|j| j.runs.get_mut(h.run as usize))
                .filter(|r| !r.done)
                .and_then(|r| r.tiles.get_mut(h.tile as usize));
            let Some(tile) = tile else {
                revoked.push(*h);
                continue;
            };
            match &mut tile.lease {
                Some(l) if l.worker == worker && h.attempt == tile.valid => l.deadline = deadline,
                None if h.attempt > 0
                    && ((tile.lapsed && h.attempt == tile.valid)
                        || (tile.restored
                            && (h.attempt == tile.valid || h.attempt == tile.attempt))) =>
                {
                    tile.valid = h.attempt;
                    tile.restored = false;
                    tile.lapsed = false;
                    tile.lease = Some(ActiveLease {
                        worker: worker.to_string(),
                        deadline,
                        cells: Vec::new(),
                        skipped: HashSet::new(),
                        running: HashSet::new(),
                    });
                    if let Some(w) = self.workers.get_mut(worker) {
                        w.leases.insert(key);
                    }
                }
                _ => revoked.push(*h),
            }
        }
        // A worker names every lease it holds: one it does not name never reached it (a lost
        // reply), so the tile goes back now instead of after the lease period.
        let named: HashSet<TileKey> = held.iter().map(|h| h.key()).collect();
        let lost: Vec<TileKey> = self
            .workers
            .get(worker)
            .map(|w| {
                w.leases
                    .iter()
                    .filter(|k| !named.contains(k))
                    .copied()
                    .collect()
            })
            .unwrap_or_default();
        for key in lost {
            if let Some(run) = self
                .jobs
                .get_mut(&key.0)
                .and_then(|j| j.runs.get_mut(key.1 as usize))
            {
                let tile = run.tiles.get(key.2 as usize);
                if tile
                    .and_then(|t| t.lease.as_ref())
                    .is_some_and(|l| l.worker == worker)
                {
                    tracing::debug!(
                        job = key.0,
                        run = key.1,
                        tile = key.2,
                        worker,
                        "lease never reached its worker; released"
                    );
                    run.end_lease(key.2 as usize);
                }
            }
            if let Some(w) = self.workers.get_mut(worker) {
                w.leases.remove(&key);
            }
        }
        revoked
    }

    /// Outcomes of the fast-PSS runs the worker holds leases of that other workers reported
    /// (its own too where its mark asks for them), from the marks the worker sent on, up to
    /// [`RELAY_BYTES`].
    fn relays(&self, worker: &str, marks: &[v1::RelayMark]) -> Vec<v1::Relay> {
        let Some(w) = self.workers.get(worker) else {
            return Vec::new();
        };
        let runs: BTreeSet<(u64, u32)> = w.leases.iter().map(|k| (k.0, k.1)).collect();
        let mut out = Vec::new();
        let mut bytes = 0;
        for key in runs {
            let Some(run) = self
                .jobs
                .get(&key.0)
                .and_then(|j| j.runs.get(key.1 as usize))
            else {
                continue;
            };
            let (mark, own) = marks
                .iter()
                .find(|m| (m.job, m.run) == key)
                .map_or((0, false), |m| (m.next, m.own));
            // A mark past the end is not this process's (a worker forgets its marks when it
            // registers again): from the start.
            let mut next = usize::try_from(mark)
                .ok()
                .filter(|&m| m <= run.relay.len())
                .unwrap_or(0);
            let mut outcomes = Vec::new();
            while next < run.relay.len() && bytes < RELAY_BYTES {
                let (from, o) = &run.relay[next];
                next += 1;
                if *from != w.serial || own {
                    bytes += o.len();
                    outcomes.push(o.clone());
                }
            }
            if next as u64 != mark {
                out.push(v1::Relay {
                    job: key.0,
                    run: key.1,
                    outcomes,
                    next: next as u64,
                });
            }
        }
        out
    }

    /// Cells of the worker's leases that no longer need an orbit, not yet told.
    fn skips(&mut self, worker: &str) -> Vec<v1::Skip> {
        let keys: Vec<TileKey> = self
            .workers
            .get(worker)
            .map(|w| w.leases.iter().copied().collect())
            .unwrap_or_default();
        let mut out = Vec::new();
        for key in keys {
            let Some(run) = self
                .jobs
                .get_mut(&key.0)
                .and_then(|j| j.runs.get_mut(key.1 as usize))
            else {
                continue;
            };
            let (ledger, tile) = (&run.ledger, &mut run.tiles[key.2 as usize]);
            let Some(lease) = tile.lease.as_mut() else {
                continue;
            };
            let cells: Vec<u32> = lease
                .cells
                .iter()
                .copied()
                .filter(|&c| {
                    !lease.skipped.contains(&c) && !ledger.wants(c) && !ledger.has_outcome(c)
                })
                .collect();
            if !cells.is_empty() {
                lease.skipped.extend(&cells);
                out.push(v1::Skip {
                    lease: Some(tile_ref(key, tile.valid)),
                    cells,
                });
            }
        }
        out
    }

    /// Fast PSS: the cells one slot of a worker with `threads` threads takes in a poll, for
    /// the run of lease `key` ([`Config::lease_cells_per_thread`]); `None` in full mode (a
    /// slot takes one tile).
    fn batch_cells(&self, key: TileKey, threads: usize) -> Option<usize> {
        let job = &self.jobs[&key.0];
        if job.spec.mode(key.1 as usize) != salient_grid::Mode::FastPss {
            return None;
        }
        let mut per_thread = self.cfg.lease_cells_per_thread;
        if let Some(orbits) = job.runs[key.1 as usize].adaptive_orbits_per_thread {
            per_thread = (per_thread * orbits / ADAPTIVE_LEASE_SHARE).max(1);
        }
        Some((threads * per_thread).max(1))
    }

    /// Answers a poll: applies its reports, renews its leases, notes its orbits' crossings
    /// and, unless the worker drains, grants leases for its free slots.
    pub fn poll(&mut self, req: &v1::PollRequest) -> Result<v1::PollReply, Status> {
        self.known_worker(&req.worker_id)?;
        let worker = req.worker_id.as_str();
        let mut replies = Replies::default();
        self.apply_reports(worker, &req.reports, &mut replies)?;
        let revoked = self.renew(worker, &req.held);
        for x in &req.crossings {
            let Some(lease) = &x.lease else { continue };
            if let Some(run) = self
                .jobs
                .get_mut(&lease.job)
                .filter(|j| !j.state.is_terminal())
                .and_then(|j| j.runs.get_mut(lease.run as usize))
            {
                run.progress(worker, lease, x);
            }
        }
        let mut leases = Vec::new();
        if !req.draining {
            let threads = self.workers.get(worker).map_or(1, |w| w.threads as usize);
            let mut after = None;
            for _ in 0..req.free_slots.min(8) {
                // Fast PSS: a slot takes the wanted cells of the units within a worker's batch
                // of the canonical order from the first unit it finds (a batch's worth of
                // cells at most), each lease judged on the latest claims, so speculation stays
                // within about one batch per worker.
                let mut slot: Option<(TileKey, usize, usize)> = None;
                while let Some((key, mut cells)) = self.next_tile(worker, after) {
                    // The slot's first unit, the units it may span, the cells it may still take.
                    let (first, span, left) = *slot.get_or_insert_with(|| {
                        let batch = self.batch_cells(key, threads).unwrap_or(usize::MAX);
                        (key, batch.div_ceil(FAST_PSS_LEASE_CELLS), batch)
                    });
                    let beyond = (first.2 as usize).saturating_add(span);
                    if (key.0, key.1) != (first.0, first.1) || key.2 as usize >= beyond {
                        break;
                    }
                    after = Some(key);
                    cells.truncate(left);
                    let left = left - cells.len();
                    slot = Some((first, span, left));
                    let full =
                        self.jobs[&key.0].spec.mode(key.1 as usize) == salient_grid::Mode::Full;
                    leases.push(self.lease(worker, key, cells)?);
                    if full || left == 0 || leases.len() >= MAX_POLL_LEASES {
                        break;
                    }
                }
            }
        }
        let (acknowledged, stale) = self.owed_answers(worker, replies);
        Ok(v1::PollReply {
            leases,
            revoked,
            skips: self.skips(worker),
            acknowledged,
            stale,
            relays: self.relays(worker, &req.relayed),
        })
    }

    /// The answers a poll's reply may carry. The event loop sends a poll's reply before the
    /// group it belongs to is committed, so that a worker waiting for cells does not wait for
    /// an fsync; the answers to the reports it carried are therefore owed, each until its
    /// group is durable, and go out with a later reply to the same worker (in the order the
    /// reports came, which the worker relies on). Outside a group the writes are durable
    /// already and the answers go at once.
    fn owed_answers(&mut self, worker: &str, now: Replies) -> (Vec<v1::TileRef>, Vec<v1::TileRef>) {
        let group = self.store.pending_group();
        let durable = self.store.durable_group();
        let Some(w) = self.workers.get_mut(worker) else {
            return (now.acknowledged, now.stale);
        };
        w.owed
            .extend(now.acknowledged.into_iter().map(|l| (group, l, false)));
        w.owed
            .extend(now.stale.into_iter().map(|l| (group, l, true)));
        let due = w.owed.iter().take_while(|&&(g, _, _)| g <= durable).count();
        let (mut acknowledged, mut stale) = (Vec::new(), Vec::new());
        for (_, lease, is_stale) in w.owed.drain(..due) {
            if is_stale {
                stale.push(lease);
            } else {
                acknowledged.push(lease);
            }
        }
        (acknowledged, stale)
    }

    /// Applies a worker's reports; the reply says which leases were acknowledged and which stale.
    pub fn report(&mut self, req: &v1::ReportRequest) -> Result<v1::ReportReply, Status> {
        self.known_worker(&req.worker_id)?;
        let mut replies = Replies::default();
        self.apply_reports(&req.worker_id, &req.reports, &mut replies)?;
        Ok(v1::ReportReply {
            acknowledged: replies.acknowledged,
            stale: replies.stale,
            skips: self.skips(&req.worker_id),
        })
    }

    /// Renews the leases a worker names; the reply lists those it must stop.
    pub fn renew_only(&mut self, req: &v1::RenewRequest) -> Result<v1::RenewReply, Status> {
        self.known_worker(&req.worker_id)?;
        Ok(v1::RenewReply {
            revoked: self.renew(&req.worker_id, &req.held),
        })
    }

    /// Releases the worker's leases (the tiles go to others) and forgets it.
    pub fn deregister(&mut self, req: &v1::DeregisterRequest) -> Result<(), Status> {
        self.known_worker(&req.worker_id)?;
        self.drop_worker(&req.worker_id);
        tracing::info!(worker = %req.worker_id, released = req.released.len(), "worker left");
        Ok(())
    }

    fn drop_worker(&mut self, id: &str) {
        let Some(w) = self.workers.remove(id) else {
            return;
        };
        for key in w.leases {
            if let Some(run) = self
                .jobs
                .get_mut(&key.0)
                .and_then(|j| j.runs.get_mut(key.1 as usize))
            {
                let t = key.2 as usize;
                let held = run.tiles.get(t).and_then(|tile| tile.lease.as_ref());
                if held.is_some_and(|l| l.worker == id) {
                    run.end_lease(t);
                    // A worker taken for lost that comes back gets it again.
                    run.tiles[t].lapsed = true;
                }
            }
        }
    }

    /// Lapses expired leases and forgets workers silent for [`Config::worker_timeout`], so
    /// their leases go to others.
    ///
    /// Silence is measured in time this process ran: when ticks stop for a while (the process
    /// was stopped, its host suspended, or the loop busy for long), nobody could be answered
    /// meanwhile, so the silence of workers and the age of leases count again from now.
    pub fn tick(&mut self) {
        let now = Instant::now();
        let gap = now.duration_since(self.last_tick);
        self.last_tick = now;
        if gap > self.cfg.worker_timeout / 2 {
            tracing::warn!(
                paused_s = gap.as_secs_f64(),
                "the coordinator did not run for a while; worker silence counts from now"
            );
            for w in self.workers.values_mut() {
                w.last_seen = now;
            }
            for tile in self
                .jobs
                .values_mut()
                .flat_map(|j| j.runs.iter_mut())
                .flat_map(|r| r.tiles.iter_mut())
            {
                if let Some(l) = tile.lease.as_mut() {
                    l.deadline += gap;
                }
            }
        }
        for job in self.jobs.values_mut() {
            for (r, run) in job.runs.iter_mut().enumerate() {
                let lapsed: Vec<usize> = (0..run.tiles.len())
                    .filter(|&t| {
                        let lease = run.tiles[t].lease.as_ref();
                        lease.is_some_and(|l| l.deadline < now)
                    })
                    .collect();
                for t in lapsed {
                    let l = run.end_lease(t).expect("checked");
                    let tile = &mut run.tiles[t];
                    tile.lapsed = true;
                    tracing::warn!(job = job.id, run = r, tile = t, attempt = tile.attempt, worker = %l.worker, "lease lapsed");
                    if let Some(w) = self.workers.get_mut(&l.worker) {
                        w.leases.remove(&(job.id, r as u32, t as u32));
                    }
                }
            }
        }
        let silent: Vec<String> = self
            .workers
            .iter()
            .filter(|(_, w)| now.duration_since(w.last_seen) > self.cfg.worker_timeout)
            .map(|(id, _)| id.clone())
            .collect();
        for id in silent {
            let name = self
                .workers
                .get(&id)
                .map(|w| w.name.clone())
                .unwrap_or_default();
            let leases = self.workers.get(&id).map_or(0, |w| w.leases.len());
            tracing::warn!(worker = %id, name = %name, leases, "worker silent; taken for dead, its leases go to others");
            self.drop_worker(&id);
        }
    }

    /// Cancels a job and takes back its leases; returns the job's state.
    pub fn cancel(&mut self, id: u64) -> Result<String, Status> {
        let Some(job) = self.jobs.get_mut(&id) else {
            let row = self
                .store
                .job(id)
                .map_err(store_err)?
                .ok_or_else(|| Status::not_found(format!("no job {id}")))?;
            return Ok(row.state.as_str().to_string());
        };
        if !job.state.is_terminal() {
            job.state = JobState::Cancelled;
            self.store
                .set_job_state(id, JobState::Cancelled, now_ms(), None)
                .map_err(store_err)?;
            tracing::info!(job = id, "cancelled");
        }
        let keys: Vec<(String, TileKey)> = job
            .runs
            .iter_mut()
            .enumerate()
            .flat_map(|(r, run)| {
                run.tiles
                    .iter_mut()
                    .enumerate()
                    .filter_map(move |(t, tile)| {
                        tile.lease
                            .take()
                            .map(|l| (l.worker, (id, r as u32, t as u32)))
                    })
            })
            .collect();
        for (w, key) in keys {
            if let Some(w) = self.workers.get_mut(&w) {
                w.leases.remove(&key);
            }
        }
        Ok(job.state.as_str().to_string())
    }

    /// Where a job's runs stand together (a simulation's timeline samples it): `None` for a
    /// job not held in memory.
    pub fn progress(&self, id: u64) -> Option<Progress> {
        let job = self.jobs.get(&id)?;
        let mut p = Progress::default();
        for run in &job.runs {
            p.committed_orbits += run.ledger.committed.len();
            p.resolved_cells += run.ledger.resolved();
            if run.ledger.mode() == salient_grid::Mode::FastPss && !run.done {
                p.wanted_cells += run.grid.canonical()[run.ledger.frontier()..]
                    .iter()
                    .filter(|&&c| run.ledger.wants(c))
                    .count();
            }
            p.leased_cells += run
                .tiles
                .iter()
                .filter_map(|t| t.lease.as_ref())
                .map(|l| l.cells.len())
                .sum::<usize>();
        }
        Some(p)
    }

    /// The cell the commits of the job's first unfinished fast-PSS run wait for, when it needs
    /// its own orbit and has no outcome yet (`None` otherwise: the frontier waits for nothing
    /// a lease could give, or the run is done).
    pub fn frontier_cell(&self, id: u64) -> Option<FrontierCell<'_>> {
        let run = self
            .jobs
            .get(&id)?
            .runs
            .iter()
            .find(|r| !r.done && r.ledger.mode() == salient_grid::Mode::FastPss)?;
        let cell = *run.grid.canonical().get(run.ledger.frontier())?;
        if !run.ledger.wants(cell) {
            return None;
        }
        let tile = &run.tiles[run.grid.tile_of(cell)?];
        Some(match &tile.lease {
            None => FrontierCell::Unleased(cell),
            Some(l) if l.cells.contains(&cell) && !l.skipped.contains(&cell) => {
                FrontierCell::Leased {
                    cell,
                    worker: &l.worker,
                }
            }
            Some(_) => FrontierCell::Stranded(cell),
        })
    }

    /// Number of workers registered.
    pub fn workers(&self) -> u32 {
        self.workers.len() as u32
    }

    fn job_status(&self, job: &Job) -> v1::JobStatus {
        let mut runs = Vec::new();
        let (mut resolved, mut compatible, mut rate) = (0u64, 0u64, 0.0);
        for (i, run) in job.runs.iter().enumerate() {
            let spec = &job.spec.runs[i];
            let c = run.grid.compatible_count() as u64;
            let r = run.ledger.resolved() as u64;
            let orbits = run.ledger.committed.len() as u64 + run.ledger.dropped;
            let wall = run.elapsed();
            let orbits_per_s = if wall > 0.0 {
                orbits as f64 / wall
            } else {
                0.0
            };
            let eta_s =
                (wall > 0.0 && r > 0 && !run.done).then(|| (c - r) as f64 * wall / r as f64);
            if !run.done && run.started.is_some() {
                rate += orbits_per_s;
            }
            resolved += r;
            compatible += c;
            runs.push(v1::RunProgress {
                run: i as u32,
                method: spec.method.name(),
                tau: spec.tau,
                t_final: spec.t_final,
                delta: spec.delta,
                compatible: c,
                resolved: r,
                orbits,
                dropped: run.ledger.dropped + run.extra_dropped_orbits,
                orbits_per_s,
                eta_s,
                done: run.done,
                wall_s: wall,
            });
        }
        v1::JobStatus {
            job: job.id,
            name: job.name.clone(),
            state: job.state.as_str().into(),
            runs_total: job.runs.len() as u32,
            runs_done: job.runs.iter().filter(|r| r.done).count() as u32,
            resolved_percent: 100.0 * resolved as f64 / compatible.max(1) as f64,
            orbits_per_s: rate,
            workers: self.workers.len() as u32,
            runs,
            error: job.error.clone().unwrap_or_default(),
            stale_reports: job.stale_reports,
        }
    }

    /// Status of one job (loaded from the store if finished) or of every job.
    pub fn status(&self, id: Option<u64>) -> Result<v1::StatusReply, Status> {
        let one = |id: u64| -> Result<v1::JobStatus, Status> {
            if let Some(j) = self.jobs.get(&id) {
                return Ok(self.job_status(j));
            }
            if let Some(st) = self.finished.borrow().get(&id) {
                return Ok(v1::JobStatus {
                    workers: self.workers(),
                    ..st.clone()
                });
            }
            let st = self.job_status(&self.load_job(id)?);
            if is_terminal_state(&st.state) {
                self.finished.borrow_mut().insert(id, st.clone());
            }
            Ok(st)
        };
        let jobs = match id {
            Some(id) => vec![one(id)?],
            None => {
                let mut out = Vec::new();
                for row in self.store.jobs().map_err(store_err)? {
                    out.push(one(row.id)?);
                }
                out
            }
        };
        Ok(v1::StatusReply {
            jobs,
            workers: self.workers(),
        })
    }

    fn with_job<T>(&self, id: u64, f: impl FnOnce(&Job) -> T) -> Result<T, Status> {
        match self.jobs.get(&id) {
            Some(j) => Ok(f(j)),
            None => Ok(f(&self.load_job(id)?)),
        }
    }

    /// The results stream's parts: header, then per run its totals and committed outcomes.
    pub fn results(&self, id: u64, batch: usize) -> Result<Vec<v1::ResultsChunk>, Status> {
        use v1::results_chunk::Part;
        self.with_job(id, |job| {
            let mut parts = vec![Part::Header(v1::ResultsHeader {
                job: id,
                spec_json: job.spec_json.clone(),
                state: job.state.as_str().into(),
            })];
            for (i, run) in job.runs.iter().enumerate() {
                parts.push(Part::Run(v1::RunHeader {
                    run: i as u32,
                    orbits_dropped: run.ledger.dropped + run.extra_dropped_orbits,
                    steps_dropped: run.ledger.dropped_steps + run.extra_dropped_steps,
                    cpu_s: run.cpu_ns as f64 / 1e9,
                    wall_s: run.elapsed(),
                    outcomes: run.ledger.committed.len() as u64,
                }));
                for chunk in run.ledger.committed.chunks(batch.max(1)) {
                    parts.push(Part::Outcomes(v1::OutcomeBatch {
                        run: i as u32,
                        outcomes: chunk.iter().map(v1::Outcome::from).collect(),
                    }));
                }
            }
            parts
                .into_iter()
                .map(|p| v1::ResultsChunk { part: Some(p) })
                .collect()
        })
    }

    /// Whether the job is finished (done, cancelled or failed); unknown jobs are an error.
    pub fn is_finished(&self, id: u64) -> Result<bool, Status> {
        match self.jobs.get(&id) {
            Some(j) => Ok(j.state.is_terminal()),
            None => self
                .store
                .job(id)
                .map_err(store_err)?
                .map(|row| row.state.is_terminal())
                .ok_or_else(|| Status::not_found(format!("no job {id}"))),
        }
    }

    /// Status lines for the periodic progress log.
    pub fn log_progress(&self) {
        for job in self.jobs.values().filter(|j| j.state == JobState::Running) {
            let s = self.job_status(job);
            for r in s.runs.iter().filter(|r| !r.done && r.orbits > 0) {
                tracing::info!(
                    job = job.id,
                    run = r.run,
                    method = %r.method,
                    tau = r.tau,
                    t_final = r.t_final,
                    resolved = r.resolved,
                    compatible = r.compatible,
                    orbits_per_s = r.orbits_per_s.round(),
                    eta_s = round2(r.eta_s.unwrap_or(f64::NAN)),
                    workers = s.workers,
                    worker_threads = self.workers.values().map(|w| w.threads).sum::<u32>(),
                    dropped = r.dropped,
                    "progress"
                );
            }
        }
    }

    /// Starts a group of calls whose store writes share one transaction (one fsync).
    pub fn begin_group(&mut self) {
        self.store.begin_group();
    }

    /// Ends the group: the store thread commits its writes and then sends the answers in
    /// `then`, while this thread goes on (a store error there stops the process before any
    /// of them goes out).
    pub fn commit_group(&mut self, then: Vec<Deferred>) {
        self.store.commit_group(then);
    }

    /// Waits until every write so far is committed.
    pub fn sync_store(&self) {
        self.store.sync();
    }

    /// Forgets finished jobs' in-memory state (the store keeps them).
    pub fn retire_finished(&mut self) {
        let done: Vec<u64> = self
            .jobs
            .values()
            .filter(|j| j.state.is_terminal())
            .map(|j| j.id)
            .collect();
        for id in done {
            let st = self.job_status(&self.jobs[&id]);
            self.finished.borrow_mut().insert(id, st);
            self.jobs.remove(&id);
        }
    }
}

fn is_terminal_state(state: &str) -> bool {
    JobState::parse(state).is_some_and(|s| s.is_terminal())
}
