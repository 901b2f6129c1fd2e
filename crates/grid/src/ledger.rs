//! The fast-PSS ledger: accepts orbit outcomes in any order and commits them in canonical
//! order, so the labels equal those of the sequential rule whatever the arrival order:
//!
//! walk compatible cells in canonical order; skip a labelled cell; otherwise integrate its
//! orbit and give its class to its own cell and to every still-unlabelled compatible cell its
//! upward crossings fall in (`full` mode: only its own cell).
//!
//! An outcome whose cell an earlier commit labelled is dropped and counted.

use crate::geometry::Grid;
use crate::pages::owned;
use salient_core::orbit::{Class, Status};
use std::collections::BTreeMap;

/// Whether visited cells are labelled too.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Mode {
    /// Fast PSS: an orbit labels its own cell and every still-unlabelled compatible cell its
    /// upward crossings fall in.
    FastPss,
    /// An orbit labels only its own cell: every compatible cell is integrated.
    Full,
}

/// The finite-time mLE, MEGNO and FLI of a full-mode orbit at its end
/// (`integration.indicators`).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct CellIndicators {
    /// Finite-time maximal Lyapunov exponent (1/t) ln‖w1(t)‖.
    pub mle: f64,
    /// MEGNO Y and its running mean ⟨Y⟩.
    pub megno: f64,
    /// ⟨Y⟩, the running mean of MEGNO.
    pub megno_mean: f64,
    /// Fast Lyapunov indicator.
    pub fli: f64,
}

/// What one orbit produced, as far as the grid is concerned.
#[derive(Clone, Debug, PartialEq)]
pub struct Outcome {
    /// The cell the orbit started from.
    pub cell: u32,
    /// The orbit's class (`None` for orbits that escaped or failed).
    pub class: Option<Class>,
    /// How the orbit ended.
    pub status: Status,
    /// The orbit's final SALI.
    pub sali: f64,
    /// Compatible cells its upward crossings fell in, sorted and deduplicated.
    pub visited: Vec<u32>,
    /// Integration steps taken.
    pub steps: u64,
    /// The time the orbit reached: t_final, or when it stopped (early stop, escape, …).
    pub t_end: f64,
    /// Classes at the run's checkpoints (full mode with checkpoints; empty otherwise).
    pub checkpoints: Vec<Option<Class>>,
    /// With `integration.indicators`, in full mode, for orbits with a class.
    pub indicators: Option<CellIndicators>,
}

/// The label a cell received.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Label {
    /// The class of the labelling orbit.
    pub class: Option<Class>,
    /// How the labelling orbit ended.
    pub status: Status,
    /// The labelling orbit's final SALI.
    pub sali: f64,
    /// The cell whose orbit labelled this one.
    pub source: u32,
    /// The time that orbit reached (its escape time for `escaped`).
    pub t_end: f64,
    /// The labelling orbit's indicators (as in [`Outcome::indicators`]).
    pub indicators: Option<CellIndicators>,
}

const COMPATIBLE: u8 = 1;
const LABELLED: u8 = 2;
/// The cell's own outcome waits in `pending`: the coordinator's lease search asks after every
/// cell of its window, and a flag answers without a map lookup.
const PENDING: u8 = 4;
/// An orbit of the cell is in progress elsewhere and said what it crossed so far
/// ([`Ledger::progress`]).
const RUNNING: u8 = 8;

/// Per cell, how many live pending outcomes before it in canonical order crossed it. A pending
/// outcome is live when no live pending outcome before it crossed its own cell: it is what the
/// sequential rule would commit if every outcome still missing labelled nothing, so its claims
/// are the likely labels, while those of an outcome that an earlier one labels are not (it will
/// be dropped and its claims with it). Counting only live claims keeps the cells those doomed
/// outcomes crossed wanted, so they are integrated alongside the rest instead of one after
/// another as the frontier drops their claimers (figures: docs/performance.md).
///
/// A count answers [`Ledger::is_claimed`], the only question asked of the claims, at one
/// increment and one decrement per visited cell (a list of claimers per cell costs an
/// allocation, a search and scattered reads, a large share of the coordinator's CPU).
#[derive(Clone, Debug)]
struct ClaimCounts {
    early: Vec<u32>,
    /// Cells whose [`Ledger::is_claimed`] may have changed since the last
    /// [`Ledger::drain_claim_changes`]; kept only after [`Ledger::track_claim_changes`].
    changes: Option<Vec<u32>>,
}

impl ClaimCounts {
    /// Makes (`add`) or takes back the claims of the pending outcome at canonical position
    /// `pos` that crossed `visited`: one rule for both, so that every claim made is released.
    /// Calls `flipped(cell, claimed)` for every cell whose claimed state changed.
    fn count(
        &mut self,
        position: &[u32],
        visited: &[u32],
        pos: usize,
        add: bool,
        mut flipped: impl FnMut(u32, bool),
    ) {
        for &v in visited {
            if (pos as u32) < position[v as usize] {
                let n = &mut self.early[v as usize];
                let was_claimed = *n != 0;
                if add {
                    *n += 1;
                } else {
                    *n -= 1;
                }
                if was_claimed != (*n != 0) {
                    if let Some(changes) = &mut self.changes {
                        changes.push(v);
                    }
                    flipped(v, !was_claimed);
                }
            }
        }
    }
}

/// An outcome waiting for the cells before it, and whether its claims count (see
/// [`ClaimCounts`]).
#[derive(Clone, Debug)]
struct Pending {
    outcome: Outcome,
    live: bool,
}

