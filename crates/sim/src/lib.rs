//! The scaling simulator: the coordinator's real [`Scheduler`] — leases, ledger, skips, relays,
//! its store in memory — answering W simulated workers in virtual time. Each worker runs the
//! product's stream decisions (the claims and local ledger of `salient worker`) over orbits
//! replayed from real integrations ([`traces`]): every orbit a worker starts is integrated for
//! real once, and its steps and crossings then take virtual time at a calibrated cost per step.
//! The coordinator is one server: each poll waits for the polls before it and takes the CPU
//! time the scheduler really spent on it (decoding, answering, encoding), so its saturation
//! shows. Network latency, bandwidth, threads, lanes, poll interval and lease sizes are
//! parameters. Results are byte-identical whatever the schedule, so only time and work are
//! simulated.

mod traces;
mod worker;
mod world;

use prost::Message;
use salient_coordinator::scheduler::{Config, FrontierCell, Progress, Scheduler};
pub use salient_core::engine::thread_cpu_ns;
use salient_grid::spec::{self, JobSpec};
use salient_grid::{executor, Forecast, Grid, Ledger, Mode};
use salient_proto::{v1, PROTOCOL_VERSION};
use salient_store::Store;
use serde::Serialize;
use std::collections::{HashMap, VecDeque};
pub use traces::calibrate_step_ns;
use traces::Traces;
use tracing::subscriber::NoSubscriber;
use worker::{LeasedCell, Shape, SimWorker, FIRST_POLL_NS};
use world::{Event, World};

/// Where the coordinator's forecast of each cell's labeller comes from.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum ForecastSource {
    /// No forecast: leases from a window past the frontier.
    None,
    /// The labellers of the job's own result: the best any forecast can do.
    Perfect,
    /// The labellers of a pilot run of the same grid and method to this t_final (its cost is
    /// not simulated).
    Pilot(f64),
}

/// What is simulated besides the spec.
#[derive(Clone, Copy, Debug)]
pub struct Params {
    /// Threads of each worker.
    pub threads: usize,
    /// Orbits a worker thread runs at once; `None`: what the product runs (the stepper's lanes
    /// for tangent-map methods, the adaptive driver's orbits per thread otherwise).
    pub lanes: Option<usize>,
    /// Round trip between a worker and the coordinator, without the transfer.
    pub rtt_ns: u64,
    /// Bytes per second each way.
    pub bandwidth: f64,
    /// Each one-way latency varies by up to this fraction, from a seeded sequence.
    pub jitter: f64,
    /// Seed of the pseudo-random sequence the jitter comes from.
    pub seed: u64,
    /// The coordinator's timing and lease sizes.
    pub config: Config,
    /// Leases a worker holds at once in full mode.
    pub max_leases: usize,
    /// CPU nanoseconds per step of one orbit in a thread's full lanes; `None`: calibrated on
    /// this machine.
    pub step_ns: Option<f64>,
    /// Nanoseconds the coordinator takes per poll; `None`: the CPU time the scheduler really
    /// takes (then the simulated times vary from run to run by the measurement's noise).
    pub coordinator_ns: Option<u64>,
    /// CPU nanoseconds the coordinator's network stack and store spend on a poll besides the
    /// scheduler (half on the way in, half on the way out); threads of their own, so polls
    /// pass through it side by side.
    pub coordinator_stack_ns: u64,
    /// CPU nanoseconds a worker's network side spends on a poll round (reading the reply,
    /// handing leases and relays over) before its lanes see the reply.
    pub worker_stack_ns: u64,
    /// Cores shared by the coordinator and every worker (all on one host), or `None`: every
    /// busy thread has a core of its own.
    pub host_cores: Option<f64>,
    /// The coordinator's forecast of who labels each cell.
    pub forecast: ForecastSource,
    /// Virtual seconds without a new outcome after which the simulation reports a stall.
    pub stall_s: f64,
}

/// Default of [`Params::coordinator_stack_ns`]: measured on the project's 2-core EPYC host,
/// the coordinator's gRPC runtime and store threads' CPU over a fast-PSS job's polls
/// (docs/distributed.md).
pub const COORDINATOR_STACK_NS: u64 = 430_000;

/// Default of [`Params::worker_stack_ns`], measured with it.
pub const WORKER_STACK_NS: u64 = 250_000;

impl Default for Params {
    fn default() -> Self {
        Params {
            threads: 1,
            lanes: None,
            rtt_ns: 500_000,
            bandwidth: 1.25e9,
            jitter: 0.1,
            seed: 1,
            config: Config::default(),
            max_leases: 2,
            step_ns: None,
            coordinator_ns: None,
            coordinator_stack_ns: COORDINATOR_STACK_NS,
            worker_stack_ns: WORKER_STACK_NS,
            host_cores: None,
            forecast: ForecastSource::None,
            stall_s: 600.0,
        }
    }
}

