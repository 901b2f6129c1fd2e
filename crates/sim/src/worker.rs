//! A simulated worker: the network loop of `salient worker` (polls, leases, skips, relays,
//! reports) and its streams of leased cells in lanes, in virtual time. Every decision about a
//! cell — start it, defer it, drop it, abandon its orbit — is taken by the product's own
//! [`Claims`] and local ledger, exactly as a worker's stream takes it; only the orbits are
//! replayed from their traces instead of integrated.

use crate::world::{Event, World};
use salient_grid::executor::{Claims, LocalLedger, OrbitTrace, Verdict};
use salient_grid::Mode;
use salient_proto::v1;
use salient_proto::{outcome_from_wire, push_partial, Expected};
use salient_worker::{crossings_of_held, free_slots, lease_key, LeaseKey};
use std::collections::{BTreeMap, HashMap, HashSet, VecDeque};
use std::sync::Arc;

/// How long an idle stream whose waiting cells are all deferred waits before it starts the
/// first anyway: the worker's own wait.
const FORCE_AFTER_NS: u64 = salient_worker::IDLE_WAIT.as_nanos() as u64;

/// A worker's first poll comes after its shortest idle wait.
pub const FIRST_POLL_NS: u64 = 2_000_000;

/// How the simulated workers are built.
#[derive(Clone, Copy, Debug)]
pub struct Shape {
    pub threads: usize,
    /// Orbits a thread runs at once.
    pub lanes: usize,
    /// CPU nanoseconds a lane takes per step (its thread steps all its lanes together).
    pub lane_step_ns: f64,
    /// Steps between two checks of a running orbit for abandonment.
    pub poll_steps: u64,
    /// Leases held at once in full mode (fast PSS takes one at a time).
    pub max_leases: usize,
    /// The coordinator's poll interval while busy, in nanoseconds.
    pub busy_poll_ns: u64,
    /// Running orbits' crossings are told (`executor::tells_crossings`).
    pub tells_crossings: bool,
}

struct RunState {
    local: LocalLedger,
    relayed: u64,
}

struct Entry {
    cell: u32,
    lease: LeaseKey,
}

/// The cells of consecutive leases of one run, taken in lease order; a lease of another run
/// starts a new stream once this one has run dry (the worker's compute thread runs one stream
/// at a time).
struct Stream {
    run: u32,
    queue: VecDeque<Entry>,
    closed: bool,
}

struct LeaseProgress {
    lease: v1::TileRef,
    left: usize,
    abandoned: (u64, u64),
    steps: u64,
}

struct Running {
    cell: u32,
    run: u32,
    lease: LeaseKey,
    /// The CPU clock when it started (its thread's lanes advance on the CPU clock).
    start_cpu: f64,
    trace: Arc<OrbitTrace>,
    /// The next crossing of `trace` to replay.
    next: usize,
    insisted: bool,
    /// An abandonment is due at the next check.
    abandoning: bool,
    /// Its crossings so far were claimed when it became the frontier.
    claimed_all: bool,
    /// Cells it crossed that were said to the coordinator.
    said: HashSet<u32>,
}

/// Where a leased cell stands at its worker ([`SimWorker::leased_cell`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum LeasedCell {
    /// In a stream, or its lease on the way.
    Waiting,
    Running,
    /// Its orbit ended; the coordinator has not had the outcome yet.
    Reporting,
}

/// Totals of one simulated worker.
#[derive(Clone, Copy, Debug, Default)]
pub struct WorkerTotals {
    pub orbits_finished: u64,
    pub orbits_abandoned: u64,
    pub steps: u64,
    pub polls: u64,
}