/// An orbit in progress and the cells it crossed so far: it claims them as a pending outcome
/// would (its outcome will visit them all), under the same liveness rule.
#[derive(Clone, Debug, Default)]
struct Partial {
    /// A cell said twice is counted twice, and released twice.
    visited: Vec<u32>,
    live: bool,
}

/// Who labelled each cell in a finished fast-PSS run ([`Ledger::forecast`]), as a forecast of
/// who will label it in a similar one: same grid, τ and t_final, another method. Integrators
/// that agree on the orbits agree on the labellers, the costly regular orbits foremost
/// (figures: docs/performance.md), so a run's lanes can leave alone the cells that an
/// earlier orbit, not yet committed, is forecast to label. A scheduling hint only: the ledger
/// alone decides the labels, so a wrong forecast costs time, never results.
#[derive(Clone, Debug, PartialEq)]
pub struct Forecast {
    /// Per cell, the canonical position of the orbit that labelled it; `u32::MAX` where no
    /// other orbit did (its own orbit, an incompatible cell, or a cell not yet labelled).
    labeller: Vec<u32>,
}

impl Forecast {
    /// Whether the cell's own orbit is probably wasted for now: the forecast names another orbit
    /// as its labeller, and that orbit may still need its own run (its position is not
    /// resolved, and no earlier orbit has labelled or claimed its cell, and its own outcome is
    /// not in). An orbit that labels a cell in a shorter run of the same grid crosses it again
    /// in a longer one, so the cell needs its own orbit only if its labeller turns out not to
    /// need one: the cell is released as soon as the ledger shows that, not when the frontier
    /// reaches the labeller. Never true of the frontier cell (its labeller would lie before
    /// it), so a scheduler that defers such cells still makes progress.
    pub fn defers(&self, cell: u32, ledger: &Ledger) -> bool {
        let Some(by) = self.labeller(cell) else {
            return false;
        };
        if by < ledger.frontier() {
            return false;
        }
        let labeller = ledger.canonical[by];
        ledger.flags[labeller as usize] & (LABELLED | PENDING) == 0 && !ledger.is_claimed(labeller)
    }

    /// The canonical position of the orbit forecast to label the cell, when another one does.
    pub fn labeller(&self, cell: u32) -> Option<usize> {
        self.labeller
            .get(cell as usize)
            .filter(|&&by| by != u32::MAX)
            .map(|&by| by as usize)
    }

    /// Whether the forecast was made on a grid of `cells` cells.
    pub fn fits(&self, cells: usize) -> bool {
        self.labeller.len() == cells
    }
}

/// What became of an offered fast-PSS outcome ([`Ledger::take_outcome_news`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum OutcomeNews {
    /// The outcome of this cell counts: it turned live (its claims count) or committed.
    Counts(u32),
    /// The outcome of this cell was dropped (an earlier one labelled its cell).
    Dropped(u32),
}

/// Commits outcomes in canonical order.
#[derive(Clone, Debug)]
pub struct Ledger {
    mode: Mode,
    canonical: Vec<u32>,
    position: Vec<u32>,
    /// Per cell: [`COMPATIBLE`], [`LABELLED`] and [`PENDING`]. The hot checks read these
    /// bytes (160 kB at 400×400, cache-resident): a commit visits ~100 cells, and a cache
    /// miss on each would be most of its cost.
    flags: Vec<u8>,
    /// Per labelled cell, the index in `committed` of the outcome that labelled it (`u32::MAX`:
    /// none). A commit writes 4 bytes per cell it labels rather than a copy of the label.
    labelled_by: Vec<u32>,
    /// Labels set so far (progress reporting asks after every batch; counting would scan the grid).
    resolved: usize,
    /// Next canonical position to commit.
    next: usize,
    pending: BTreeMap<usize, Pending>,
    /// Orbits in progress whose crossings so far were said, by canonical position.
    running: BTreeMap<usize, Partial>,
    /// Outcomes committed, in canonical order (their checkpoints feed Fig. 7).
    pub committed: Vec<Outcome>,
    /// Outcomes dropped and speculative orbits abandoned (their cell was already labelled).
    pub dropped: u64,
    /// Steps of the dropped outcomes and abandoned orbits.
    pub dropped_steps: u64,
    /// Steps of the committed outcomes.
    pub committed_steps: u64,
    /// Cells labelled since the last [`Ledger::take_newly_labelled`].
    newly_labelled: Vec<u32>,
    /// Fast PSS, once [`Ledger::watch_outcomes`] asked: what became of offered outcomes since
    /// the last [`Ledger::take_outcome_news`].
    news: Option<Vec<OutcomeNews>>,
    /// Fast PSS: the claims of live pending outcomes.
    claims: ClaimCounts,
    /// Cells that lost their last claim while unlabelled, so far (see [`Ledger::reopenings`]).
    reopened: u64,
    /// Positions of pending outcomes whose liveness may have changed (see [`Ledger::relive`]).
    recheck: std::collections::BinaryHeap<std::cmp::Reverse<usize>>,
}

impl Ledger {
    /// An empty ledger of `grid` in `mode`.
    pub fn new(grid: &Grid, mode: Mode) -> Self {
        let cells = grid.cells();
        Ledger {
            mode,
            canonical: grid.canonical().to_vec(),
            position: grid.positions().to_vec(),
            flags: (0..cells as u32)
                .map(|c| if grid.is_compatible(c) { COMPATIBLE } else { 0 })
                .collect(),
            labelled_by: vec![u32::MAX; cells],
            resolved: 0,
            next: 0,
            pending: BTreeMap::new(),
            running: BTreeMap::new(),
            committed: Vec::new(),
            dropped: 0,
            dropped_steps: 0,
            committed_steps: 0,
            newly_labelled: Vec::new(),
            news: None,
            claims: ClaimCounts {
                early: owned(vec![0; cells], || 0),
                changes: None,
            },
            reopened: 0,
            recheck: std::collections::BinaryHeap::new(),
        }
    }

