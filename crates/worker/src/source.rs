//! Where a stream's lanes take their cells: the leased cells of one run in lease order, each
//! let go, deferred or dropped by the run's ledger, and per lease what has ended, so that
//! outcomes and finishing reports go to the network side as orbits end.

use crate::compute::{Done, Work};
use crate::signals::{lease_key, LeaseKey, Signals};
use salient_grid::executor::{CellSource, LocalLedger, Take, Verdict};
use salient_grid::process_cpu_seconds;
use salient_grid::Outcome;
use salient_proto::{push_partial, v1};
use std::collections::{HashMap, VecDeque};
use std::sync::atomic::{AtomicBool, AtomicU64, AtomicUsize, Ordering};
use std::sync::{Arc, Condvar, Mutex};
use std::time::Duration;
use tokio::sync::mpsc;

/// How long a stream whose lanes are all idle waits for a lease or an ended orbit before it
/// starts the first deferred cell anyway (then nothing here could settle it).
pub const IDLE_WAIT: Duration = Duration::from_millis(5);

/// The leases of one stream: their cells waiting in order, and per lease what has ended.
pub(crate) struct LeaseSource {
    state: Mutex<SourceState>,
    /// Entries waiting in the queue, readable without the lock: idle lanes ask every few
    /// steps, and taking the lock for each (shared by all threads) would be a large share of
    /// the run (figures: docs/performance.md).
    waiting: AtomicUsize,
    /// `Done::Hungry` went out since the last lease came.
    hungry: AtomicBool,
    /// Bumped whenever a waiting cell's verdict may have changed (a lease came, an orbit
    /// ended); `dry` holds its value plus the local ledger's offers at the last search that let
    /// no cell go, so idle lanes, which ask every few steps, search again only after a change.
    changes: AtomicU64,
    local: Arc<LocalLedger>,
    dry: AtomicU64,
    /// Signalled when cells arrive or the stream closes.
    more: Condvar,
    done: mpsc::UnboundedSender<Done>,
    signals: Arc<Mutex<Signals>>,
    draining: Arc<AtomicBool>,
}

#[derive(Default)]
struct SourceState {
    /// Entries (see [`Take::Cell`]) not started, in lease order.
    queue: VecDeque<u64>,
    /// The lease of every entry queued or running.
    lease_of: HashMap<u64, LeaseKey>,
    leases: HashMap<LeaseKey, LeaseProgress>,
    /// Entries handed out so far (the high bits of the next one).
    serial: u64,
    closed: bool,
    /// Process CPU time when the last finishing report went out.
    cpu_mark: Option<f64>,
    /// Entries handed out whose orbits have not ended.
    running: usize,
}

struct LeaseProgress {
    lease: v1::TileRef,
    /// Entries queued or running.
    left: usize,
    /// Entries handed out.
    started: usize,
    abandoned: (u64, u64),
}

impl LeaseSource {
    pub(crate) fn new(
        local: Arc<LocalLedger>,
        done: mpsc::UnboundedSender<Done>,
        signals: Arc<Mutex<Signals>>,
        draining: Arc<AtomicBool>,
    ) -> Self {
        LeaseSource {
            state: Mutex::new(SourceState::default()),
            waiting: AtomicUsize::new(0),
            hungry: AtomicBool::new(false),
            changes: AtomicU64::new(0),
            local,
            dry: AtomicU64::new(u64::MAX),
            more: Condvar::new(),
            done,
            signals,
            draining,
        }
    }