/// Cells the sequential rule's ledger takes per round when [`Simulation::sequential`] traces
/// them: enough to fill every thread's lanes.
const SEQUENTIAL_ROUND: usize = 256;

/// One simulated job with W workers.
#[derive(Clone, Debug, Default, Serialize)]
pub struct RunStats {
    /// Workers W.
    pub workers: usize,
    /// From the first lease to the job's end, virtual seconds.
    pub wall_s: f64,
    /// Orbits integrated to their end.
    pub orbits_finished: u64,
    /// Orbits abandoned before their end (their cell already labelled).
    pub orbits_abandoned: u64,
    /// Steps integrated by all workers, abandoned orbits' included.
    pub steps: u64,
    /// Polls the workers sent.
    pub polls: u64,
    /// Leases the coordinator granted.
    pub leases: u64,
    /// Cells in those leases.
    pub leased_cells: u64,
    /// Outcomes the coordinator received.
    pub outcomes: u64,
    /// CPU seconds the scheduler spent answering polls.
    pub coordinator_cpu_s: f64,
    /// Seconds the coordinator was busy (its CPU, or the fixed cost per poll).
    pub coordinator_busy_s: f64,
    /// Bytes of the encoded poll requests.
    pub request_bytes: u64,
    /// Bytes of the encoded poll replies.
    pub reply_bytes: u64,
    /// Of the replies: relayed outcomes.
    pub relay_bytes: u64,
    /// How long the commits waited for the frontier cell, by where it stood.
    pub frontier: FrontierWait,
    /// Samples of the job's progress over virtual time (written to timeline.csv, not to the
    /// table's JSON).
    #[serde(skip)]
    pub timeline: Vec<Sample>,
}

/// Virtual seconds the commits waited for the cell at the frontier, which needed its own orbit,
/// by where that cell stood: the commit chain's share of the wall. A schedule that ran needed
/// orbits early has their outcomes in before the frontier reaches them, and waits little.
#[derive(Clone, Copy, Debug, Default, Serialize)]
pub struct FrontierWait {
    /// No lease held it.
    pub unleased_s: f64,
    /// Leased, waiting in its worker's queue (or for the lease to reach the worker).
    pub queued_s: f64,
    /// Its own orbit running.
    pub running_s: f64,
    /// Its orbit ended; the outcome is on its way (it waits for the worker's next poll).
    pub reporting_s: f64,
    /// Its tile leased without it (claimed or skipped when that lease was made).
    pub stranded_s: f64,
}

impl FrontierWait {
    fn add(
        &mut self,
        cell: Option<FrontierCell>,
        ws: &[SimWorker],
        index: &HashMap<&str, usize>,
        ns: u64,
    ) {
        let s = ns as f64 * 1e-9;
        match cell {
            None => {}
            Some(FrontierCell::Unleased(_)) => self.unleased_s += s,
            Some(FrontierCell::Stranded(_)) => self.stranded_s += s,
            Some(FrontierCell::Leased { cell, worker }) => {
                let at = index.get(worker).map(|&w| ws[w].leased_cell(cell));
                match at.unwrap_or(LeasedCell::Waiting) {
                    LeasedCell::Waiting => self.queued_s += s,
                    LeasedCell::Running => self.running_s += s,
                    LeasedCell::Reporting => self.reporting_s += s,
                }
            }
        }
    }
}

/// The state of a simulated job at one moment: where a run that scales badly stalls shows as
/// lanes idle while the committed orbits stand still.
#[derive(Clone, Copy, Debug, Default)]
pub struct Sample {
    /// Virtual seconds since the workers started.
    pub t_s: f64,
    /// Orbits running in the workers' lanes.
    pub running_orbits: usize,
    /// Threads busy: computing, or in either side's network stack.
    pub busy_threads: usize,
    /// The scheduler's progress of the job.
    pub progress: Progress,
}

/// Samples a timeline keeps at most: when full, every other one goes and the interval doubles,
/// so a run of any length leaves between half and all of them.
const TIMELINE_SAMPLES: usize = 2000;

/// The first interval between timeline samples, virtual nanoseconds.
const FIRST_SAMPLE_NS: u64 = 1_000_000;

/// What the sequential rule integrates: every cell's own orbit in canonical order unless an
/// earlier orbit labelled it.
#[derive(Clone, Copy, Debug, Default, Serialize)]
pub struct Sequential {
    /// Orbits integrated.
    pub orbits: u64,
    /// Steps of those orbits.
    pub steps: u64,
    /// Steps of the longest of those orbits.
    pub longest_steps: u64,
}

