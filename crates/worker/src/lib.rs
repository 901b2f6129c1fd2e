//! The worker: registers with a coordinator, keeps a few tile leases, and runs the cells of
//! every lease of one run through one stream of the grid's tile executor on a rayon pool — the
//! same code `salient run` uses — so a lane freed by an ended orbit takes the next leased cell
//! whatever lease it came in. Outcomes go out in its polls as orbits end. Reports stay in an
//! outbox until acknowledged, so they survive a coordinator restart; on drain it finishes the
//! leases it started, releases the ones not started, and deregisters.

mod explain;

pub use explain::explain_transport;
use salient_grid::executor::{integrate_stream, CellSource, LocalLedger, Take, Verdict};
use salient_grid::spec::{self, JobSpec};
use salient_grid::Outcome;
use salient_grid::{process_cpu_seconds, CellRun, Grid};
use salient_proto::v1;
use salient_proto::v1::worker_service_client::WorkerServiceClient;
use salient_proto::{outcome_from_wire, MAX_MESSAGE_BYTES, PROTOCOL_VERSION};
use std::collections::{HashMap, HashSet, VecDeque};
use std::future::Future;
use std::sync::atomic::{AtomicBool, AtomicU64, AtomicUsize, Ordering};
use std::sync::{Arc, Condvar, Mutex};
use std::time::Duration;
use tokio::sync::mpsc;
use tonic::service::interceptor::InterceptedService;
use tonic::transport::{Certificate, Channel, ClientTlsConfig, Endpoint};
use tonic::{Code, Request, Status};

/// How the worker runs.
pub struct Options {
    pub coordinator: String,
    pub threads: usize,
    pub name: String,
    pub token: Option<String>,
    /// PEM of the certificate authority that signed the coordinator's certificate.
    pub tls_ca: Option<Vec<u8>>,
    /// Leases held at once: one in progress and the rest ready, so the pool need not wait on
    /// the network (fast-PSS leases are held one at a time, see [`free_slots`]).
    pub max_leases: usize,
    /// How long a drain may take: past it the worker stops whatever it still holds (a
    /// coordinator that is gone cannot take its reports; its leases go to others anyway).
    pub drain_timeout: Duration,
}

/// Leases to ask for: up to `max` held, but one at a time while the last lease was fast PSS
/// (and before any lease came), and [`HUNGRY_LEASES`] more whenever the compute side is
/// `hungry` (a lane idle with no leased cell waiting; the leases held then are only finishing
/// their orbits). A fast-PSS lease is the next cells the coordinator's ledger needs; one asked
/// for before a lane is free would take cells before the outcomes that may label them arrive,
/// and is slower (figures: docs/performance.md). Full-mode tiles carry no such risk, and a
/// second one keeps the threads busy across the round trip.
fn free_slots(held: usize, hungry: bool, one_at_a_time: bool, max: usize) -> usize {
    let cap = if one_at_a_time { 1 } else { max };
    let hungry = if hungry { HUNGRY_LEASES } else { 0 };
    cap.saturating_sub(held).max(hungry)
}

/// Leases a hungry compute side asks for at once. A fast-PSS lease holds the wanted cells of
/// one tile, often only a few of the batch it may hold, and every poll that carries reports
/// waits for the coordinator's fsync while the lanes run dry. Two beat one; three drop more
/// and are no faster (figures: docs/performance.md).
const HUNGRY_LEASES: usize = 2;

/// An endpoint for `url` with TLS when it is https.
pub fn endpoint(url: &str, tls_ca: Option<&[u8]>) -> Result<Endpoint, String> {
    if !(url.starts_with("http://") || url.starts_with("https://")) {
        return Err(format!(
            "--coordinator must be an http:// or https:// URL (got {url:?})"
        ));
    }
    let mut ep = Endpoint::from_shared(url.to_string())
        .map_err(|e| format!("--coordinator {url:?} is not a valid URL: {e}"))?
        .connect_timeout(Duration::from_secs(5))
        .tcp_nodelay(true);
    if url.starts_with("https://") {
        let mut tls = ClientTlsConfig::new().with_webpki_roots();
        if let Some(ca) = tls_ca {
            tls = tls.ca_certificate(Certificate::from_pem(ca));
        }
        ep = ep
            .tls_config(tls)
            .map_err(|e| format!("TLS configuration: {e}"))?;
    }
    Ok(ep)
}