    pub(crate) fn add(&self, w: Work) {
        let claims = self.local.claims();
        let key = lease_key(&w.lease);
        {
            // The coordinator leases a cell only when it needs it: a claim left from an
            // earlier skip of this cell must not abandon it now.
            let s = self.signals.lock().expect("signals");
            let skips = s.skips.get(&key);
            for &c in &w.cells {
                if skips.is_some_and(|sk| sk.contains(&c)) {
                    claims.claim(c);
                } else {
                    claims.unclaim(c);
                }
            }
        }
        let mut st = self.state.lock().expect("lease source");
        self.hungry.store(false, Ordering::Relaxed);
        st.cpu_mark.get_or_insert_with(process_cpu_seconds);
        for &c in &w.cells {
            st.serial += 1;
            let entry = (st.serial << 32) | c as u64;
            st.queue.push_back(entry);
            st.lease_of.insert(entry, key);
        }
        self.waiting.store(st.queue.len(), Ordering::Relaxed);
        self.changes.fetch_add(1, Ordering::Release);
        st.leases.insert(
            key,
            LeaseProgress {
                lease: w.lease,
                left: w.cells.len(),
                started: 0,
                abandoned: (0, 0),
            },
        );
        if w.cells.is_empty() {
            self.end_lease(&mut st, key, Vec::new());
        }
        drop(st);
        self.more.notify_all();
    }

    /// A lane is idle and no entry waits: asks the network side for a lease (once until one
    /// comes).
    fn say_hungry(&self) {
        if !self.hungry.load(Ordering::Relaxed) && !self.hungry.swap(true, Ordering::Relaxed) {
            let _ = self.done.send(Done::Hungry);
        }
    }

    pub(crate) fn close(&self) {
        self.state.lock().expect("lease source").closed = true;
        // Wakes the lanes that wait for entries, so they see the end.
        self.waiting.store(usize::MAX, Ordering::Relaxed);
        self.more.notify_all();
    }

    /// Draining: leases none of whose cells started go back to the coordinator.
    fn release_unstarted(&self, st: &mut SourceState) {
        let unstarted: Vec<LeaseKey> = st
            .leases
            .iter()
            .filter(|(_, p)| p.started == 0)
            .map(|(k, _)| *k)
            .collect();
        if unstarted.is_empty() {
            return;
        }
        let SourceState {
            queue, lease_of, ..
        } = st;
        queue.retain(|e| !unstarted.contains(&lease_of[e]));
        lease_of.retain(|_, k| !unstarted.contains(k));
        if !st.closed {
            self.waiting.store(st.queue.len(), Ordering::Relaxed);
        }
        for k in unstarted {
            if let Some(p) = st.leases.remove(&k) {
                let _ = self.done.send(Done::Released(p.lease));
            }
        }
    }

    /// Sends the lease's finishing report and forgets it.
    fn end_lease(&self, st: &mut SourceState, key: LeaseKey, outcomes: Vec<v1::Outcome>) {
        let Some(p) = st.leases.remove(&key) else {
            return;
        };
        let now = process_cpu_seconds();
        let cpu = st.cpu_mark.replace(now).map_or(0.0, |m| (now - m).max(0.0));
        let _ = self.done.send(Done::Report(v1::TileReport {
            lease: Some(p.lease),
            outcomes,
            finished: true,
            cpu_ns: (cpu * 1e9) as u64,
            abandoned_orbits: p.abandoned.0,
            abandoned_steps: p.abandoned.1,
        }));
        let mut s = self.signals.lock().expect("signals");
        s.skips.remove(&key);
        s.revoked.remove(&key);
    }
}