/// One row of a scaling table.
#[derive(Clone, Debug, Serialize)]
pub struct Point {
    /// The simulated job's totals.
    #[serde(flatten)]
    pub stats: RunStats,
    /// Threads of each worker.
    pub threads: usize,
    /// One worker's wall over this one's.
    pub speedup: f64,
    /// min(W, T₁ / T_longest_orbit): no schedule beats it.
    pub bound: f64,
    /// Steps integrated over one worker's.
    pub steps_vs_one: f64,
    /// Steps integrated beyond the sequential rule's, in % of those.
    pub extra_steps_pct: f64,
    /// The coordinator's busy share of the wall, in %.
    pub coordinator_busy_pct: f64,
    /// Coordinator CPU microseconds per outcome received.
    pub coordinator_us_per_outcome: f64,
    /// [`open_share`] of as many cells as these workers' lanes run orbits at once.
    pub open_share: f64,
}

/// Frontiers [`open_share`] samples, spread evenly over a run's needed orbits.
const OPEN_SHARE_FRONTIERS: usize = 256;

/// Of the first `n` cells past a commit frontier that no committed orbit labels, the share
/// that need their own orbit, by the labels of the sequential rule (`labels`, a finished
/// run's [`Forecast`]), averaged over frontiers at needed orbits sampled evenly. A schedule
/// without a forecast that keeps `n` orbits in flight starts them on such cells, and the
/// others' orbits are wasted as soon as an orbit still running labels their cells: this share
/// is about the most of its steps that can be needed ones.
pub fn open_share(grid: &Grid, labels: &Forecast, n: usize) -> f64 {
    let order = grid.canonical();
    let needed: Vec<usize> = (0..order.len())
        .filter(|&p| labels.labeller(order[p]).is_none())
        .collect();
    let stride = needed.len().div_ceil(OPEN_SHARE_FRONTIERS).max(1);
    let (mut open, mut own) = (0usize, 0usize);
    for &frontier in needed.iter().step_by(stride) {
        let mut seen = 0;
        for &cell in &order[frontier + 1..] {
            if seen == n {
                break;
            }
            match labels.labeller(cell) {
                None => own += 1,
                Some(by) if by >= frontier => {}
                Some(_) => continue,
            }
            seen += 1;
        }
        open += seen;
    }
    if open == 0 {
        1.0
    } else {
        own as f64 / open as f64
    }
}

/// A spec and parameters, with the orbits traced so far (shared by every worker count).
pub struct Simulation {
    spec: JobSpec,
    spec_json: String,
    grid: Grid,
    params: Params,
    traces: Vec<Traces>,
    lanes: usize,
    step_ns: f64,
    /// Per run, the forecast given to the coordinator (made once).
    forecasts: Option<Vec<Forecast>>,
}

impl Simulation {
    /// Reads the spec (the JSON the coordinator takes) and calibrates the cost of a step unless
    /// it is given.
    pub fn new(spec_json: &str, params: Params) -> Result<Self, String> {
        let spec = spec::parse(spec_json, true).map_err(|e| e.0)?;
        // The simulated world holds one grid in one mode: every run of the job shares them.
        if spec.sweeps_mode() {
            return Err(
                "sweep.mode: the simulator takes one mode at a time (give grid.mode, or one value)"
                    .into(),
            );
        }
        if spec.sweeps_energy() {
            return Err(
                "sweep.energy: the simulator takes one energy at a time (give system.energy, or one value)"
                    .into(),
            );
        }
        if params.threads == 0 {
            return Err("threads must be at least 1".into());
        }
        let grid = spec.grid(0);
        let mode = spec.mode(0);
        let first = spec.cell_run(0);
        let method = &first.run.method;
        let lanes = params.lanes.unwrap_or_else(|| match method.is_adaptive() {
            false => executor::lanes(mode),
            true => salient_core::run::adaptive_orbits_per_thread(
                method,
                first.config.tau,
                first.config.t_final,
            ),
        });
        if lanes == 0 {
            return Err("lanes must be at least 1".into());
        }
        let traces = (0..spec.runs.len())
            .map(|i| Traces::new(&spec.grid(i), spec.cell_run(i), mode))
            .collect();
        let step_ns = match params.step_ns {
            Some(ns) if ns > 0.0 && ns.is_finite() => ns,
            Some(ns) => return Err(format!("step cost must be positive (got {ns} ns)")),
            None => calibrate_step_ns(&grid, &first, mode),
        };
        Ok(Simulation {
            spec,
            spec_json: spec_json.to_string(),
            grid,
            params,
            traces,
            lanes,
            step_ns,
            forecasts: None,
        })
    }

    /// CPU nanoseconds per orbit-step in full lanes.
    pub fn step_ns(&self) -> f64 {
        self.step_ns
    }

    /// Orbits a worker thread runs at once.
    pub fn lanes(&self) -> usize {
        self.lanes
    }