pub struct SimWorker {
    pub index: usize,
    pub id: String,
    job: u64,
    shape: Shape,
    mode: Mode,
    runs: HashMap<u32, RunState>,
    streams: VecDeque<Stream>,
    leases: HashMap<LeaseKey, LeaseProgress>,
    running: HashMap<u64, Running>,
    next_orbit: u64,
    revoked: HashSet<LeaseKey>,
    hungry_said: bool,
    /// No orbit runs and no waiting cell went: the stream sleeps until a lease comes or
    /// [`FORCE_AFTER_NS`] pass (outcomes relayed meanwhile wake it no sooner, as in the
    /// worker, whose idle lanes wait on a condition that only leases and ended orbits signal).
    asleep: bool,
    force_gen: u64,
    // The network side.
    held: Vec<v1::TileRef>,
    outbox: Vec<v1::TileReport>,
    partial: Vec<v1::TileReport>,
    /// Crossings of running orbits not yet said, and whether the orbit was abandoned since,
    /// by (lease, orbit's cell): ordered, so that a seed gives one schedule.
    crossings: BTreeMap<(LeaseKey, u32), (Vec<u32>, bool)>,
    /// Cells whose outcomes wait for the next poll, and those the poll in flight carries.
    unsent: HashSet<u32>,
    sent: HashSet<u32>,
    hungry_compute: bool,
    hungry_backoff_ns: u64,
    pub in_flight: bool,
    wake_pending: bool,
    pub timer_gen: u64,
    /// Compute threads with an orbit running, as counted in the world's busy threads.
    busy_threads: usize,
    pub totals: WorkerTotals,
}

impl SimWorker {
    pub fn new(index: usize, id: String, job: u64, shape: Shape, mode: Mode) -> Self {
        SimWorker {
            index,
            id,
            job,
            shape,
            mode,
            runs: HashMap::new(),
            streams: VecDeque::new(),
            leases: HashMap::new(),
            running: HashMap::new(),
            next_orbit: 0,
            revoked: HashSet::new(),
            hungry_said: false,
            asleep: false,
            force_gen: 0,
            held: Vec::new(),
            outbox: Vec::new(),
            partial: Vec::new(),
            crossings: BTreeMap::new(),
            unsent: HashSet::new(),
            sent: HashSet::new(),
            hungry_compute: false,
            hungry_backoff_ns: FIRST_POLL_NS,
            in_flight: false,
            wake_pending: false,
            timer_gen: 0,
            busy_threads: 0,
            totals: WorkerTotals::default(),
        }
    }

    /// Where `cell`, leased here, stands.
    pub fn leased_cell(&self, cell: u32) -> LeasedCell {
        if self.running.values().any(|r| r.cell == cell) {
            LeasedCell::Running
        } else if self.unsent.contains(&cell) || self.sent.contains(&cell) {
            LeasedCell::Reporting
        } else {
            LeasedCell::Waiting
        }
    }

    /// Orbits running in this worker's lanes.
    pub fn running_orbits(&self) -> usize {
        self.running.len()
    }

    fn lanes(&self) -> usize {
        self.shape.threads * self.shape.lanes
    }

    /// Tells the world how many of this worker's compute threads are busy: those whose lanes
    /// hold the running orbits, filled one thread at a time.
    fn count_busy(&mut self, world: &mut World) {
        let busy = self
            .running
            .len()
            .div_ceil(self.shape.lanes)
            .min(self.shape.threads);
        world.add_busy(busy as isize - self.busy_threads as isize);
        self.busy_threads = busy;
    }

    /// Leases to ask for: the worker's own rule.
    fn free_slots(&self) -> usize {
        free_slots(
            self.held.len(),
            self.hungry_compute,
            self.mode == Mode::FastPss,
            self.shape.max_leases,
        )
    }

    /// Schedules the next poll `delay_ns` from now (replacing any timer set before).
    pub fn schedule_send(&mut self, world: &mut World, delay_ns: u64) {
        self.timer_gen += 1;
        world.at(
            world.now + delay_ns,
            Event::Send {
                worker: self.index,
                gen: self.timer_gen,
            },
        );
    }