/// Adds `authorization: Bearer <token>` to every request when a token is set.
#[derive(Clone)]
pub struct Token(pub Option<String>);

impl tonic::service::Interceptor for Token {
    fn call(&mut self, mut req: Request<()>) -> Result<Request<()>, Status> {
        if let Some(t) = &self.0 {
            let v = format!("Bearer {t}").parse().map_err(|_| {
                Status::invalid_argument("the token holds characters a header cannot")
            })?;
            req.metadata_mut().insert("authorization", v);
        }
        Ok(req)
    }
}

type Client = WorkerServiceClient<InterceptedService<Channel, Token>>;

/// Runs whose grid a worker keeps built at once.
const MAX_BUILT_RUNS: usize = 4;

/// Reports sent in one poll at most (bytes); the rest go in the next, well below the
/// coordinator's message limit.
const POLL_REPORT_BYTES: usize = 4 << 20;

/// How long a sent report may wait for its answer before it is sent again. Answers come with
/// the next poll after the coordinator's commit, milliseconds later; one missing this long
/// was lost with a coordinator that stopped before committing it (a restart is caught
/// sooner, by its NOT_FOUND).
const UNANSWERED_RESEND: Duration = Duration::from_secs(10);

/// How long a stopping worker waits for the coordinator to take its leave.
const DEREGISTER_TIMEOUT: Duration = Duration::from_secs(2);

/// A lease handed to the compute thread.
struct Work {
    lease: v1::TileRef,
    spec: Arc<JobSpec>,
    cells: Vec<u32>,
}

/// What the compute thread hands back.
enum Done {
    Report(v1::TileReport),
    /// Not started because the worker is draining.
    Released(v1::TileRef),
    /// A lane is idle and no leased cell waits: time for another lease.
    Hungry,
}

/// Cells to skip and leases revoked, written by the network side, read by the compute side;
/// and per run its own ledger, fed relayed outcomes by the network side, whose claims a skip
/// abandons an orbit already running through.
#[derive(Default)]
struct Signals {
    /// By lease (job, run, tile, attempt).
    skips: HashMap<LeaseKey, HashSet<u32>>,
    revoked: HashSet<LeaseKey>,
    ledgers: HashMap<(u64, u32), RunLedger>,
    /// Runs this worker has made a ledger of: one made again (the compute side keeps few)
    /// asks for its own outcomes to be relayed too.
    made: HashSet<(u64, u32)>,
    /// Outcomes of leases still running, for the next poll: a report that woke the network
    /// side for every outcome would make a poll (and a store commit) of each, and the
    /// coordinator shares the cores.
    partial: Vec<v1::TileReport>,
}

type LeaseKey = (u64, u32, u32, u32);

/// A fast-PSS run's own ledger and how far it got in the coordinator's relayed outcomes (its
/// `RelayMark`): kept together so that a ledger made afresh always starts from the beginning.
struct RunLedger {
    local: Arc<LocalLedger>,
    relayed: u64,
    /// The relay must bring this worker's own outcomes as well: the ledger was made after an
    /// earlier one of the same run was dropped, with the outcomes this worker had offered it.
    /// Without them the ledger's commits stop at the first such cell, its pending outcomes
    /// keep claiming cells the coordinator still leases, and those cells are abandoned at
    /// every lease.
    own: bool,
}

impl Signals {
    /// The run's ledger, made if there is none (on `grid`, or on the spec's grid, built only
    /// then).
    fn ledger(&mut self, key: (u64, u32), spec: &JobSpec, grid: Option<&Grid>) -> &mut RunLedger {
        let again = !self.made.insert(key);
        self.ledgers.entry(key).or_insert_with(|| {
            if again {
                tracing::debug!(
                    job = key.0,
                    run = key.1,
                    "ledger made again; asking for this worker's own outcomes too"
                );
            }
            RunLedger {
                local: Arc::new(match grid {
                    Some(g) => LocalLedger::new(g, spec.grid.mode),
                    None => LocalLedger::new(&spec.grid(), spec.grid.mode),
                }),
                relayed: 0,
                own: again,
            }
        })
    }
}

fn lease_key(l: &v1::TileRef) -> LeaseKey {
    (l.job, l.run, l.tile, l.attempt)
}