impl CellSource for LeaseSource {
    fn take(&self, all_idle: bool, judge: &dyn Fn(u32) -> Verdict) -> Take {
        if !all_idle
            && (self.waiting.load(Ordering::Relaxed) == 0
                || self.dry.load(Ordering::Relaxed) == self.version())
        {
            self.say_hungry();
            return Take::Wait;
        }
        let mut st = self.state.lock().expect("lease source");
        if self.draining.load(Ordering::Relaxed) {
            self.release_unstarted(&mut st);
        }
        let mut force = false;
        loop {
            let seen = self.version();
            let (pick, dropped) = self.search(&mut st, judge, force);
            if !st.closed {
                self.waiting.store(st.queue.len(), Ordering::Relaxed);
            }
            if let Some((entry, forced)) = pick {
                st.running += 1;
                drop(st);
                for e in dropped {
                    self.end_entry(e, None, 0);
                }
                return if forced {
                    Take::Insist(entry)
                } else {
                    Take::Cell(entry)
                };
            }
            if !dropped.is_empty() {
                drop(st);
                for e in dropped {
                    self.end_entry(e, None, 0);
                }
                st = self.state.lock().expect("lease source");
            }
            if st.closed && st.queue.is_empty() {
                return Take::Done;
            }
            self.dry.store(seen, Ordering::Relaxed);
            self.say_hungry();
            if !all_idle || force {
                return Take::Wait;
            }
            // Every lane is idle: wait for a lease or an ended orbit rather than spin. With no
            // orbit running here, what the waiting cells wait for comes from elsewhere (the
            // coordinator's skips, other workers' outcomes): after a wait, the first of them
            // goes anyway, so the stream cannot stall.
            let (g, timeout) = self.more.wait_timeout(st, IDLE_WAIT).expect("lease source");
            st = g;
            if timeout.timed_out() {
                if st.running > 0 {
                    return Take::Wait;
                }
                force = true;
            }
        }
    }

    fn ended(&self, entry: u64, outcome: Option<Outcome>, steps: u64) {
        self.state.lock().expect("lease source").running -= 1;
        self.end_entry(entry, outcome, steps);
    }

    fn crossed(&self, first_crossings: &[(u64, u32)]) {
        let st = self.state.lock().expect("lease source");
        let mut s = self.signals.lock().expect("signals");
        for &(entry, cell) in first_crossings {
            if let Some(&key) = st.lease_of.get(&entry) {
                let orbit = entry as u32;
                s.crossings.entry((key, orbit)).or_default().0.push(cell);
            }
        }
    }
}

impl LeaseSource {
    /// Grows whenever a waiting cell's verdict may have changed.
    fn version(&self) -> u64 {
        self.changes.load(Ordering::Acquire) + self.local.offers()
    }

    /// The first waiting entry that `judge` lets go (or, with `force`, the first it defers,
    /// when none goes; flagged `true`), taken out of the queue, and the entries it dropped
    /// (revoked leases' among them: their reports would be stale).
    fn search(
        &self,
        st: &mut SourceState,
        judge: &dyn Fn(u32) -> Verdict,
        force: bool,
    ) -> (Option<(u64, bool)>, Vec<u64>) {
        let signals = self.signals.lock().expect("signals");
        let mut dropped = Vec::new();
        let mut first_later = None;
        let mut i = 0;
        while i < st.queue.len() {
            let entry = st.queue[i];
            let key = st.lease_of[&entry];
            let verdict = if signals.revoked.contains(&key) {
                Verdict::Drop
            } else {
                judge(entry as u32)
            };
            match verdict {
                Verdict::Later => {
                    first_later.get_or_insert(i);
                    i += 1;
                    continue;
                }
                Verdict::Go => {}
                Verdict::Drop => dropped.push(entry),
            }
            st.queue.remove(i);
            if let Some(p) = st.leases.get_mut(&key) {
                p.started += 1;
            }
            if verdict == Verdict::Go {
                return (Some((entry, false)), dropped);
            }
        }
        let forced = first_later
            .filter(|_| force)
            .and_then(|i| st.queue.remove(i));
        if let Some(entry) = forced {
            if let Some(p) = st.leases.get_mut(&st.lease_of[&entry]) {
                p.started += 1;
            }
        }
        (forced.map(|e| (e, true)), dropped)
    }