    /// The compute side handed something to the network side (a report, or hunger): the
    /// worker polls at once, or right after the poll in flight.
    fn wake(&mut self, world: &mut World) {
        if self.in_flight {
            self.wake_pending = true;
        } else {
            self.schedule_send(world, 0);
        }
    }

    /// The poll the network side sends now.
    pub fn poll_request(&mut self) -> v1::PollRequest {
        self.collect_partial();
        self.totals.polls += 1;
        self.in_flight = true;
        self.sent = std::mem::take(&mut self.unsent);
        v1::PollRequest {
            worker_id: self.id.clone(),
            free_slots: self.free_slots() as u32,
            held: self.held.clone(),
            reports: std::mem::take(&mut self.outbox),
            draining: false,
            // Those of held leases, as the worker sends them.
            crossings: crossings_of_held(std::mem::take(&mut self.crossings), &self.held),
            relayed: self
                .runs
                .iter()
                .map(|(&run, r)| v1::RelayMark {
                    job: self.job,
                    run,
                    next: r.relayed,
                    own: false,
                })
                .collect(),
        }
    }

    fn collect_partial(&mut self) {
        let held = &self.held;
        self.outbox.extend(
            std::mem::take(&mut self.partial)
                .into_iter()
                .filter(|r| held.iter().any(|h| Some(h) == r.lease.as_ref())),
        );
    }

    /// The coordinator's reply arrived.
    pub fn on_reply(&mut self, world: &mut World, reply: v1::PollReply) -> Result<(), String> {
        self.in_flight = false;
        self.sent.clear();
        for skip in &reply.skips {
            if let Some(l) = skip.lease {
                if let Some(r) = self.runs.get(&l.run) {
                    let claims = r.local.claims();
                    skip.cells.iter().for_each(|&c| claims.claim(c));
                }
            }
        }
        for r in &reply.revoked {
            self.revoked.insert(lease_key(r));
            self.held.retain(|h| h != r);
            self.outbox.retain(|o| o.lease.as_ref() != Some(r));
        }
        self.hungry_backoff_ns = if reply.leases.is_empty() {
            (self.hungry_backoff_ns * 2).min(self.shape.busy_poll_ns)
        } else {
            FIRST_POLL_NS
        };
        for lease in reply.leases {
            let Some(tile) = lease.lease else { continue };
            let run = tile.run;
            world.traces[run as usize].ensure(&lease.cells);
            if self.mode == Mode::FastPss {
                let grid = &world.grid;
                self.runs.entry(run).or_insert_with(|| RunState {
                    local: LocalLedger::new(grid, Mode::FastPss),
                    relayed: 0,
                });
            }
            self.hungry_compute = false;
            self.held.push(tile);
            self.add(world, tile, lease.cells);
        }
        for relay in &reply.relays {
            let Some(r) = self.runs.get_mut(&relay.run) else {
                continue;
            };
            for encoded in &relay.outcomes {
                let o = <v1::Outcome as prost::Message>::decode(&encoded[..])
                    .map_err(|e| e.to_string())?;
                let o = outcome_from_wire(&o, r.local.grid(), Expected::as_sent(&o))?;
                r.local.offer(o);
            }
            r.relayed = relay.next;
        }
        self.settle(world);
        let idle = if self.wake_pending || !self.outbox.is_empty() {
            0
        } else if self.free_slots() > 0 {
            self.hungry_backoff_ns.min(self.shape.busy_poll_ns)
        } else {
            self.shape.busy_poll_ns
        };
        self.wake_pending = false;
        self.schedule_send(world, idle);
        Ok(())
    }