    /// Orbits integrated for real so far (the traces).
    pub fn traced(&self) -> usize {
        self.traces.iter().map(|t| t.integrated).sum()
    }

    /// Virtual nanoseconds a lane takes per step.
    fn lane_step_ns(&self) -> f64 {
        self.step_ns * self.lanes as f64
    }

    /// The ledger of every run under the sequential rule, from `traces`: the cells the ledger
    /// needs next are traced [`SEQUENTIAL_ROUND`] at a time (in full lanes, on every thread)
    /// and offered; those an earlier orbit labels meanwhile are dropped.
    fn sequential_ledgers(grid: &Grid, mode: Mode, traces: &mut [Traces]) -> Vec<Ledger> {
        traces
            .iter_mut()
            .map(|t| {
                let mut ledger = Ledger::new(grid, mode);
                while !ledger.done() {
                    let cells = ledger.needed(SEQUENTIAL_ROUND, &|_| false);
                    t.ensure(&cells);
                    for c in cells {
                        ledger.offer(t.get(c).outcome.clone());
                    }
                }
                ledger
            })
            .collect()
    }

    /// The forecasts `params.forecast` asks for, made on first use.
    fn forecasts(&mut self) -> Option<Vec<Forecast>> {
        if self.forecasts.is_none() {
            let mode = self.spec.mode(0);
            self.forecasts = match self.params.forecast {
                ForecastSource::None => None,
                ForecastSource::Perfect => Some(
                    Self::sequential_ledgers(&self.grid, mode, &mut self.traces)
                        .iter()
                        .map(Ledger::forecast)
                        .collect(),
                ),
                ForecastSource::Pilot(t_final) => {
                    let mut pilots: Vec<Traces> = (0..self.spec.runs.len())
                        .map(|i| {
                            let mut run = self.spec.cell_run(i);
                            run.config.t_final = t_final.min(run.config.t_final);
                            Traces::new(&self.grid, run, mode)
                        })
                        .collect();
                    Some(
                        Self::sequential_ledgers(&self.grid, mode, &mut pilots)
                            .iter()
                            .map(Ledger::forecast)
                            .collect(),
                    )
                }
            };
        }
        self.forecasts.clone()
    }

    /// What the sequential rule integrates, summed over the runs (the longest orbit: of all).
    pub fn sequential(&mut self) -> Sequential {
        let mode = self.spec.mode(0);
        let mut total = Sequential::default();
        for ledger in Self::sequential_ledgers(&self.grid, mode, &mut self.traces) {
            total.orbits += ledger.committed.len() as u64;
            total.steps += ledger.committed_steps;
            let longest = ledger.committed.iter().map(|o| o.steps).max();
            total.longest_steps = total.longest_steps.max(longest.unwrap_or(0));
        }
        total
    }

    /// Simulates the job with `workers` workers.
    pub fn run(&mut self, workers: usize) -> Result<RunStats, String> {
        if workers == 0 {
            return Err("workers must be at least 1".into());
        }
        let forecasts = self.forecasts();
        // The scheduler's log lines (jobs, leases, runs done) tell of simulated events: not shown.
        tracing::subscriber::with_default(NoSubscriber::default(), || {
            let store = Store::open_in_memory().map_err(|e| e.to_string())?;
            let mut scheduler = Scheduler::new(store, self.params.config)?;
            let (job, _) = scheduler
                .submit(&self.spec_json)
                .map_err(|e| e.message().to_string())?;
            for (run, f) in forecasts.into_iter().flatten().enumerate() {
                scheduler
                    .set_forecast(job, run, f)
                    .map_err(|e| e.message().to_string())?;
            }
            let traces = std::mem::take(&mut self.traces);
            let mut world = World::new(
                self.grid.clone(),
                traces,
                self.params.seed,
                self.params.host_cores,
            );
            let result = self.drive(&mut scheduler, job, workers, &mut world);
            self.traces = std::mem::take(&mut world.traces);
            result
        })
    }

    /// One-way latency of a message of `bytes`.
    fn latency(&self, world: &mut World, bytes: usize) -> u64 {
        let half = self.params.rtt_ns as f64 / 2.0;
        let jittered = half * (1.0 + self.params.jitter * world.unit());
        (jittered.max(0.0) + bytes as f64 / self.params.bandwidth * 1e9) as u64
    }