/// The compute side: runs every lease of one run through one stream of the tile executor
/// ([`integrate_stream`]), so lanes freed by an ended orbit take the next leased cell at once
/// whatever lease it came in, and a lease's outcomes go out as its orbits end (lease by lease,
/// each lease would wait for its longest orbit with the other lanes idle; figures:
/// docs/performance.md). A lease for another run ends the stream when the cells already
/// leased are done.
fn compute_thread(
    pool: rayon::ThreadPool,
    work: std::sync::mpsc::Receiver<Work>,
    done: mpsc::UnboundedSender<Done>,
    signals: Arc<Mutex<Signals>>,
    draining: Arc<AtomicBool>,
) {
    // Built grids per (job, run), each tied to the spec it was built from (a coordinator on
    // another store reuses job ids), and few: a worker moves through runs in order.
    type Built = (Arc<JobSpec>, Grid, CellRun, Arc<LocalLedger>);
    let mut runs: HashMap<(u64, u32), Built> = HashMap::new();
    let mut next: Option<Work> = None;
    loop {
        let w = match next.take() {
            Some(w) => w,
            None => match work.recv() {
                Ok(w) => w,
                Err(_) => return,
            },
        };
        if draining.load(Ordering::Relaxed) {
            let _ = done.send(Done::Released(w.lease));
            continue;
        }
        let key = w.lease.key();
        if runs
            .get(&(key.0, key.1))
            .is_some_and(|b| !Arc::ptr_eq(&b.0, &w.spec))
            || (runs.len() >= MAX_BUILT_RUNS && !runs.contains_key(&(key.0, key.1)))
        {
            runs.clear();
            // The network side made the new run's ledger (it may hold relayed outcomes).
            let keep = (key.0, key.1);
            signals
                .lock()
                .expect("signals")
                .ledgers
                .retain(|k, _| *k == keep);
        }
        let (spec, grid, cell_run, local) = runs.entry((key.0, key.1)).or_insert_with(|| {
            let grid = w.spec.grid();
            let local = signals
                .lock()
                .expect("signals")
                .ledger((key.0, key.1), &w.spec, Some(&grid))
                .local
                .clone();
            (w.spec.clone(), grid, w.spec.cell_run(key.1 as usize), local)
        });
        let source = LeaseSource::new(
            local.clone(),
            done.clone(),
            signals.clone(),
            draining.clone(),
        );
        source.add(w);
        let mode = spec.grid.mode;
        std::thread::scope(|scope| {
            scope.spawn(|| pool.install(|| integrate_stream(grid, cell_run, mode, local, &source)));
            // Leases of the same run join the stream; another run's lease, or the network
            // side's end, closes it.
            loop {
                match work.recv() {
                    Ok(w) if draining.load(Ordering::Relaxed) => {
                        let _ = done.send(Done::Released(w.lease));
                    }
                    Ok(w)
                        if (w.lease.job, w.lease.run) == (key.0, key.1)
                            && Arc::ptr_eq(&w.spec, spec) =>
                    {
                        source.add(w);
                    }
                    Ok(w) => {
                        next = Some(w);
                        break;
                    }
                    Err(_) => break,
                }
            }
            source.close();
        });
    }
}

