//! A worker's stream of leased cells ([`integrate_stream`]): lanes take the next leased cell
//! the claims let go, whatever lease it came in.

use super::{crossed_cells, drive_feed, initial_point, outcome, requests_for};
use super::{CellRun, Claims, LocalLedger};

use crate::geometry::Grid;
use crate::ledger::{Mode, Outcome};
use salient_core::orbit::OrbitResult;
use salient_core::section::{CellLattice, Crossing};
use salient_core::tangent_map::batch::{BatchFeed, Feed};

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
    /// Cells that running orbits crossed for the first time, as (entry, cell), for a source
    /// that tells others (a worker tells its coordinator, whose lease decisions they inform).
    fn crossed(&self, _first_crossings: &[(u64, u32)]) {}
}

/// First crossings a driver keeps before it hands them to [`CellSource::crossed`], and the
/// crossings it sees at most meanwhile (a few milliseconds of lanes): one call per crossing
/// would take the source's lock thousands of times per second per lane, and an orbit that
/// crosses few new cells must not hold them back for long. Every orbit's end hands them too.
const CROSSINGS_BATCH: usize = 256;
const CROSSINGS_HELD: usize = 4096;

/// Steps per orbit (t_final / τ) from which a stream tells its source what running orbits
/// cross. Shorter orbits end, and their outcomes tell the same, before a claim said on the way
/// could spare much; and they cross the section every few steps, so the bookkeeping costs
/// more than it saves (figures: docs/performance.md).
pub const TELL_CROSSINGS_FROM_STEPS: f64 = 1e6;

/// Whether a stream of `cell_run` tells its source what running orbits cross
/// ([`CellSource::crossed`]).
pub fn tells_crossings(cell_run: &CellRun) -> bool {
    cell_run.config.t_final / cell_run.config.tau >= TELL_CROSSINGS_FROM_STEPS
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
    rayon::broadcast(|_| {
        let mut feed = StreamFeed {
            grid,
            cell_run,
            checkpoints: &checkpoints,
            local,
            claims: local.claims(),
            source,
            insisted: Vec::new(),
            said_by: if tells_crossings(cell_run) {
                vec![u32::MAX; grid.cells()]
            } else {
                Vec::new()
            },
            fresh: Vec::new(),
            seen: 0,
        };
        drive_feed(grid, cell_run, mode, &requests, false, &mut feed);
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
    /// Per cell, the cell of the orbit that last said it crossed it: an orbit says each cell
    /// once unless another said it since (rare, and harmless). An array, because a crossing
    /// comes every few steps at large τ and a set per orbit cost a fifth of a lane's time
    /// (figures: docs/performance.md); 4 bytes a cell.
    said_by: Vec<u32>,
    /// First crossings not yet handed to the source.
    fresh: Vec<(u64, u32)>,
    /// Crossings seen since `fresh` was last handed over.
    seen: usize,
}

impl StreamFeed<'_> {
    /// Hands the first crossings kept to the source.
    fn flush_crossings(&mut self) {
        if !self.fresh.is_empty() {
            self.source.crossed(&self.fresh);
            self.fresh.clear();
        }
        self.seen = 0;
    }
}

impl<const N: usize> BatchFeed<N> for StreamFeed<'_> {
    fn next(&mut self, all_idle: bool) -> Feed<N> {
        let (claims, grid) = (self.claims, self.grid);
        // Dropped cells are left without an outcome: the coordinator leases them again if it
        // still needs them.
        let judge = |cell: u32| claims.stream_verdict(grid, cell);
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
    fn finished(&mut self, id: usize, r: OrbitResult<N>) {
        let cell = id as u32;
        self.claims.set_running(cell, false);
        self.insisted.retain(|&e| e != id);
        self.flush_crossings();
        let visited = crossed_cells(self.grid, &r.crossings);
        let o = outcome(self.cell_run, self.checkpoints, cell, &r, visited);
        self.local.offer(o.clone());
        self.source.ended(id as u64, Some(o), r.steps);
    }
    fn books_by_cell(&self) -> Option<CellLattice> {
        Some(self.grid.lattice())
    }
    fn on_crossing(&mut self, id: usize, c: &Crossing<N>) {
        if let Some(to) = self.grid.cell_of(c.q[1], c.p[1]) {
            // Asked first: the frontier's orbit claims what it crosses.
            let tell = !self.said_by.is_empty() && self.claims.worth_telling(id as u32, to);
            self.claims.stream_crossed(self.grid, id as u32, to);
            if tell
                && self
                    .said_by
                    .get(to as usize)
                    .is_some_and(|&s| s != id as u32)
            {
                self.said_by[to as usize] = id as u32;
                self.fresh.push((id as u64, to));
            }
            self.seen += 1;
            if self.fresh.len() >= CROSSINGS_BATCH
                || (self.seen >= CROSSINGS_HELD && !self.fresh.is_empty())
            {
                self.flush_crossings();
            }
        }
    }
    fn cancelled(&mut self, id: usize) -> bool {
        let insisted = self.insisted.contains(&id);
        self.claims.stream_cancels(self.grid, id as u32, insisted)
    }
    fn abandoned(&mut self, id: usize, steps: u64) {
        let cell = id as u32;
        self.claims.set_running(cell, false);
        self.insisted.retain(|&e| e != id);
        self.flush_crossings();
        self.claims.record_abandoned(steps);
        self.source.ended(id as u64, None, steps);
    }
}