    fn drive(
        &self,
        scheduler: &mut Scheduler,
        job: u64,
        workers: usize,
        world: &mut World,
    ) -> Result<RunStats, String> {
        let mut ws = self.start_workers(scheduler, job, workers, world)?;
        let mut coordinator = Coordinator {
            requests: vec![None; workers],
            replies: vec![None; workers],
            waiting: VecDeque::new(),
            busy: false,
            first_lease_ns: None,
            finishing: false,
            finished_ns: None,
            last_outcome_ns: 0,
            stats: RunStats {
                workers,
                ..RunStats::default()
            },
        };
        let stall_ns = (self.params.stall_s * 1e9) as u64;
        let (mut next_sample, mut sample_ns) = (0, FIRST_SAMPLE_NS);
        let stack_half = self.params.coordinator_stack_ns as f64 / 2.0;
        let ids: Vec<String> = ws.iter().map(|w| w.id.clone()).collect();
        let index: HashMap<&str, usize> = ids
            .iter()
            .enumerate()
            .map(|(i, id)| (id.as_str(), i))
            .collect();
        let mut last_event = 0;
        while let Some(event) = world.pop() {
            // Where the frontier stood since the last event (nothing changes between events),
            // from the first lease on, as the wall.
            if coordinator.first_lease_ns.is_some() {
                coordinator.stats.frontier.add(
                    scheduler.frontier_cell(job),
                    &ws,
                    &index,
                    world.now - last_event,
                );
            }
            last_event = world.now;
            if world.now >= next_sample {
                let timeline = &mut coordinator.stats.timeline;
                if timeline.len() == TIMELINE_SAMPLES {
                    let kept: Vec<Sample> = timeline.iter().step_by(2).copied().collect();
                    *timeline = kept;
                    sample_ns *= 2;
                }
                timeline.push(sample(scheduler, job, &ws, world));
                next_sample = world.now + sample_ns;
            }
            match event {
                Event::Send { worker, gen } => {
                    let w = &mut ws[worker];
                    if gen != w.timer_gen || w.in_flight {
                        continue;
                    }
                    let bytes = w.poll_request().encode_to_vec();
                    coordinator.stats.request_bytes += bytes.len() as u64;
                    let at = world.now + self.latency(world, bytes.len());
                    coordinator.requests[worker] = Some(bytes);
                    world.at(at, Event::Arrive { worker });
                }
                Event::Arrive { worker } => {
                    world.add_busy(1);
                    world.after_cpu(stack_half, Event::Received { worker });
                }
                Event::Received { worker } => {
                    world.add_busy(-1);
                    coordinator.waiting.push_back(worker);
                    if !coordinator.busy {
                        self.serve(scheduler, job, &mut coordinator, world)?;
                    }
                }
                Event::Served { worker } => {
                    world.add_busy(-1);
                    coordinator.busy = false;
                    if coordinator.finishing {
                        coordinator.finished_ns = Some(world.now);
                        break;
                    }
                    if world.now - coordinator.last_outcome_ns > stall_ns {
                        return Err(format!(
                            "the simulated job made no progress for {} virtual seconds \
                             (at {:.3} s): a livelock in the schedule",
                            self.params.stall_s,
                            world.now as f64 * 1e-9
                        ));
                    }
                    world.add_busy(1);
                    world.after_cpu(stack_half, Event::Sent { worker });
                    if !coordinator.waiting.is_empty() {
                        self.serve(scheduler, job, &mut coordinator, world)?;
                    }
                }
                Event::Sent { worker } => {
                    world.add_busy(-1);
                    let bytes = coordinator.replies[worker].as_ref().map_or(0, Vec::len);
                    let at = world.now + self.latency(world, bytes);
                    world.at(at, Event::Reply { worker });
                }
                Event::Reply { worker } => {
                    world.add_busy(1);
                    world.after_cpu(self.params.worker_stack_ns as f64, Event::Read { worker });
                }
                Event::Read { worker } => {
                    world.add_busy(-1);
                    let bytes = coordinator.replies[worker].take().expect("a reply");
                    let reply = v1::PollReply::decode(&bytes[..]).map_err(|e| e.to_string())?;
                    ws[worker].on_reply(world, reply)?;
                }
                Event::Crossing { worker, orbit } => ws[worker].on_crossing(world, orbit),
                Event::End { worker, orbit } => ws[worker].on_end(world, orbit),
                Event::Abandon { worker, orbit } => ws[worker].on_abandon(world, orbit),
                Event::Force { worker, gen } => ws[worker].on_force(world, gen),
            }
        }
        // The final state, in place of a sample taken at the same instant.
        let last = sample(scheduler, job, &ws, world);
        let timeline = &mut coordinator.stats.timeline;
        match timeline.last_mut() {
            Some(s) if s.t_s >= last.t_s => *s = last,
            _ => timeline.push(last),
        }
        totals(coordinator, &ws)
    }