    /// Whether visited cells are labelled too.
    pub fn mode(&self) -> Mode {
        self.mode
    }

    /// The label of `cell` (`None` while it has none).
    pub fn label(&self, cell: u32) -> Option<Label> {
        let o = self
            .committed
            .get(self.labelled_by[cell as usize] as usize)?;
        Some(Label {
            class: o.class,
            status: o.status,
            sali: o.sali,
            source: o.cell,
            t_end: o.t_end,
            indicators: o.indicators,
        })
    }

    /// Whether `cell` has a label.
    pub fn is_labelled(&self, cell: u32) -> bool {
        self.flags[cell as usize] & LABELLED != 0
    }

    /// Every compatible cell is labelled.
    pub fn done(&self) -> bool {
        self.next == self.canonical.len()
    }

    /// Compatible cells labelled so far.
    pub fn resolved(&self) -> usize {
        self.resolved
    }

    /// Canonical position of the first cell not yet committed or skipped.
    pub fn frontier(&self) -> usize {
        self.next
    }

    /// Up to `count` cells from the frontier on that are unlabelled and have no pending outcome:
    /// the cells worth integrating next.
    pub fn needed(&self, count: usize, in_flight: &dyn Fn(u32) -> bool) -> Vec<u32> {
        let mut cells = Vec::new();
        if count > 0 {
            self.scan_needed(|c| {
                if !in_flight(c) {
                    cells.push(c);
                }
                cells.len() == count
            });
        }
        cells
    }

    /// Shows `visit` the cells from the frontier on that are unlabelled and have no pending
    /// outcome, in canonical order, until it returns true.
    pub fn scan_needed(&self, mut visit: impl FnMut(u32) -> bool) {
        for &c in &self.canonical[self.next..] {
            if self.flags[c as usize] & (LABELLED | PENDING) == 0 && visit(c) {
                return;
            }
        }
    }

    /// Who labelled each cell so far, as a [`Forecast`] for a similar run.
    pub fn forecast(&self) -> Forecast {
        Forecast {
            labeller: self
                .labelled_by
                .iter()
                .enumerate()
                .map(|(cell, &k)| match self.committed.get(k as usize) {
                    Some(o) if o.cell as usize != cell => self.position[o.cell as usize],
                    _ => u32::MAX,
                })
                .collect(),
        }
    }

    /// Whether an outcome for the cell's own orbit is pending or committed.
    pub fn has_outcome(&self, cell: u32) -> bool {
        let pos = self.position[cell as usize];
        pos != u32::MAX
            && (self.flags[cell as usize] & PENDING != 0
                || self.label(cell).is_some_and(|l| l.source == cell))
    }

    /// Whether a live pending outcome earlier in canonical order crossed the cell (see
    /// [`ClaimCounts`]): if that outcome commits, the cell is labelled by it, so integrating the
    /// cell now is probably wasted. Only probably: an orbit not yet integrated may label the
    /// claimer's cell, and then the claim goes with it. The frontier cell is never claimed
    /// (every pending outcome lies after it), so a scheduler that skips claimed cells still
    /// makes progress.
    pub fn is_claimed(&self, cell: u32) -> bool {
        self.claims.early[cell as usize] != 0
    }

    fn is_unlabelled_compatible(&self, cell: u32) -> bool {
        self.flags[cell as usize] & (COMPATIBLE | LABELLED) == COMPATIBLE
    }

    /// Whether the cell still needs its own orbit now: compatible, unlabelled, without an
    /// outcome, and not claimed by an earlier live pending outcome.
    pub fn wants(&self, cell: u32) -> bool {
        // Unlabelled, so an outcome of its own can only be pending.
        self.flags[cell as usize] & (COMPATIBLE | LABELLED | PENDING) == COMPATIBLE
            && !self.is_claimed(cell)
    }

    /// Changes whenever an unlabelled cell loses its last claim (its claimers were dropped or
    /// stopped being live). Every other way out of [`Ledger::wants`] is for good (a cell
    /// labelled stays labelled; a pending outcome is committed, labelling its cell, or dropped
    /// because its cell is labelled; a committed claimer labels the cells it claimed), so a
    /// cell found unwanted stays unwanted while this count is unchanged: the coordinator skips
    /// tiles it found empty without scanning them again.
    pub fn reopenings(&self) -> u64 {
        self.reopened
    }

    /// Keeps the cells whose claims change, for a reader that mirrors [`Ledger::is_claimed`]
    /// outside the ledger's lock (the embedded engine's running orbits).
    pub fn track_claim_changes(&mut self) {
        self.claims.changes.get_or_insert_with(Vec::new);
    }

    /// Calls `f(cell, is_claimed(cell))` for every cell whose claims changed since the last
    /// call (some more than once).
    pub fn drain_claim_changes(&mut self, mut f: impl FnMut(u32, bool)) {
        let Some(mut changes) = self.claims.changes.take() else {
            return;
        };
        for &c in &changes {
            f(c, self.is_claimed(c));
        }
        changes.clear();
        self.claims.changes = Some(changes);
    }

