//! What a fast-PSS stream knows while its orbits run: [`Claims`] on cells (labelled, crossed
//! by the frontier orbit or by running orbits, told by the coordinator), and a worker's
//! [`LocalLedger`] that keeps them in step with the outcomes it has seen.

use super::Verdict;
use crate::geometry::Grid;
use crate::ledger::{Ledger, Mode, Outcome};
use crate::pages::owned;
use std::sync::atomic::{AtomicBool, AtomicU32, AtomicU64, AtomicUsize, Ordering};
use std::sync::Mutex;

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
    /// Per cell, whether a live pending outcome before it in canonical order crossed it: the
    /// ledger's [`Ledger::is_claimed`], mirrored at every [`Claims::sync`] so that running
    /// orbits can ask without the lock (the embedded engine only).
    pending_claimed: Vec<AtomicBool>,
    /// Bumped whenever an orbit stops running (finished or abandoned): only then can a cell
    /// that a search for work skipped become available, so an idle lane searches again only
    /// after a bump.
    pub(crate) stopped: AtomicU64,
    abandoned: AtomicU64,
    abandoned_steps: AtomicU64,
}

impl Claims {
    /// Claims of `grid` with none set, the frontier at canonical position 0.
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

    pub(crate) fn claimed_any(&self, cell: u32) -> bool {
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

    /// Whether `cell` is the ledger's frontier: its orbit is certain to commit.
    pub fn is_frontier(&self, cell: u32) -> bool {
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
    pub(crate) fn note_crossed(&self, grid: &Grid, from: u32, cell: u32) {
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
    pub(crate) fn claim_crossed(&self, cell: u32) {
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
    pub(crate) fn running_crosser(&self, grid: &Grid, cell: u32) -> Option<u32> {
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

    /// Whether the orbit of `cell` is probably wasted: a live pending outcome before it crossed
    /// it, or a running orbit before it did and that orbit is itself neither claimed nor crossed
    /// by an earlier running one, so it will very likely commit and label the cell. (If it
    /// does not, the cell is integrated again later: abandoning costs the steps done so far,
    /// running on costs the rest.)
    ///
    /// The pending outcomes matter because [`Claims::running_crosser`] knows only orbits that
    /// still run: once an orbit that crossed the cell has ended, only its pending outcome
    /// tells, and without it the cell's orbit would run to its end and be dropped (figures:
    /// docs/performance.md).
    pub(crate) fn probably_labelled(&self, grid: &Grid, cell: u32) -> bool {
        if self.is_pending_claimed(cell) {
            return true;
        }
        self.running_crosser(grid, cell).is_some_and(|from| {
            !self.claimed_any(from) && self.running_crosser(grid, from).is_none()
        })
    }

    /// Whether a live pending outcome before the cell in canonical order crossed it (see
    /// [`Claims::probably_labelled`]).
    pub(crate) fn is_pending_claimed(&self, cell: u32) -> bool {
        self.pending_claimed[cell as usize].load(Ordering::Relaxed) && !self.is_frontier(cell)
    }

    /// Whether the cell's orbit runs in some lane.
    pub(crate) fn is_running(&self, cell: u32) -> bool {
        self.running[cell as usize].load(Ordering::Relaxed)
    }

    /// Marks whether `cell`'s orbit runs in some lane.
    pub fn set_running(&self, cell: u32, running: bool) {
        self.running[cell as usize].store(running, Ordering::Relaxed);
        if !running {
            // Release, paired with the Acquire in `LedgerFeed::next`: a driver that sees the
            // new count also sees the cell stopped (`abandoned` stores without the lock).
            self.stopped.fetch_add(1, Ordering::Release);
        }
    }

    pub(crate) fn record_abandoned(&self, steps: u64) {
        self.abandoned.fetch_add(1, Ordering::Relaxed);
        self.abandoned_steps.fetch_add(steps, Ordering::Relaxed);
    }

    /// What a stream makes of waiting `cell`: dropped when it is claimed or its orbit runs
    /// (no outcome: the coordinator leases it again if it still needs it), deferred while a
    /// live pending outcome or a running orbit before it crossed it, else started.
    pub fn stream_verdict(&self, grid: &Grid, cell: u32) -> Verdict {
        if self.is_claimed(cell) || self.is_running(cell) {
            Verdict::Drop
        } else if self.is_pending_claimed(cell) || self.running_crosser(grid, cell).is_some() {
            Verdict::Later
        } else {
            Verdict::Go
        }
    }

    /// A stream's running orbit of cell `from` crossed `to`: claimed when `from` is the
    /// frontier, noted as a crosser otherwise.
    pub fn stream_crossed(&self, grid: &Grid, from: u32, to: u32) {
        if self.is_frontier(from) {
            self.claim_crossed(to);
        }
        self.note_crossed(grid, from, to);
    }

    /// Whether the crossing of `to` by the running orbit of `from` is worth telling the
    /// coordinator: `to` comes after `from` in canonical order (a claim on an earlier cell
    /// counts for nothing) and is not certain to be labelled already.
    pub fn worth_telling(&self, from: u32, to: u32) -> bool {
        !self.claimed[to as usize].load(Ordering::Relaxed)
            && self.position[from as usize] < self.position[to as usize]
    }

    /// Whether a stream abandons the running orbit of `cell`: once it is claimed, or, unless
    /// the source `insisted` on it (see [`super::Take::Insist`]), once it is probably labelled.
    pub fn stream_cancels(&self, grid: &Grid, cell: u32, insisted: bool) -> bool {
        self.is_claimed(cell) || (!insisted && self.probably_labelled(grid, cell))
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
/// at once, and orbits crossed by a live pending outcome are abandoned — instead of waiting for
/// the coordinator's skips. Full mode labels no crossed cell, so there it keeps only the
/// coordinator's claims.
pub struct LocalLedger {
    grid: Grid,
    ledger: Option<Mutex<Ledger>>,
    claims: Claims,
    offers: AtomicU64,
}

impl LocalLedger {
    /// The ledger of `grid` in `mode` (full mode keeps only the coordinator's claims).
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

    /// The grid of the run.
    pub fn grid(&self) -> &Grid {
        &self.grid
    }

    /// The claims the streams read.
    pub fn claims(&self) -> &Claims {
        &self.claims
    }
}