    /// Registers `workers` simulated workers, each polling first after its shortest wait.
    fn start_workers(
        &self,
        scheduler: &mut Scheduler,
        job: u64,
        workers: usize,
        world: &mut World,
    ) -> Result<Vec<SimWorker>, String> {
        let shape = Shape {
            threads: self.params.threads,
            lanes: self.lanes,
            lane_step_ns: self.lane_step_ns(),
            poll_steps: salient_core::tangent_map::batch::poll_interval(
                self.spec.cell_run(0).config.tau,
            ),
            max_leases: self.params.max_leases,
            busy_poll_ns: self.params.config.poll.as_nanos() as u64,
            tells_crossings: executor::tells_crossings(&self.spec.cell_run(0)),
        };
        (0..workers)
            .map(|i| {
                let reg = scheduler
                    .register(&v1::RegisterRequest {
                        protocol_version: PROTOCOL_VERSION,
                        name: format!("simulated-{i}"),
                        threads: self.params.threads as u32,
                    })
                    .map_err(|e| e.message().to_string())?;
                let mut w = SimWorker::new(i, reg.worker_id, job, shape, self.spec.mode(0));
                w.schedule_send(world, FIRST_POLL_NS);
                Ok(w)
            })
            .collect()
    }

    /// The coordinator answers the first waiting poll: the real scheduler, timed.
    fn serve(
        &self,
        scheduler: &mut Scheduler,
        job: u64,
        c: &mut Coordinator,
        world: &mut World,
    ) -> Result<(), String> {
        let Some(worker) = c.waiting.pop_front() else {
            return Ok(());
        };
        let bytes = c.requests[worker].take().expect("a request");
        let cpu_start = thread_cpu_ns();
        let req = v1::PollRequest::decode(&bytes[..]).map_err(|e| e.to_string())?;
        scheduler.begin_group();
        let reply = scheduler.poll(&req);
        scheduler.commit_group(Vec::new());
        let reply = reply.map_err(|e| format!("the scheduler refused a poll: {}", e.message()))?;
        let out = reply.encode_to_vec();
        let cpu = thread_cpu_ns().saturating_sub(cpu_start);
        // The store thread commits while the loop goes on; waiting for it here (outside the
        // timed part) makes the acknowledgements the next reply carries independent of how
        // fast this machine's store thread is, so a seed fixes the schedule.
        scheduler.sync_store();
        let service = self.params.coordinator_ns.unwrap_or(cpu);
        let outcomes: usize = req.reports.iter().map(|r| r.outcomes.len()).sum();
        if outcomes > 0 {
            c.last_outcome_ns = world.now;
        }
        c.stats.outcomes += outcomes as u64;
        c.stats.coordinator_cpu_s += cpu as f64 * 1e-9;
        c.stats.coordinator_busy_s += service as f64 * 1e-9;
        c.stats.reply_bytes += out.len() as u64;
        c.stats.leases += reply.leases.len() as u64;
        c.stats.leased_cells += reply
            .leases
            .iter()
            .map(|l| l.cells.len() as u64)
            .sum::<u64>();
        c.stats.relay_bytes += reply
            .relays
            .iter()
            .flat_map(|r| &r.outcomes)
            .map(|o| o.len() as u64)
            .sum::<u64>();
        if c.first_lease_ns.is_none() && !reply.leases.is_empty() {
            c.first_lease_ns = Some(world.now);
        }
        if !c.finishing
            && scheduler
                .is_finished(job)
                .map_err(|e| e.message().to_string())?
        {
            c.finishing = true;
        }
        c.busy = true;
        c.replies[worker] = Some(out);
        world.add_busy(1);
        world.after_cpu(service as f64, Event::Served { worker });
        Ok(())
    }

    /// Simulates every worker count of `workers` (one worker first, as the yardstick, whether
    /// listed or not), calling `each` with every row as it is done.
    pub fn sweep(
        &mut self,
        workers: &[usize],
        mut each: impl FnMut(&Point),
    ) -> Result<Vec<Point>, String> {
        let one = self.run(1)?;
        let sequential = self.sequential();
        let labels: Vec<Forecast> =
            Self::sequential_ledgers(&self.grid, self.spec.mode(0), &mut self.traces)
                .iter()
                .map(Ledger::forecast)
                .collect();
        let in_flight = self.params.threads * self.lanes;
        let longest_s = sequential.longest_steps as f64 * self.lane_step_ns() * 1e-9;
        let mut points = Vec::new();
        for &w in workers {
            let stats = if w == 1 { one.clone() } else { self.run(w)? };
            let bound = (w as f64).min(one.wall_s / longest_s.max(1e-12));
            let speedup = one.wall_s / stats.wall_s.max(1e-12);
            let point = Point {
                threads: self.params.threads,
                speedup,
                bound,
                steps_vs_one: stats.steps as f64 / one.steps.max(1) as f64,
                extra_steps_pct: 100.0
                    * (stats.steps as f64 / sequential.steps.max(1) as f64 - 1.0),
                coordinator_busy_pct: 100.0 * stats.coordinator_busy_s / stats.wall_s.max(1e-12),
                coordinator_us_per_outcome: 1e6 * stats.coordinator_cpu_s
                    / stats.outcomes.max(1) as f64,
                open_share: labels
                    .iter()
                    .map(|l| open_share(&self.grid, l, w * in_flight))
                    .sum::<f64>()
                    / labels.len().max(1) as f64,
                stats,
            };
            each(&point);
            points.push(point);
        }
        Ok(points)
    }
}