    /// The cells labelled since the last call.
    pub fn take_newly_labelled(&mut self) -> Vec<u32> {
        std::mem::take(&mut self.newly_labelled)
    }

    /// Starts recording what becomes of offered outcomes ([`Ledger::take_outcome_news`]).
    pub fn watch_outcomes(&mut self) {
        self.news.get_or_insert_with(Vec::new);
    }

    /// What became of offered outcomes since the last call (nothing unless
    /// [`Ledger::watch_outcomes`] was called): an outcome may be told more than once as
    /// counting (turned live, then committed), and once as dropped.
    pub fn take_outcome_news(&mut self) -> Vec<OutcomeNews> {
        self.news.as_mut().map(std::mem::take).unwrap_or_default()
    }

    fn tell(&mut self, news: OutcomeNews) {
        if let Some(n) = &mut self.news {
            n.push(news);
        }
    }

    /// Counts speculative orbits abandoned before they finished (their cell was certain to be
    /// labelled by an earlier orbit) with the steps they had taken.
    pub fn record_abandoned(&mut self, orbits: u64, steps: u64) {
        self.dropped += orbits;
        self.dropped_steps = self.dropped_steps.saturating_add(steps);
    }

    /// Fast PSS: the orbit of `cell`, still in progress, crossed `crossed` (more of them on
    /// each call). Until its outcome comes or [`Ledger::forget_progress`], these cells are
    /// claimed as its outcome would claim them, so that they are not integrated meanwhile.
    /// A scheduling hint only: labels come from outcomes alone.
    pub fn progress(&mut self, cell: u32, crossed: &[u32]) {
        let pos = self.position[cell as usize];
        if self.mode != Mode::FastPss
            || pos == u32::MAX
            || (pos as usize) < self.next
            || self.flags[cell as usize] & (LABELLED | PENDING) != 0
        {
            return;
        }
        let pos = pos as usize;
        let partial = self.running.entry(pos).or_default();
        if self.flags[cell as usize] & RUNNING == 0 {
            self.flags[cell as usize] |= RUNNING;
            self.recheck.push(std::cmp::Reverse(pos));
        }
        let fresh: Vec<u32> = crossed
            .iter()
            .copied()
            .filter(|&c| {
                self.flags
                    .get(c as usize)
                    .is_some_and(|f| f & COMPATIBLE != 0)
            })
            .collect();
        partial.visited.extend_from_slice(&fresh);
        if partial.live {
            let (flags, position, recheck) = (&self.flags, &self.position, &mut self.recheck);
            self.claims
                .count(position, &fresh, pos, true, |c, claimed| {
                    if claimed && flags[c as usize] & (PENDING | RUNNING) != 0 {
                        recheck.push(std::cmp::Reverse(position[c as usize] as usize));
                    }
                });
        }
        self.relive();
    }

    /// The orbit of `cell` in progress stopped without an outcome: its claims go.
    pub fn forget_progress(&mut self, cell: u32) {
        if let Some(&pos) = self.position.get(cell as usize).filter(|&&p| p != u32::MAX) {
            self.end_progress(pos as usize);
            self.relive();
        }
    }

    /// Removes the orbit in progress at `pos`, taking back its claims if they counted.
    fn end_progress(&mut self, pos: usize) {
        if let Some(p) = self.running.remove(&pos) {
            self.flags[self.canonical[pos] as usize] &= !RUNNING;
            if p.live {
                self.release(&p.visited, pos);
            }
        }
    }

    /// Accepts an outcome (any order) and commits whatever the canonical order now allows.
    pub fn offer(&mut self, outcome: Outcome) {
        let pos = self.position[outcome.cell as usize];
        assert!(
            pos != u32::MAX,
            "outcome for an incompatible cell {}",
            outcome.cell
        );
        let pos = pos as usize;
        // The outcome takes over from its orbit's progress.
        self.end_progress(pos);
        if pos < self.next || self.flags[outcome.cell as usize] & (LABELLED | PENDING) != 0 {
            if self.flags[outcome.cell as usize] & PENDING == 0 {
                self.tell(OutcomeNews::Dropped(outcome.cell));
            }
            self.dropped += 1;
            self.dropped_steps = self.dropped_steps.saturating_add(outcome.steps);
            self.advance();
            return;
        }
        self.flags[outcome.cell as usize] |= PENDING;
        self.pending.insert(
            pos,
            Pending {
                outcome,
                live: false,
            },
        );
        self.advance();
        // Claims matter only while an outcome waits for earlier ones, so they are made only
        // for one that did not commit at once (in a streaming run most do).
        if self.mode == Mode::FastPss && self.pending.contains_key(&pos) {
            self.recheck.push(std::cmp::Reverse(pos));
            self.relive();
        }
    }

    /// Commits pending outcomes in canonical order while the next one is there.
    fn advance(&mut self) {
        while self.next < self.canonical.len() {
            let cell = self.canonical[self.next];
            let pos = self.next;
            if self.is_labelled(cell) {
                self.end_progress(pos);
                if let Some(p) = self.pending.remove(&pos) {
                    self.flags[cell as usize] &= !PENDING;
                    if p.live {
                        self.release(&p.outcome.visited, pos);
                    }
                    self.tell(OutcomeNews::Dropped(cell));
                    self.dropped += 1;
                    self.dropped_steps = self.dropped_steps.saturating_add(p.outcome.steps);
                }
                self.next += 1;
                continue;
            }
            let Some(p) = self.pending.remove(&pos) else {
                break;
            };
            self.flags[cell as usize] &= !PENDING;
            self.tell(OutcomeNews::Counts(cell));
            // Labels first: the claims it releases then fall on labelled cells, which reopen
            // nothing.
            self.commit(p.outcome);
            if p.live {
                let last = self.committed.len() - 1;
                let visited = std::mem::take(&mut self.committed[last].visited);
                self.release(&visited, pos);
                self.committed[last].visited = visited;
            }
            self.next += 1;
        }
        self.relive();
    }