    /// A lease's cells join the stream of its run.
    fn add(&mut self, world: &mut World, lease: v1::TileRef, cells: Vec<u32>) {
        let key = lease_key(&lease);
        if let Some(r) = self.runs.get(&lease.run) {
            // The coordinator leases a cell only when it needs it: an earlier skip no longer
            // holds.
            cells.iter().for_each(|&c| r.local.claims().unclaim(c));
        }
        self.hungry_said = false;
        self.asleep = false;
        self.leases.insert(
            key,
            LeaseProgress {
                lease,
                left: cells.len(),
                abandoned: (0, 0),
                steps: 0,
            },
        );
        if cells.is_empty() {
            self.end_lease(world, key, Vec::new());
            return;
        }
        let entries = cells.into_iter().map(|cell| Entry { cell, lease: key });
        match self.streams.back_mut() {
            Some(s) if s.run == lease.run && !s.closed => s.queue.extend(entries),
            _ => {
                if let Some(s) = self.streams.back_mut() {
                    s.closed = true;
                }
                self.streams.push_back(Stream {
                    run: lease.run,
                    queue: entries.collect(),
                    closed: false,
                });
            }
        }
    }

    fn claims(&self, run: u32) -> Option<&Claims> {
        self.runs.get(&run).map(|r| r.local.claims())
    }

    /// After any change: orbits that became the frontier claim what they crossed, orbits now
    /// labelled elsewhere are abandoned at their next check, and free lanes take cells.
    pub fn settle(&mut self, world: &mut World) {
        let ids: Vec<u64> = self.running.keys().copied().collect();
        for &id in &ids {
            let r = self.running.get_mut(&id).expect("running");
            let Some(state) = self.runs.get(&r.run) else {
                continue;
            };
            let claims = state.local.claims();
            if !r.claimed_all && claims.is_frontier(r.cell) {
                for &(to, _) in &r.trace.crossings[..r.next] {
                    claims.stream_crossed(&world.grid, r.cell, to);
                }
                r.claimed_all = true;
            }
        }
        for id in ids {
            self.check(world, id);
        }
        self.fill(world);
    }

    /// Schedules the abandonment of orbit `id` at its next check if its cell is labelled
    /// elsewhere (certainly, or probably unless insisted on).
    fn check(&mut self, world: &mut World, id: u64) {
        let Some(r) = self.running.get(&id) else {
            return;
        };
        if r.abandoning {
            return;
        }
        let Some(claims) = self.claims(r.run) else {
            return;
        };
        if !claims.stream_cancels(&world.grid, r.cell, r.insisted) {
            return;
        }
        let done = ((world.cpu_now - r.start_cpu) / self.shape.lane_step_ns) as u64;
        let boundary = (done / self.shape.poll_steps + 1) * self.shape.poll_steps;
        if boundary >= r.trace.outcome.steps {
            return; // it ends before its next check
        }
        let at = r.start_cpu + boundary as f64 * self.shape.lane_step_ns;
        self.running.get_mut(&id).expect("running").abandoning = true;
        world.at_cpu(
            at,
            Event::Abandon {
                worker: self.index,
                orbit: id,
            },
        );
    }

    /// Free lanes take the next cells their stream lets go; a lane left without one makes the
    /// worker hungry.
    fn fill(&mut self, world: &mut World) {
        if self.asleep {
            return;
        }
        while self.running.len() < self.lanes() {
            match self.take(world, false) {
                Some((entry, insisted)) => self.start(world, entry, insisted),
                None => break,
            }
        }
        if self.running.len() < self.lanes() {
            if !self.hungry_said {
                self.hungry_said = true;
                self.hungry_compute = true;
                self.wake(world);
            }
            if self.running.is_empty() {
                self.asleep = true;
                self.force_gen += 1;
                world.at(
                    world.now + FORCE_AFTER_NS,
                    Event::Force {
                        worker: self.index,
                        gen: self.force_gen,
                    },
                );
            }
        }
    }

    /// Nothing ran for a while and the waiting cells are all deferred: the first goes anyway.
    pub fn on_force(&mut self, world: &mut World, gen: u64) {
        if gen != self.force_gen || !self.asleep {
            return;
        }
        self.asleep = false;
        if let Some((entry, insisted)) = self.take(world, true) {
            self.start(world, entry, insisted);
        }
        self.fill(world);
    }