/// The leases of one stream: their cells waiting in order, and per lease what has ended.
struct LeaseSource {
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
    fn new(
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

    fn add(&self, w: Work) {
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

    fn close(&self) {
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
            let (g, timeout) = self
                .more
                .wait_timeout(st, Duration::from_millis(5))
                .expect("lease source");
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
            let mut s = self.signals.lock().expect("signals");
            match s.partial.last_mut() {
                Some(r) if r.lease == Some(lease) => r.outcomes.push(o),
                _ => s.partial.push(v1::TileReport {
                    lease: Some(lease),
                    outcomes: vec![o],
                    finished: false,
                    cpu_ns: 0,
                    abandoned_orbits: 0,
                    abandoned_steps: 0,
                }),
            }
        }
    }
}

/// Offers another worker's outcomes, relayed by the coordinator, to the run's own ledger; one
/// that does not fit the grid is logged and left out (the relay is advice, never a reason to
/// stop).
fn apply_relay(local: &LocalLedger, relay: &v1::Relay) {
    for encoded in &relay.outcomes {
        let checked = <v1::Outcome as prost::Message>::decode(&encoded[..])
            .map_err(|e| e.to_string())
            .and_then(|o| outcome_from_wire(&o, local.grid(), o.checkpoints.len()));
        match checked {
            Ok(o) => local.offer(o),
            Err(e) => {
                tracing::warn!(job = relay.job, run = relay.run, error = %e, "relayed outcome left out");
            }
        }
    }
}

/// Moves the outcomes of running leases into the outbox (those of leases still held).
fn collect_partial(
    signals: &Mutex<Signals>,
    held: &[v1::TileRef],
    outbox: &mut Vec<v1::TileReport>,
) {
    let partial = std::mem::take(&mut signals.lock().expect("signals").partial);
    outbox.extend(
        partial
            .into_iter()
            .filter(|r| held.iter().any(|h| Some(h) == r.lease.as_ref())),
    );
}

async fn connect(opts: &Options) -> Result<Client, String> {
    let channel = endpoint(&opts.coordinator, opts.tls_ca.as_deref())?.connect_lazy();
    Ok(
        WorkerServiceClient::with_interceptor(channel, Token(opts.token.clone()))
            .max_decoding_message_size(MAX_MESSAGE_BYTES)
            .max_encoding_message_size(MAX_MESSAGE_BYTES),
    )
}

/// Registers, retrying with backoff while the coordinator is away. Refusals (wrong protocol
/// version, bad token) end the worker.
async fn register(client: &mut Client, opts: &Options) -> Result<v1::RegisterReply, String> {
    let mut backoff = Duration::from_millis(100);
    loop {
        let req = v1::RegisterRequest {
            protocol_version: PROTOCOL_VERSION,
            name: opts.name.clone(),
            threads: opts.threads as u32,
        };
        match client.register(req).await {
            Ok(r) => {
                let r = r.into_inner();
                tracing::info!(worker = %r.worker_id, coordinator = %opts.coordinator, "registered");
                return Ok(r);
            }
            Err(e)
                if matches!(
                    e.code(),
                    Code::Unavailable | Code::Unknown | Code::Cancelled | Code::DeadlineExceeded
                ) =>
            {
                tracing::warn!(coordinator = %opts.coordinator, error = %explain_transport(&opts.coordinator, &e), retry_in_ms = backoff.as_millis() as u64, "coordinator unreachable");
                tokio::time::sleep(backoff).await;
                backoff = (backoff * 2).min(Duration::from_secs(5));
            }
            Err(e) => {
                return Err(format!(
                    "the coordinator refused this worker: {}",
                    e.message()
                ))
            }
        }
    }
}

/// Runs until `drain` resolves and the held leases are finished or released.
pub async fn run(opts: Options, drain: impl Future<Output = ()>) -> Result<(), String> {
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(opts.threads)
        .thread_name(|i| format!("salient-worker-{i}"))
        .build()
        .map_err(|e| format!("starting the thread pool: {e}"))?;
    let signals = Arc::new(Mutex::new(Signals::default()));
    let draining = Arc::new(AtomicBool::new(false));
    let (work_tx, work_rx) = std::sync::mpsc::channel::<Work>();
    let (done_tx, mut done_rx) = mpsc::unbounded_channel::<Done>();
    let compute = {
        let (signals, draining) = (signals.clone(), draining.clone());
        std::thread::Builder::new()
            .name("salient-compute".into())
            .spawn(move || compute_thread(pool, work_rx, done_tx, signals, draining))
            .map_err(|e| format!("starting the compute thread: {e}"))?
    };

    let mut client = connect(&opts).await?;
    // The drain signal goes to the lease loop and to the drain deadline both.
    let (drain_tx, drain_rx) = tokio::sync::watch::channel(false);
    let mut reg: Option<v1::RegisterReply> = None;
    let mut held: Vec<v1::TileRef> = Vec::new();
    let mut released: Vec<v1::TileRef> = Vec::new();
    let lease_loop = lease_loop(
        &opts,
        &mut client,
        &mut reg,
        &mut held,
        &mut released,
        (&signals, &draining),
        (&work_tx, &mut done_rx),
        drain_rx,
    );
    let drained_in_time = tokio::select! {
        r = lease_loop => { r?; true }
        _ = async {
            drain.await;
            let _ = drain_tx.send(true);
            tokio::time::sleep(opts.drain_timeout).await;
        } => false,
    };
    drop(work_tx);
    if !drained_in_time {
        tracing::warn!(
            drain_timeout_s = opts.drain_timeout.as_secs_f64(),
            held = held.len(),
            "drain deadline passed; stopping with leases unfinished (the coordinator gives them to others)"
        );
        released.append(&mut held);
    }
    if let Some(reg) = &reg {
        // Bounded: a coordinator that is gone would keep this waiting.
        let _ = tokio::time::timeout(
            DEREGISTER_TIMEOUT,
            client.deregister(v1::DeregisterRequest {
                worker_id: reg.worker_id.clone(),
                released,
            }),
        )
        .await;
    }
    if drained_in_time {
        let _ = tokio::task::spawn_blocking(move || compute.join()).await;
    }
    tracing::info!("worker stopped");
    Ok(())
}

/// Registers, then polls for leases, hands them to the compute thread and reports what it
/// computes, until the drain signal came and nothing is held or owed any more.
#[allow(clippy::too_many_arguments)]
async fn lease_loop(
    opts: &Options,
    client: &mut Client,
    reg_slot: &mut Option<v1::RegisterReply>,
    held: &mut Vec<v1::TileRef>,
    released: &mut Vec<v1::TileRef>,
    (signals, draining): (&Arc<Mutex<Signals>>, &Arc<AtomicBool>),
    (work_tx, done_rx): (
        &std::sync::mpsc::Sender<Work>,
        &mut mpsc::UnboundedReceiver<Done>,
    ),
    mut drain_rx: tokio::sync::watch::Receiver<bool>,
) -> Result<(), String> {
    let mut reg = register(client, opts).await?;
    *reg_slot = Some(reg.clone());
    let mut specs: HashMap<u64, (String, Arc<JobSpec>)> = HashMap::new();
    let mut one_at_a_time = true;
    let mut hungry_compute = false;
    let mut outbox: Vec<v1::TileReport> = Vec::new();
    // Reports sent and not yet answered, in the order sent. The coordinator answers a poll
    // before committing what it carried, so the answers to its reports come with a later
    // reply, in the order the reports came: each answer for a lease is the answer to the
    // oldest report of that lease waiting here.
    let mut awaiting: VecDeque<(std::time::Instant, v1::TileReport)> = VecDeque::new();
    let mut backoff = Duration::from_millis(100);
    let mut drain_seen = false;
    // A worker with free slots and nothing leased polls soon again (the frontier moves as
    // others report), backing off to the coordinator's interval while nothing comes.
    let mut hungry = Duration::from_millis(2);
    loop {
        let busy = Duration::from_millis(reg.poll_ms.clamp(10, 5000) as u64);
        let idle = if !outbox.is_empty() {
            // Reports left over from a poll that carried its byte budget.
            Duration::ZERO
        } else if free_slots(held.len(), hungry_compute, one_at_a_time, opts.max_leases) > 0
            && !draining.load(Ordering::Relaxed)
        {
            hungry.min(busy)
        } else {
            busy
        };
        tokio::select! {
            _ = drain_rx.wait_for(|&d| d), if !drain_seen => {
                drain_seen = true;
                draining.store(true, Ordering::Relaxed);
                tracing::info!(held = held.len(), "draining: finishing the lease in progress, releasing the rest");
            }
            d = done_rx.recv() => {
                let Some(d) = d else { return Err("the compute thread stopped".into()) };
                let mut next = Some(d);
                while let Some(d) = next.take().or_else(|| done_rx.try_recv().ok()) {
                    match d {
                        Done::Report(r) => {
                            collect_partial(signals, held, &mut outbox);
                            // Reports of leases revoked or forgotten meanwhile are stale.
                            if !held.iter().any(|h| Some(h) == r.lease.as_ref()) {
                                continue;
                            }
                            if r.finished {
                                held.retain(|h| Some(h) != r.lease.as_ref());
                            }
                            outbox.push(r);
                        }
                        Done::Released(l) => {
                            held.retain(|h| *h != l);
                            released.push(l);
                        }
                        Done::Hungry => hungry_compute = true,
                    }
                }
            }
            _ = tokio::time::sleep(idle) => {}
        }
        let draining_now = draining.load(Ordering::Relaxed);
        if draining_now && held.is_empty() && outbox.is_empty() && awaiting.is_empty() {
            return Ok(());
        }
        // Answers are normally one poll behind; ones missing for long were lost (a
        // coordinator that failed before committing them): send those reports again.
        let now = std::time::Instant::now();
        while awaiting
            .front()
            .is_some_and(|(at, _)| now.duration_since(*at) > UNANSWERED_RESEND)
        {
            let (_, r) = awaiting.pop_front().expect("checked");
            tracing::warn!(lease = ?r.lease, "report not acknowledged; resending");
            outbox.insert(0, r);
        }
        collect_partial(signals, held, &mut outbox);
        let req = v1::PollRequest {
            worker_id: reg.worker_id.clone(),
            free_slots: if draining_now {
                0
            } else {
                free_slots(held.len(), hungry_compute, one_at_a_time, opts.max_leases) as u32
            },
            held: held.clone(),
            reports: {
                // At least one report, then as many as fit the budget.
                let mut bytes = 0;
                outbox
                    .iter()
                    .take_while(|r| {
                        let first = bytes == 0;
                        bytes += prost::Message::encoded_len(*r);
                        first || bytes <= POLL_REPORT_BYTES
                    })
                    .cloned()
                    .collect::<Vec<_>>()
            },
            draining: draining_now,
            relayed: signals
                .lock()
                .expect("signals")
                .ledgers
                .iter()
                .map(|(&(job, run), r)| v1::RelayMark {
                    job,
                    run,
                    next: r.relayed,
                    own: r.own,
                })
                .collect(),
        };
        // The first `sent` of the outbox go with this poll and wait for their answers.
        let sent = req.reports.len();
        awaiting.extend(outbox.drain(..sent).map(|r| (now, r)));
        match client.poll(req).await {
            Ok(reply) => {
                backoff = Duration::from_millis(100);
                let reply = reply.into_inner();
                for answered in reply.acknowledged.iter().chain(&reply.stale) {
                    let key = lease_key(answered);
                    match awaiting
                        .iter()
                        .position(|(_, r)| r.lease.as_ref().map(lease_key) == Some(key))
                    {
                        Some(k) => drop(awaiting.remove(k)),
                        None => tracing::debug!(lease = %answered, "answer to no report waiting"),
                    }
                }
                {
                    let mut s = signals.lock().expect("signals");
                    for skip in reply.skips {
                        if let Some(l) = skip.lease {
                            if let Some(r) = s.ledgers.get(&(l.job, l.run)) {
                                let claims = r.local.claims();
                                skip.cells.iter().for_each(|&cell| claims.claim(cell));
                            }
                            s.skips
                                .entry((l.job, l.run, l.tile, l.attempt))
                                .or_default()
                                .extend(skip.cells);
                        }
                    }
                    for r in &reply.revoked {
                        s.revoked.insert((r.job, r.run, r.tile, r.attempt));
                    }
                }

                for r in &reply.revoked {
                    tracing::info!(lease = %r, "lease revoked");
                    held.retain(|h| h != r);
                    outbox.retain(|o| o.lease.as_ref() != Some(r));
                }
                hungry = if reply.leases.is_empty() {
                    (hungry * 2).min(busy)
                } else {
                    Duration::from_millis(2)
                };
                for lease in reply.leases {
                    let Some(tile) = lease.lease else { continue };
                    let spec = match specs.get(&tile.job) {
                        Some((text, s)) if *text == lease.spec_json => s.clone(),
                        _ => match spec::parse(&lease.spec_json, true) {
                            Ok(s) => {
                                let s = Arc::new(s);
                                if specs.len() >= 16 {
                                    specs.retain(|job, _| held.iter().any(|h| h.job == *job));
                                }
                                specs.insert(tile.job, (lease.spec_json.clone(), s.clone()));
                                s
                            }
                            Err(e) => {
                                tracing::error!(job = tile.job, error = %e, "cannot read the job's spec; not taking the lease (the coordinator gets it back at the next poll)");
                                continue;
                            }
                        },
                    };
                    tracing::debug!(lease = %tile, cells = lease.cells.len(), "leased");
                    if spec.grid.mode == salient_grid::Mode::FastPss {
                        // Made here, not by the compute side, so that the outcomes relayed in
                        // this reply find it.
                        signals
                            .lock()
                            .expect("signals")
                            .ledger((tile.job, tile.run), &spec, None);
                    }
                    one_at_a_time = spec.grid.mode == salient_grid::Mode::FastPss;
                    hungry_compute = false;
                    held.push(tile);
                    if work_tx
                        .send(Work {
                            lease: tile,
                            spec,
                            cells: lease.cells,
                        })
                        .is_err()
                    {
                        return Err("the compute thread stopped".into());
                    }
                }
                if !reply.relays.is_empty() {
                    let mut s = signals.lock().expect("signals");
                    for relay in &reply.relays {
                        if let Some(r) = s.ledgers.get_mut(&(relay.job, relay.run)) {
                            apply_relay(&r.local, relay);
                            r.relayed = relay.next;
                        }
                    }
                }
            }
            Err(e) if e.code() == Code::NotFound => {
                // The coordinator restarted and forgot us: register again, keep the outbox
                // and the leases; the next poll resends and re-adopts them.
                tracing::warn!(error = %e.message(), "coordinator does not know this worker");
                let again = register(client, opts).await?;
                // What it had not committed is gone with it: everything unanswered goes again.
                for (_, r) in awaiting.drain(..).rev() {
                    outbox.insert(0, r);
                }
                // The marks counted the old process's relays.
                for r in signals.lock().expect("signals").ledgers.values_mut() {
                    r.relayed = 0;
                }
                if again.coordinator_id != reg.coordinator_id {
                    // Another store: its job ids, tiles and attempts are not the ones we hold.
                    tracing::warn!(
                        dropped_reports = outbox.len(),
                        dropped_leases = held.len(),
                        "the coordinator runs on another store; forgetting jobs, leases and reports"
                    );
                    let mut s = signals.lock().expect("signals");
                    for h in held.drain(..) {
                        s.revoked.insert((h.job, h.run, h.tile, h.attempt));
                    }
                    outbox.clear();
                    specs.clear();
                    s.ledgers.clear();
                    s.made.clear();
                }
                *reg_slot = Some(again.clone());
                reg = again;
            }
            Err(e) if e.code() == Code::InvalidArgument && sent > 0 => {
                // The coordinator refuses what this poll carried (it changed nothing): drop
                // those reports rather than resend them forever; their tiles are leased again.
                tracing::error!(error = %e.message(), dropped_reports = sent, "the coordinator refused reports; dropping them");
                awaiting.truncate(awaiting.len().saturating_sub(sent));
            }
            Err(e)
                if matches!(
                    e.code(),
                    Code::Unauthenticated | Code::FailedPrecondition | Code::InvalidArgument
                ) =>
            {
                return Err(format!("the coordinator refused a poll: {}", e.message()));
            }
            Err(e) => {
                // Perhaps applied, perhaps not: this poll's reports go again (a repeat
                // changes nothing); their answers, if owed, come all the same.
                for _ in 0..sent {
                    if let Some((_, r)) = awaiting.pop_back() {
                        outbox.insert(0, r);
                    }
                }
                tracing::warn!(error = %e.message(), retry_in_ms = backoff.as_millis() as u64, pending_reports = outbox.len(), "poll failed");
                tokio::time::sleep(backoff).await;
                backoff = (backoff * 2).min(Duration::from_secs(5));
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A stream's source hands out the first cell its judge lets go, ends the dropped ones
    /// without an outcome, keeps the deferred ones, and lets a deferred one go only when every
    /// lane is idle and no orbit runs (nothing here could settle it).
    #[test]
    fn the_source_defers_drops_and_never_stalls() {
        let json = r#"{"name": "t", "system": {"kind": "henon-heiles", "energy": 0.125},
            "grid": {"cells": [14, 12], "tile": [14, 12], "mode": "fast-pss"},
            "sweep": {"method": ["tm-sbab2c"], "tau": [0.5], "t_final": [10.0]}}"#;
        let spec = Arc::new(spec::parse(json, true).unwrap());
        let grid = spec.grid();
        let cells: Vec<u32> = grid.canonical()[..3].to_vec();
        let (tx, mut rx) = mpsc::unbounded_channel();
        let local = Arc::new(LocalLedger::new(&grid, spec.grid.mode));
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

    #[test]
    fn fast_pss_leases_are_held_one_at_a_time() {
        // Fast PSS (and before any lease): one at a time, whatever --leases says.
        assert_eq!(free_slots(0, false, true, 4), 1);
        assert_eq!(free_slots(1, false, true, 4), 0);
        // Full mode: up to --leases.
        assert_eq!(free_slots(0, false, false, 4), 4);
        assert_eq!(free_slots(3, false, false, 4), 1);
        assert_eq!(free_slots(5, false, false, 4), 0);
        // A hungry compute side gets more, whatever is held.
        assert_eq!(free_slots(1, true, true, 4), HUNGRY_LEASES);
        assert_eq!(free_slots(5, true, false, 4), HUNGRY_LEASES);
        assert_eq!(free_slots(0, true, false, 4), 4);
    }
}