    /// Takes back the claims of a live outcome at `pos` that crossed `visited`; an unlabelled
    /// cell left without a claim is reopened, and a pending outcome there is checked again.
    fn release(&mut self, visited: &[u32], pos: usize) {
        let (flags, position, recheck, reopened) = (
            &self.flags,
            &self.position,
            &mut self.recheck,
            &mut self.reopened,
        );
        self.claims
            .count(position, visited, pos, false, |cell, claimed| {
                if !claimed && flags[cell as usize] & LABELLED == 0 {
                    *reopened += 1;
                    if flags[cell as usize] & (PENDING | RUNNING) != 0 {
                        recheck.push(std::cmp::Reverse(position[cell as usize] as usize));
                    }
                }
            });
    }

    /// Brings the liveness of the pending outcomes queued in `recheck` up to date, earliest
    /// first: an outcome's liveness depends only on the live outcomes before it, so each
    /// change queues only later ones and one pass in canonical order settles them all.
    fn relive(&mut self) {
        while let Some(std::cmp::Reverse(pos)) = self.recheck.pop() {
            let cell = self.canonical[pos];
            let should =
                self.flags[cell as usize] & LABELLED == 0 && self.claims.early[cell as usize] == 0;
            let slot = match self.pending.get_mut(&pos) {
                Some(p) => Some((&mut p.live, &mut p.outcome.visited)),
                None => self
                    .running
                    .get_mut(&pos)
                    .map(|r| (&mut r.live, &mut r.visited)),
            };
            let Some((live, visited)) = slot else {
                continue;
            };
            if *live == should {
                continue;
            }
            *live = should;
            let visited = std::mem::take(visited);
            if should && self.pending.contains_key(&pos) {
                self.tell(OutcomeNews::Counts(cell));
            }
            if should {
                let (flags, position, recheck) = (&self.flags, &self.position, &mut self.recheck);
                self.claims
                    .count(position, &visited, pos, true, |cell, claimed| {
                        if claimed && flags[cell as usize] & (PENDING | RUNNING) != 0 {
                            recheck.push(std::cmp::Reverse(position[cell as usize] as usize));
                        }
                    });
            } else {
                self.release(&visited, pos);
            }
            match self.pending.get_mut(&pos) {
                Some(p) => p.outcome.visited = visited,
                None => {
                    if let Some(r) = self.running.get_mut(&pos) {
                        r.visited = visited;
                    }
                }
            }
        }
    }

    fn commit(&mut self, o: Outcome) {
        let index = u32::try_from(self.committed.len()).expect("fewer outcomes than cells");
        self.labelled_by[o.cell as usize] = index;
        self.flags[o.cell as usize] |= LABELLED;
        self.resolved += 1;
        self.newly_labelled.push(o.cell);
        if self.mode == Mode::FastPss {
            for &v in &o.visited {
                if self.is_unlabelled_compatible(v) {
                    if self.flags[v as usize] & (PENDING | RUNNING) != 0 {
                        // Its outcome will be dropped: its claims no longer count.
                        self.recheck
                            .push(std::cmp::Reverse(self.position[v as usize] as usize));
                    }
                    self.labelled_by[v as usize] = index;
                    self.flags[v as usize] |= LABELLED;
                    self.resolved += 1;
                    self.newly_labelled.push(v);
                }
            }
        }
        self.committed_steps = self.committed_steps.saturating_add(o.steps);
        self.committed.push(o);
    }
}

