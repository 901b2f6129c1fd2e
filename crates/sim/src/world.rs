//! Virtual time: the queues of what happens next, and what every simulated party shares.
//!
//! Two clocks: the wall clock, and a CPU clock that measures the CPU time one busy thread has
//! had since the start. Messages in transit and timers wait on the wall clock; computing (a
//! lane's steps, the coordinator's answer, the work of each side's network stack) waits on
//! the CPU clock. With a core per busy thread the two run together; on a host of `cores`
//! shared by more busy threads (the coordinator and workers on one machine), the CPU clock
//! runs at cores / busy threads of the wall's speed: every busy thread gets an equal share,
//! as the kernel's fair scheduler gives it.

use crate::traces::Traces;
use salient_grid::Grid;
use std::cmp::Reverse;
use std::collections::BinaryHeap;

/// What happens at a moment of virtual time.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord)]
pub enum Event {
    /// A worker's network side sends its poll (unless a later timer replaced this one).
    Send { worker: usize, gen: u64 },
    /// A poll reaches the coordinator.
    Arrive { worker: usize },
    /// A poll passed the coordinator's network stack and waits for the scheduler.
    Received { worker: usize },
    /// The scheduler finished answering a worker's poll.
    Served { worker: usize },
    /// The reply passed the coordinator's network stack and leaves.
    Sent { worker: usize },
    /// The coordinator's reply reaches the worker's host.
    Reply { worker: usize },
    /// The worker's network side has read the reply.
    Read { worker: usize },
    /// A running orbit crosses its next cell.
    Crossing { worker: usize, orbit: u64 },
    /// A running orbit reaches its end.
    End { worker: usize, orbit: u64 },
    /// A running orbit's check that abandons it.
    Abandon { worker: usize, orbit: u64 },
    /// An idle stream starts a deferred cell anyway.
    Force { worker: usize, gen: u64 },
}

pub struct World {
    /// Wall nanoseconds since the workers started.
    pub now: u64,
    /// The CPU clock, in nanoseconds (see the module's documentation).
    pub cpu_now: f64,
    wall_queue: BinaryHeap<Reverse<(u64, u64, Event)>>,
    cpu_queue: BinaryHeap<Reverse<(u64, u64, Event)>>,
    /// Orders events of the same moment by when they were scheduled.
    seq: u64,
    pub traces: Vec<Traces>,
    pub grid: Grid,
    rng: u64,
    /// Cores shared by every party, or `None`: each busy thread has a core of its own.
    cores: Option<f64>,
    /// Threads busy now.
    busy: usize,
}

impl World {
    pub fn new(grid: Grid, traces: Vec<Traces>, seed: u64, cores: Option<f64>) -> Self {
        World {
            now: 0,
            cpu_now: 0.0,
            wall_queue: BinaryHeap::new(),
            cpu_queue: BinaryHeap::new(),
            seq: 0,
            traces,
            grid,
            rng: seed,
            cores,
            busy: 0,
        }
    }

    /// Schedules `event` at wall time `time` (never before now).
    pub fn at(&mut self, time: u64, event: Event) {
        self.seq += 1;
        self.wall_queue
            .push(Reverse((time.max(self.now), self.seq, event)));
    }

    /// Schedules `event` at CPU time `cpu` (never before now).
    pub fn at_cpu(&mut self, cpu: f64, event: Event) {
        self.seq += 1;
        let key = cpu.max(self.cpu_now).ceil() as u64;
        self.cpu_queue.push(Reverse((key, self.seq, event)));
    }

    /// Schedules `event` once a thread busy from now has had `work_ns` of CPU.
    pub fn after_cpu(&mut self, work_ns: f64, event: Event) {
        self.at_cpu(self.cpu_now + work_ns, event);
    }

    /// A thread starts (`+1`) or stops (`-1`) being busy.
    /// Threads busy now (compute, and either side's network work).
    pub fn busy(&self) -> usize {
        self.busy
    }

    pub fn add_busy(&mut self, delta: isize) {
        self.busy = self.busy.saturating_add_signed(delta);
    }

    /// CPU nanoseconds a busy thread gets per wall nanosecond now.
    fn rate(&self) -> f64 {
        match self.cores {
            Some(cores) if self.busy as f64 > cores => cores / self.busy as f64,
            _ => 1.0,
        }
    }

    /// The next event, with both clocks moved to it.
    pub fn pop(&mut self) -> Option<Event> {
        let wall = self
            .wall_queue
            .peek()
            .map(|Reverse((t, s, _))| (*t as f64, *s));
        let rate = self.rate();
        let cpu = self.cpu_queue.peek().map(|Reverse((c, s, _))| {
            let wait = (*c as f64 - self.cpu_now).max(0.0) / rate;
            (self.now as f64 + wait, *s, *c as f64)
        });
        let (time, event, cpu_key) = match (wall, cpu) {
            (None, None) => return None,
            (Some((t, _)), Some((tc, _, _))) if t <= tc => {
                let Reverse((_, _, e)) = self.wall_queue.pop().expect("peeked");
                (t, e, None)
            }
            (Some((t, _)), None) => {
                let Reverse((_, _, e)) = self.wall_queue.pop().expect("peeked");
                (t, e, None)
            }
            (_, Some((tc, _, c))) => {
                let Reverse((_, _, e)) = self.cpu_queue.pop().expect("peeked");
                (tc, e, Some(c))
            }
        };
        let time = time.max(self.now as f64);
        self.cpu_now += (time - self.now as f64) * rate;
        if let Some(c) = cpu_key {
            self.cpu_now = self.cpu_now.max(c);
        }
        self.now = time.round() as u64;
        Some(event)
    }

    /// A pseudo-random number in [-1, 1] (splitmix64: the same sequence for the same seed).
    pub fn unit(&mut self) -> f64 {
        self.rng = self.rng.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.rng;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^= z >> 31;
        (z >> 11) as f64 / (1u64 << 52) as f64 - 1.0
    }
}