/// The job's state now, for the timeline.
fn sample(scheduler: &Scheduler, job: u64, ws: &[SimWorker], world: &World) -> Sample {
    Sample {
        t_s: world.now as f64 * 1e-9,
        running_orbits: ws.iter().map(SimWorker::running_orbits).sum(),
        busy_threads: world.busy(),
        progress: scheduler.progress(job).unwrap_or_default(),
    }
}

/// A finished simulation's totals: the coordinator's and every worker's.
fn totals(coordinator: Coordinator, ws: &[SimWorker]) -> Result<RunStats, String> {
    let finished = coordinator
        .finished_ns
        .ok_or("the simulation ran out of events before the job finished")?;
    let mut stats = coordinator.stats;
    stats.wall_s = (finished - coordinator.first_lease_ns.unwrap_or(0)) as f64 * 1e-9;
    for w in ws {
        stats.orbits_finished += w.totals.orbits_finished;
        stats.orbits_abandoned += w.totals.orbits_abandoned;
        stats.steps += w.totals.steps;
        stats.polls += w.totals.polls;
    }
    Ok(stats)
}

/// The coordinator's side of the simulation: the polls waiting for it and what it answered.
struct Coordinator {
    requests: Vec<Option<Vec<u8>>>,
    replies: Vec<Option<Vec<u8>>>,
    waiting: VecDeque<usize>,
    busy: bool,
    first_lease_ns: Option<u64>,
    /// The poll being answered committed the job's last outcome.
    finishing: bool,
    finished_ns: Option<u64>,
    last_outcome_ns: u64,
    stats: RunStats,
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A small fast-PSS grid, in the JSON the coordinator takes.
    fn spec(cells: usize, tile: usize) -> String {
        format!(
            r#"{{"name": "sim", "system": {{"kind": "henon-heiles", "energy": 0.125}},
               "grid": {{"cells": [{cells}, {cells}], "tile": [{tile}, {tile}], "mode": "fast-pss"}},
               "sweep": {{"method": ["tm-sbab2c"], "tau": [0.5], "t_final": [1000.0]}}}}"#
        )
    }

    /// Fixed costs, so that nothing measured enters the schedule.
    fn fixed(lanes: Option<usize>, rtt_ns: u64) -> Params {
        Params {
            lanes,
            rtt_ns,
            step_ns: Some(25.0),
            coordinator_ns: Some(20_000),
            ..Params::default()
        }
    }

    /// Labels of a sequential run where the orbit at position 0 labels positions 2 and 5, the
    /// one at 3 labels 4 and 7, and every other orbit labels nothing else. With one cell past
    /// each frontier: 0, 1 and every needed one from 6 on see a needed cell next, 3 sees 4
    /// (its own orbit's), the last sees none.
    #[test]
    fn the_open_share_counts_needed_cells_among_those_no_committed_orbit_labels() {
        let grid = Grid::new(0.125, 6, 6, (-0.43, 0.67), (-0.5, 0.5), (3, 3));
        let order = grid.canonical().to_vec();
        let len = order.len();
        assert!(len >= 10, "{len} cells");
        let mut ledger = Ledger::new(&grid, Mode::FastPss);
        for (p, &cell) in order.iter().enumerate() {
            let visited = match p {
                0 => vec![order[2], order[5]],
                3 => vec![order[4], order[7]],
                _ => Vec::new(),
            };
            ledger.offer(salient_grid::Outcome {
                cell,
                class: None,
                status: salient_core::Status::Ok,
                sali: 1.0,
                visited,
                steps: 1,
                t_end: 1.0,
                checkpoints: Vec::new(),
                indicators: None,
            });
        }
        let labels = ledger.forecast();
        assert_eq!(labels.labeller(order[7]), Some(3));
        let share = open_share(&grid, &labels, 1);
        assert!(
            (share - (len - 6) as f64 / (len - 5) as f64).abs() < 1e-12,
            "{share}"
        );
        // With nothing in flight past the frontier there is nothing to waste.
        assert_eq!(open_share(&grid, &labels, 0), 1.0);
    }

    #[test]
    fn a_fixed_seed_gives_the_same_schedule() {
        let text = spec(40, 8);
        let mut a = Simulation::new(&text, fixed(None, 500_000)).unwrap();
        let mut b = Simulation::new(&text, fixed(None, 500_000)).unwrap();
        // Everything but the scheduler's CPU time, which is measured (and not used here).
        let schedule = |mut s: RunStats| {
            s.coordinator_cpu_s = 0.0;
            format!("{s:?}")
        };
        for w in [1, 3] {
            let (x, y) = (a.run(w).unwrap(), b.run(w).unwrap());
            assert_eq!(schedule(x.clone()), schedule(y), "{w} workers");
            assert!(x.steps > 0 && x.wall_s > 0.0);
        }
        // Another seed jitters the latencies otherwise.
        let mut c = Simulation::new(
            &text,
            Params {
                seed: 7,
                ..fixed(None, 500_000)
            },
        )
        .unwrap();
        let (x, z) = (a.run(3).unwrap(), c.run(3).unwrap());
        assert_ne!(x.wall_s, z.wall_s);
    }

    /// One worker with one lane starts an orbit only when the previous one ended and was
    /// committed, so it integrates exactly the orbits the sequential rule does.
    #[test]
    fn one_worker_with_one_lane_integrates_the_sequential_rules_orbits() {
        let mut sim = Simulation::new(&spec(40, 8), fixed(Some(1), 0)).unwrap();
        let one = sim.run(1).unwrap();
        let sequential = sim.sequential();
        assert!(sequential.orbits > 20, "{sequential:?}");
        assert_eq!(one.orbits_finished, sequential.orbits);
        assert_eq!(one.orbits_abandoned, 0);
        assert_eq!(one.steps, sequential.steps);
        assert_eq!(one.outcomes, sequential.orbits);
    }

    /// The frontier's waits account for no more than the wall. One worker with one lane runs
    /// only the frontier's cell, so the frontier waits the whole wall (here mostly for the
    /// outcomes of short orbits to come back); four workers wait less.
    #[test]
    fn the_frontier_waits_show_the_commit_chain() {
        let mut sim = Simulation::new(&spec(40, 8), fixed(Some(1), 500_000)).unwrap();
        let (one, four) = (sim.run(1).unwrap(), sim.run(4).unwrap());
        let waited = |s: &RunStats| {
            let f = s.frontier;
            f.unleased_s + f.queued_s + f.running_s + f.reporting_s + f.stranded_s
        };
        for s in [&one, &four] {
            assert!(waited(s) <= s.wall_s * 1.001, "{s:?}");
        }
        assert!(waited(&one) > 0.9 * one.wall_s, "{one:?}");
        assert!(one.frontier.running_s > 0.0 && one.frontier.reporting_s > 0.0);
        assert!(waited(&four) < waited(&one), "{one:?} {four:?}");
    }

    /// Lanes and workers speculate: more orbits start than the sequential rule needs, and
    /// latency costs time.
    #[test]
    fn speculation_and_latency_show() {
        let mut near = Simulation::new(&spec(40, 8), fixed(None, 0)).unwrap();
        let mut far = Simulation::new(&spec(40, 8), fixed(None, 20_000_000)).unwrap();
        let sequential = near.sequential();
        let (a, b) = (near.run(4).unwrap(), far.run(4).unwrap());
        assert!(a.steps > sequential.steps, "{a:?} {sequential:?}");
        assert!(b.wall_s > 2.0 * a.wall_s, "{a:?} {b:?}");
    }

    /// With the job's own labellers as the coordinator's forecast, four workers integrate
    /// exactly the sequential rule's orbits, and sooner than one.
    #[test]
    fn a_perfect_forecast_leaves_nothing_to_drop() {
        let params = Params {
            forecast: ForecastSource::Perfect,
            ..fixed(None, 500_000)
        };
        let mut sim = Simulation::new(&spec(40, 8), params).unwrap();
        let (one, four) = (sim.run(1).unwrap(), sim.run(4).unwrap());
        let sequential = sim.sequential();
        for s in [&one, &four] {
            assert_eq!(s.steps, sequential.steps, "{s:?}");
            assert_eq!(s.orbits_abandoned, 0);
        }
        assert!(four.wall_s < one.wall_s / 2.0, "{one:?} {four:?}");
    }

    #[test]
    fn bad_parameters_are_refused() {
        let bad = |p: Params| Simulation::new(&spec(20, 10), p).err().unwrap();
        assert!(bad(Params {
            threads: 0,
            ..fixed(None, 0)
        })
        .contains("threads"));
        assert!(bad(Params {
            lanes: Some(0),
            ..fixed(None, 0)
        })
        .contains("lanes"));
        assert!(Simulation::new("{}", fixed(None, 0)).is_err());
        let mut sim = Simulation::new(&spec(20, 10), fixed(None, 0)).unwrap();
        assert!(sim.run(0).unwrap_err().contains("workers"));
    }
}