    /// The first waiting entry of the current stream its claims let go (with `force`, the
    /// first deferred one when none goes); entries dropped on the way end without an outcome.
    fn take(&mut self, world: &mut World, force: bool) -> Option<(Entry, bool)> {
        loop {
            let front = self.streams.front()?;
            let run = front.run;
            let running_here = self.running.values().any(|r| r.run == run);
            if front.queue.is_empty() {
                if front.closed && !running_here {
                    self.streams.pop_front();
                    continue;
                }
                return None;
            }
            let claims = self.runs.get(&run).map(|r| r.local.claims());
            let mut dropped = Vec::new();
            let mut pick = None;
            let mut first_later = None;
            for (i, e) in front.queue.iter().enumerate() {
                let verdict = if self.revoked.contains(&e.lease) {
                    Verdict::Drop
                } else {
                    claims.map_or(Verdict::Go, |c| c.stream_verdict(&world.grid, e.cell))
                };
                match verdict {
                    Verdict::Drop => dropped.push(i),
                    Verdict::Later => {
                        first_later.get_or_insert(i);
                    }
                    Verdict::Go => {
                        pick = Some((i, false));
                        break;
                    }
                }
            }
            if pick.is_none() && force {
                pick = first_later.map(|i| (i, true));
            }
            let queue = &mut self.streams.front_mut().expect("front").queue;
            let picked = pick.map(|(i, insisted)| (queue[i].cell, queue[i].lease, insisted));
            let mut ended = Vec::new();
            let mut k = 0;
            queue.retain(|e| {
                let i = k;
                k += 1;
                let drop = dropped.contains(&i) || pick.is_some_and(|(p, _)| p == i);
                if dropped.contains(&i) {
                    ended.push(e.lease);
                }
                !drop
            });
            for lease in ended {
                self.end_entry(world, lease, None, 0);
            }
            return picked.map(|(cell, lease, insisted)| (Entry { cell, lease }, insisted));
        }
    }

    fn start(&mut self, world: &mut World, entry: Entry, insisted: bool) {
        let run = self.streams.front().map_or(0, |s| s.run);
        if let Some(c) = self.claims(run) {
            c.set_running(entry.cell, true);
        }
        let trace = world.traces[run as usize].get(entry.cell);
        let id = self.next_orbit;
        self.next_orbit += 1;
        self.running.insert(
            id,
            Running {
                cell: entry.cell,
                run,
                lease: entry.lease,
                start_cpu: world.cpu_now,
                trace,
                next: 0,
                insisted,
                abandoning: false,
                claimed_all: false,
                said: HashSet::new(),
            },
        );
        self.schedule_next(world, id);
        self.count_busy(world);
    }

    /// The orbit's next event: its next crossing, or its end.
    fn schedule_next(&mut self, world: &mut World, id: u64) {
        let r = &self.running[&id];
        let at_step = |s: u64| r.start_cpu + s as f64 * self.shape.lane_step_ns;
        let event = match r.trace.crossings.get(r.next) {
            Some(&(_, step)) => (
                at_step(step),
                Event::Crossing {
                    worker: self.index,
                    orbit: id,
                },
            ),
            None => (
                at_step(r.trace.outcome.steps),
                Event::End {
                    worker: self.index,
                    orbit: id,
                },
            ),
        };
        world.at_cpu(event.0, event.1);
    }