/// The sequential definition itself, for tests: `integrate(cell)` gives a cell's outcome.
pub fn sequential(
    grid: &Grid,
    mode: Mode,
    mut integrate: impl FnMut(u32) -> Outcome,
) -> Vec<Option<Label>> {
    let mut labels: Vec<Option<Label>> = vec![None; grid.cells()];
    for &cell in grid.canonical() {
        if labels[cell as usize].is_some() {
            continue;
        }
        let o = integrate(cell);
        let label = Label {
            class: o.class,
            status: o.status,
            sali: o.sali,
            source: cell,
            t_end: o.t_end,
            indicators: o.indicators,
        };
        labels[cell as usize] = Some(label);
        if mode == Mode::FastPss {
            for &v in &o.visited {
                if grid.is_compatible(v) && labels[v as usize].is_none() {
                    labels[v as usize] = Some(label);
                }
            }
        }
    }
    labels
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    /// A fake orbit: a deterministic pseudo-random class and visited set per cell.
    fn fake(grid: &Grid, seed: u64, cell: u32) -> Outcome {
        let mut x = seed ^ (cell as u64).wrapping_mul(0x9e37_79b9_7f4a_7c15);
        let mut next = || {
            x ^= x << 13;
            x ^= x >> 7;
            x ^= x << 17;
            x
        };
        let class = [Class::Regular, Class::Sticky, Class::Chaotic][(next() % 3) as usize];
        let n = (next() % 12) as usize;
        let mut visited: Vec<u32> = (0..n)
            .map(|_| {
                // Mostly near the start cell, sometimes anywhere: like regular and chaotic orbits.
                let r = next();
                if r % 4 == 0 {
                    (r % grid.cells() as u64) as u32
                } else {
                    let d = (r % 9) as i64 - 4;
                    (cell as i64 + d).clamp(0, grid.cells() as i64 - 1) as u32
                }
            })
            .filter(|&c| grid.is_compatible(c))
            .collect();
        visited.sort_unstable();
        visited.dedup();
        Outcome {
            cell,
            class: Some(class),
            status: Status::Ok,
            sali: 0.5,
            visited,
            steps: 100,
            t_end: 1.0,
            checkpoints: Vec::new(),
            indicators: None,
        }
    }

    proptest! {
        #![proptest_config(ProptestConfig { cases: 48, ..ProptestConfig::default() })]

        /// Outcomes for every compatible cell (speculation beyond the rule), offered in a random
        /// order, leave exactly the sequential labels; the committed orbits are exactly the
        /// sequentially integrated ones, and everything else is counted as dropped.
        #[test]
        fn ledger_equals_the_sequential_rule_for_any_arrival_order(
            seed in any::<u64>(),
            shuffle in any::<u64>(),
            full in any::<bool>(),
            n in 4usize..24,
            tile in 1usize..7,
        ) {
            let grid = Grid::new(0.125, n, n + 3, (-0.43, 0.67), (-0.5, 0.5), (tile, tile + 1));
            let mode = if full { Mode::Full } else { Mode::FastPss };
            let mut integrated = Vec::new();
            let want = sequential(&grid, mode, |c| { integrated.push(c); fake(&grid, seed, c) });
            let mut order: Vec<u32> = grid.canonical().to_vec();
            let mut s = shuffle | 1;
            for i in (1..order.len()).rev() {
                s ^= s << 13; s ^= s >> 7; s ^= s << 17;
                order.swap(i, (s % (i as u64 + 1)) as usize);
            }
            let mut ledger = Ledger::new(&grid, mode);
            for &c in &order {
                ledger.offer(fake(&grid, seed, c));
                let labelled = (0..grid.cells() as u32).filter(|&c| ledger.is_labelled(c)).count();
                prop_assert_eq!(ledger.resolved(), labelled);
                for c in 0..grid.cells() as u32 {
                    let pending = grid.position(c).is_some_and(|p| ledger.pending.contains_key(&p));
                    prop_assert_eq!(ledger.flags[c as usize] & PENDING != 0, pending);
                }
                // A cell is claimed exactly when a live pending outcome before it crossed it,
                // live meaning that no live one before it crossed its own (unlabelled) cell.
                let mut claimed = vec![false; grid.cells()];
                if mode == Mode::FastPss {
                    for (&p, pending) in &ledger.pending {
                        let live = !ledger.is_labelled(pending.outcome.cell)
                            && !claimed[pending.outcome.cell as usize];
                        prop_assert_eq!(pending.live, live, "outcome at {}", p);
                        for &v in pending.outcome.visited.iter().filter(|_| live) {
                            if grid.position(v).is_some_and(|q| p < q) {
                                claimed[v as usize] = true;
                            }
                        }
                    }
                }
                for c in 0..grid.cells() as u32 {
                    prop_assert_eq!(ledger.is_claimed(c), claimed[c as usize], "cell {}", c);
                }
            }
            prop_assert!(ledger.done());
            for c in 0..grid.cells() as u32 {
                prop_assert_eq!(ledger.label(c), want[c as usize]);
            }
            let committed: Vec<u32> = ledger.committed.iter().map(|o| o.cell).collect();
            prop_assert_eq!(&committed, &integrated);
            prop_assert_eq!(ledger.dropped as usize, grid.compatible_count() - integrated.len());
        }

        /// A worker's own ledger sees only some outcomes (its own and those relayed so far), in
        /// any order. What it commits is a prefix of what the full ledger commits: every label
        /// it sets is the full ledger's, its frontier is at or before the full one, and a cell
        /// its claims hold certain ([`crate::executor::LocalLedger`]) is labelled in the end.
        #[test]
        fn a_ledger_of_some_outcomes_commits_a_prefix_of_the_full_one(
            seed in any::<u64>(),
            pick in any::<u64>(),
            n in 4usize..20,
            tile in 1usize..6,
        ) {
            let grid = Grid::new(0.125, n, n + 2, (-0.43, 0.67), (-0.5, 0.5), (tile, tile + 1));
            let want = sequential(&grid, Mode::FastPss, |c| fake(&grid, seed, c));
            let mut s = pick | 1;
            let mut rnd = move || { s ^= s << 13; s ^= s >> 7; s ^= s << 17; s };
            let mut some: Vec<u32> = grid.canonical().iter().copied().filter(|_| rnd() % 5 < 3).collect();
            for i in (1..some.len()).rev() {
                some.swap(i, (rnd() % (i as u64 + 1)) as usize);
            }
            let mut part = Ledger::new(&grid, Mode::FastPss);
            let local = crate::executor::LocalLedger::new(&grid, Mode::FastPss);
            for &c in &some {
                part.offer(fake(&grid, seed, c));
                local.offer(fake(&grid, seed, c));
            }
            let mut full = Ledger::new(&grid, Mode::FastPss);
            for &c in grid.canonical() {
                full.offer(fake(&grid, seed, c));
            }
            prop_assert!(part.frontier() <= full.frontier());
            for c in 0..grid.cells() as u32 {
                if let Some(l) = part.label(c) {
                    prop_assert_eq!(Some(l), want[c as usize]);
                }
                if local.claims().is_claimed(c) {
                    prop_assert!(want[c as usize].is_some(), "cell {} claimed", c);
                }
                // And the claims know every label of the ledger they mirror.
                prop_assert_eq!(part.is_labelled(c), local.claims().is_claimed(c), "cell {}", c);
            }
        }

        /// A scheduler that only integrates cells the ledger `wants` (any of them, with outcomes
        /// arriving in any order, running orbits saying part of what they crossed, some of them
        /// abandoned) never stalls and ends with the sequential labels: claims from pending
        /// outcomes that are later dropped, and from abandoned orbits, are released. A mirror
        /// of the claims kept from [`Ledger::drain_claim_changes`] equals
        /// [`Ledger::is_claimed`] throughout, and no unwanted cell becomes wanted without a
        /// change of [`Ledger::reopenings`].
        #[test]
        fn integrating_only_wanted_cells_makes_progress_and_equals_the_rule(
            seed in any::<u64>(),
            choices in any::<u64>(),
            n in 4usize..20,
            tile in 1usize..6,
        ) {
            let grid = Grid::new(0.125, n, n + 2, (-0.43, 0.67), (-0.5, 0.5), (tile, tile + 1));
            let want = sequential(&grid, Mode::FastPss, |c| fake(&grid, seed, c));
            let mut ledger = Ledger::new(&grid, Mode::FastPss);
            ledger.track_claim_changes();
            let mut mirror = vec![false; grid.cells()];
            let mut in_flight: Vec<Outcome> = Vec::new();
            let mut s = choices | 1;
            let mut rnd = move || { s ^= s << 13; s ^= s >> 7; s ^= s << 17; s };
            let mut integrated = 0usize;
            while !ledger.done() {
                let wanted: Vec<u32> = grid
                    .canonical()
                    .iter()
                    .copied()
                    .filter(|&c| ledger.wants(c) && !in_flight.iter().any(|o| o.cell == c))
                    .take(6)
                    .collect();
                prop_assert!(!(wanted.is_empty() && in_flight.is_empty()), "stalled");
                if !wanted.is_empty() && (in_flight.is_empty() || rnd() % 2 == 0) {
                    let c = wanted[(rnd() % wanted.len() as u64) as usize];
                    let o = fake(&grid, seed, c);
                    if rnd() % 2 == 0 {
                        let said = (rnd() % (o.visited.len() as u64 + 1)) as usize;
                        ledger.progress(c, &o.visited[..said]);
                    }
                    in_flight.push(o);
                } else {
                    let k = (rnd() % in_flight.len() as u64) as usize;
                    let unwanted: Vec<u32> =
                        grid.canonical().iter().copied().filter(|&c| !ledger.wants(c)).collect();
                    let reopenings = ledger.reopenings();
                    let o = in_flight.swap_remove(k);
                    match rnd() % 4 {
                        0 => ledger.forget_progress(o.cell),
                        1 => {
                            // More of it said, twice over for some cells; still running.
                            ledger.progress(o.cell, &o.visited);
                            in_flight.push(o);
                        }
                        _ => {
                            integrated += 1;
                            ledger.offer(o);
                        }
                    }
                    ledger.drain_claim_changes(|c, claimed| mirror[c as usize] = claimed);
                    for c in grid.canonical() {
                        prop_assert_eq!(mirror[*c as usize], ledger.is_claimed(*c), "cell {}", c);
                    }
                    if ledger.reopenings() == reopenings {
                        for &c in &unwanted {
                            prop_assert!(!ledger.wants(c), "cell {} wanted again", c);
                        }
                    }
                }
            }
            for c in 0..grid.cells() as u32 {
                prop_assert_eq!(ledger.label(c), want[c as usize]);
            }
            prop_assert!(integrated <= grid.compatible_count());
        }
    }

    #[test]
    fn a_forecast_defers_a_cell_only_while_its_labeller_may_still_need_its_orbit() {
        let grid = Grid::new(0.125, 12, 14, (-0.43, 0.67), (-0.5, 0.5), (3, 4));
        let mut finished = Ledger::new(&grid, Mode::FastPss);
        while !finished.done() {
            let next = finished.needed(1, &|_| false)[0];
            finished.offer(fake(&grid, 7, next));
        }
        let forecast = finished.forecast();
        assert!(forecast.fits(grid.cells()) && !forecast.fits(grid.cells() + 1));
        let canon = grid.canonical();
        let labeller = |c: u32| {
            let source = finished.label(c).unwrap().source;
            canon.iter().position(|&x| x == source).unwrap()
        };
        // The same run again, outcome by outcome: a cell is deferred while its forecast
        // labeller has not run, and never once the frontier reaches it.
        let mut again = Ledger::new(&grid, Mode::FastPss);
        let mut deferred = 0;
        loop {
            let frontier = again.frontier();
            for (pos, &c) in canon.iter().enumerate() {
                let by = labeller(c);
                assert!(
                    by <= pos,
                    "a label comes from an earlier orbit or the cell's own"
                );
                let want = by != pos && by >= frontier && !again.has_outcome(canon[by]);
                assert_eq!(forecast.defers(c, &again), want, "cell {c} at {frontier}");
                deferred += usize::from(want);
                if pos == frontier {
                    assert!(!forecast.defers(c, &again));
                }
            }
            if again.done() {
                break;
            }
            let next = again.needed(1, &|_| false)[0];
            again.offer(fake(&grid, 7, next));
        }
        assert!(deferred > 0);
        for c in (0..grid.cells() as u32).filter(|&c| !grid.is_compatible(c)) {
            assert!(!forecast.defers(c, &Ledger::new(&grid, Mode::FastPss)));
        }
        // A labeller whose cell an earlier outcome claims may not need its orbit: the cells it
        // was forecast to label are released at once, far ahead of the frontier.
        let fresh = Ledger::new(&grid, Mode::FastPss);
        let (c, by) = canon
            .iter()
            .map(|&c| (c, labeller(c)))
            .find(|&(c, by)| by > 1 && forecast.defers(c, &fresh))
            .expect("a deferred cell whose labeller is not among the first two");
        let mut claimer = fake(&grid, 7, canon[0]);
        claimer.visited = vec![canon[by]];
        let mut claimed = Ledger::new(&grid, Mode::FastPss);
        claimed.offer(claimer);
        assert!(claimed.is_claimed(canon[by]) || claimed.is_labelled(canon[by]));
        assert!(!forecast.defers(c, &claimed));
    }

    #[test]
    fn ledger_waits_for_the_frontier_and_reports_what_is_needed() {
        let grid = Grid::new(0.125, 6, 6, (-0.43, 0.67), (-0.5, 0.5), (3, 3));
        let mut ledger = Ledger::new(&grid, Mode::FastPss);
        let canon = grid.canonical().to_vec();
        // An outcome beyond the frontier is held, not committed.
        ledger.offer(fake(&grid, 1, canon[2]));
        assert_eq!(ledger.frontier(), 0);
        assert!(!ledger.is_labelled(canon[2]));
        let needed = ledger.needed(2, &|_| false);
        assert_eq!(needed, vec![canon[0], canon[1]]);
        assert_eq!(
            ledger.needed(2, &|c| c == canon[0]),
            vec![canon[1], canon[3]]
        );
    }

    /// The news of the chain below: an outcome counts when it turns live or commits (again
    /// after it was dead for a while), and is dropped once, also when it arrives for a cell
    /// already labelled.
    #[test]
    fn outcome_news_tell_when_an_outcome_counts_and_when_it_is_dropped() {
        let grid = Grid::new(0.125, 6, 6, (-0.43, 0.67), (-0.5, 0.5), (3, 3));
        let canon = grid.canonical().to_vec();
        let outcome = |at: usize, crosses: Option<usize>| Outcome {
            visited: crosses.map(|c| canon[c]).into_iter().collect(),
            ..fake(&grid, 1, canon[at])
        };
        use OutcomeNews::{Counts, Dropped};
        let mut ledger = Ledger::new(&grid, Mode::FastPss);
        ledger.offer(outcome(5, None));
        assert!(
            ledger.take_outcome_news().is_empty(),
            "nothing unless watched"
        );
        let mut ledger = Ledger::new(&grid, Mode::FastPss);
        ledger.watch_outcomes();
        let mut step = |at: usize, crosses: Option<usize>| {
            ledger.offer(outcome(at, crosses));
            ledger.take_outcome_news()
        };
        assert_eq!(step(4, Some(6)), [Counts(canon[4])]);
        // 2 crosses 4, which turns dead: nothing to tell of it.
        assert_eq!(step(2, Some(4)), [Counts(canon[2])]);
        // 1 crosses 2: 2 dead, 4 live again.
        assert_eq!(step(1, Some(2)), [Counts(canon[1]), Counts(canon[4])]);
        // 0 and 1 commit, 1 labels 2: dropped.
        assert_eq!(
            step(0, None),
            [Counts(canon[0]), Counts(canon[1]), Dropped(canon[2])]
        );
        assert_eq!(step(3, Some(4)), [Counts(canon[3]), Dropped(canon[4])]);
        assert_eq!(step(2, None), [Dropped(canon[2])], "a late repeat");
    }

    /// Pending outcomes in a chain, each crossing the next one's cell: only those that no live
    /// earlier one crossed are live, and only live ones claim. Each outcome added before the
    /// chain flips the liveness of everything after it.
    #[test]
    fn an_outcome_whose_cell_an_earlier_one_crossed_claims_nothing() {
        let grid = Grid::new(0.125, 6, 6, (-0.43, 0.67), (-0.5, 0.5), (3, 3));
        let canon = grid.canonical().to_vec();
        let outcome = |at: usize, crosses: Option<usize>| Outcome {
            visited: crosses.map(|c| canon[c]).into_iter().collect(),
            ..fake(&grid, 1, canon[at])
        };
        let (first, third) = (canon[2], canon[6]);
        let mut ledger = Ledger::new(&grid, Mode::FastPss);
        ledger.offer(outcome(4, Some(6)));
        assert!(ledger.is_claimed(third) && !ledger.wants(third));
        // The outcome at 2 crosses the one at 4, which will be dropped: its claim goes.
        ledger.offer(outcome(2, Some(4)));
        assert!(!ledger.is_claimed(third) && ledger.wants(third));
        // The outcome at 1 crosses the one at 2: 4 is live again and claims 6.
        ledger.offer(outcome(1, Some(2)));
        assert!(ledger.is_claimed(third) && !ledger.wants(third));
        // Committing 0 and 1 labels 2, whose outcome is dropped; 4 waits behind the hole at 3,
        // still claiming 6.
        ledger.offer(outcome(0, None));
        assert!(ledger.is_labelled(first));
        assert_eq!(ledger.frontier(), 3);
        assert!(ledger.is_claimed(third) && !ledger.wants(third));
        let reopenings = ledger.reopenings();
        // An outcome at 3 crossing 4 makes 4's claim go for good.
        ledger.offer(outcome(3, Some(4)));
        assert!(!ledger.is_claimed(third) && ledger.wants(third));
        assert!(ledger.reopenings() > reopenings);
    }
}
