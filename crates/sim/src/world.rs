//! Virtual time: the queue of what happens next, and what every simulated party shares.

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
    /// The coordinator finished answering a poll.
    Served,
    /// The coordinator's reply reaches the worker.
    Reply { worker: usize },
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
    /// Virtual nanoseconds since the workers started.
    pub now: u64,
    queue: BinaryHeap<Reverse<(u64, u64, Event)>>,
    /// Orders events of the same moment by when they were scheduled.
    seq: u64,
    pub traces: Vec<Traces>,
    pub grid: Grid,
    rng: u64,
}

impl World {
    pub fn new(grid: Grid, traces: Vec<Traces>, seed: u64) -> Self {
        World {
            now: 0,
            queue: BinaryHeap::new(),
            seq: 0,
            traces,
            grid,
            rng: seed,
        }
    }

    /// Schedules `event` at `time` (never before now).
    pub fn at(&mut self, time: u64, event: Event) {
        self.seq += 1;
        self.queue
            .push(Reverse((time.max(self.now), self.seq, event)));
    }

    /// The next event, with the clock moved to it.
    pub fn pop(&mut self) -> Option<Event> {
        let Reverse((time, _, event)) = self.queue.pop()?;
        self.now = time;
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