    pub fn on_crossing(&mut self, world: &mut World, id: u64) {
        let Some(r) = self.running.get_mut(&id) else {
            return;
        };
        let (to, _) = r.trace.crossings[r.next];
        r.next += 1;
        let (from, run) = (r.cell, r.run);
        let claims = self.runs.get(&run).map(|s| s.local.claims());
        // Asked first, as the worker's stream does: the frontier's orbit claims what it crosses.
        let tell = self.shape.tells_crossings && claims.is_some_and(|c| c.worth_telling(from, to));
        if tell && r.said.insert(to) {
            let said = self.crossings.entry((r.lease, from)).or_default();
            said.0.push(to);
        }
        if let Some(c) = claims {
            c.stream_crossed(&world.grid, from, to);
        }
        self.schedule_next(world, id);
        // Only the orbit of the cell crossed can have become labelled elsewhere.
        let crossed: Vec<u64> = self
            .running
            .iter()
            .filter(|(_, r)| r.cell == to && r.run == run)
            .map(|(&k, _)| k)
            .collect();
        for k in crossed {
            self.check(world, k);
        }
    }

    pub fn on_end(&mut self, world: &mut World, id: u64) {
        let Some(r) = self.running.remove(&id) else {
            return;
        };
        let outcome = r.trace.outcome.clone();
        let steps = outcome.steps;
        if let Some(state) = self.runs.get(&r.run) {
            state.local.claims().set_running(r.cell, false);
            state.local.offer(outcome.clone());
        }
        self.count_busy(world);
        self.totals.orbits_finished += 1;
        self.totals.steps += steps;
        self.unsent.insert(r.cell);
        self.end_entry(world, r.lease, Some(outcome), steps);
        self.settle(world);
    }

    pub fn on_abandon(&mut self, world: &mut World, id: u64) {
        let Some(r) = self.running.get_mut(&id) else {
            return;
        };
        r.abandoning = false;
        let still = self.runs.get(&r.run).is_some_and(|s| {
            s.local
                .claims()
                .stream_cancels(&world.grid, r.cell, r.insisted)
        });
        if !still {
            return;
        }
        let r = self.running.remove(&id).expect("running");
        let steps = (((world.cpu_now - r.start_cpu) / self.shape.lane_step_ns).round() as u64)
            .min(r.trace.outcome.steps);
        if let Some(state) = self.runs.get(&r.run) {
            state.local.claims().set_running(r.cell, false);
        }
        self.count_busy(world);
        self.totals.orbits_abandoned += 1;
        self.totals.steps += steps;
        if steps > 0 {
            self.crossings.entry((r.lease, r.cell)).or_default().1 = true;
        }
        self.end_entry(world, r.lease, None, steps);
        self.settle(world);
    }

    /// An entry's end: its outcome to the next poll, and the lease's finishing report once
    /// every entry of it ended.
    fn end_entry(
        &mut self,
        world: &mut World,
        key: LeaseKey,
        outcome: Option<salient_grid::Outcome>,
        steps: u64,
    ) {
        let Some(p) = self.leases.get_mut(&key) else {
            return;
        };
        p.left -= 1;
        p.steps += steps;
        if outcome.is_none() && steps > 0 {
            p.abandoned.0 += 1;
            p.abandoned.1 += steps;
        }
        let out = outcome.as_ref().map(v1::Outcome::from);
        if p.left == 0 {
            self.end_lease(world, key, out.into_iter().collect());
        } else if let Some(o) = out {
            push_partial(&mut self.partial, p.lease, o);
        }
    }

    /// The lease's finishing report goes out with a poll at once.
    fn end_lease(&mut self, world: &mut World, key: LeaseKey, outcomes: Vec<v1::Outcome>) {
        let Some(p) = self.leases.remove(&key) else {
            return;
        };
        self.revoked.remove(&key);
        if !self.held.contains(&p.lease) {
            return; // revoked: its report would be stale
        }
        self.collect_partial();
        self.held.retain(|h| *h != p.lease);
        let cpu_ns = (p.steps as f64 * self.shape.lane_step_ns / self.shape.lanes as f64) as u64;
        self.outbox.push(v1::TileReport {
            lease: Some(p.lease),
            outcomes,
            finished: true,
            cpu_ns,
            abandoned_orbits: p.abandoned.0,
            abandoned_steps: p.abandoned.1,
        });
        self.wake(world);
    }
}