    /// An entry's end: its outcome to the next poll, and the lease's finishing report once
    /// every entry of it ended.
    fn end_entry(&self, entry: u64, outcome: Option<Outcome>, steps: u64) {
        let mut st = self.state.lock().expect("lease source");
        self.changes.fetch_add(1, Ordering::Release);
        self.more.notify_all();
        let Some(key) = st.lease_of.remove(&entry) else {
            return;
        };
        let Some(p) = st.leases.get_mut(&key) else {
            return;
        };
        p.left -= 1;
        let out = match &outcome {
            Some(o) => Some(v1::Outcome::from(o)),
            None => {
                if steps > 0 {
                    p.abandoned.0 += 1;
                    p.abandoned.1 += steps;
                    // The coordinator may count what it crossed as claims.
                    let mut s = self.signals.lock().expect("signals");
                    s.crossings.entry((key, entry as u32)).or_default().1 = true;
                }
                None
            }
        };
        if p.left == 0 {
            self.end_lease(&mut st, key, out.into_iter().collect());
        } else if let Some(o) = out {
            // Out with the next poll (before the lease's finishing report, which is sent
            // after this and makes the network side collect these first).
            let lease = p.lease;
            push_partial(&mut self.signals.lock().expect("signals").partial, lease, o);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use salient_grid::spec;

    /// A stream's source hands out the first cell its judge lets go, ends the dropped ones
    /// without an outcome, keeps the deferred ones, and lets a deferred one go only when every
    /// lane is idle and no orbit runs (nothing here could settle it).
    #[test]
    fn the_source_defers_drops_and_never_stalls() {
        let json = r#"{"name": "t", "system": {"kind": "henon-heiles", "energy": 0.125},
            "grid": {"cells": [14, 12], "tile": [14, 12], "mode": "fast-pss"},
            "sweep": {"method": ["tm-sbab2c"], "tau": [0.5], "t_final": [10.0]}}"#;
        let spec = Arc::new(spec::parse(json, true).unwrap());
        let grid = spec.grid(0);
        let cells: Vec<u32> = grid.canonical()[..3].to_vec();
        let (tx, mut rx) = mpsc::unbounded_channel();
        let local = Arc::new(LocalLedger::new(&grid, spec.mode(0)));
        let source = LeaseSource::new(
            local.clone(),
            tx,
            Arc::new(Mutex::new(Signals::default())),
            Arc::new(AtomicBool::new(false)),
        );
        let lease = v1::TileRef {
            job: 1,
            run: 0,
            tile: 0,
            attempt: 1,
        };
        source.add(Work {
            lease,
            spec,
            cells: cells.clone(),
        });
        let (later, drop, go) = (cells[0], cells[1], cells[2]);
        let judge = |c: u32| match c {
            c if c == later => Verdict::Later,
            c if c == drop => Verdict::Drop,
            _ => Verdict::Go,
        };
        let taken = |t: Take| match t {
            Take::Cell(e) | Take::Insist(e) => Some(e as u32),
            _ => None,
        };
        let go_entry = match source.take(false, &judge) {
            Take::Cell(e) => e,
            _ => panic!("the cell the judge lets go is taken"),
        };
        assert_eq!(go_entry as u32, go);
        // Nothing else goes while an orbit runs, idle or not.
        assert_eq!(taken(source.take(false, &judge)), None);
        assert_eq!(taken(source.take(true, &judge)), None);
        source.ended(go_entry, None, 5);
        // No orbit runs now: with every lane idle the deferred cell goes after a wait.
        assert_eq!(taken(source.take(false, &judge)), None);
        let later_entry = match source.take(true, &judge) {
            Take::Insist(e) => e,
            _ => panic!("a deferred cell goes, insisted on, when nothing runs"),
        };
        assert_eq!(later_entry as u32, later);
        let mut report = || {
            std::iter::from_fn(|| rx.try_recv().ok()).find_map(|d| match d {
                Done::Report(r) => Some(r),
                _ => None,
            })
        };
        assert!(report().is_none(), "the lease has not ended yet");
        source.ended(later_entry, None, 7);
        // Every cell ended (one dropped, two abandoned): the lease's finishing report.
        let r = report().expect("a finishing report");
        assert!(r.finished && r.outcomes.is_empty());
        assert_eq!((r.abandoned_orbits, r.abandoned_steps), (2, 12));
    }
}
