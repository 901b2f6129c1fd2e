//! The worker: registers with a coordinator, keeps one or a few tile leases, integrates each
//! lease's cells with the grid's tile executor on a rayon pool — the same code `salient run`
//! uses — and reports outcomes chunk by chunk in its polls. Reports stay
//! in an outbox until acknowledged, so they survive a coordinator restart; on drain it finishes
//! the lease in progress, releases the ones not started, and deregisters.

use salient_grid::executor::{integrate_cells_with, lanes, Claims};
use salient_grid::spec::{self, JobSpec};
use salient_grid::{CellRun, Grid};
use salient_proto::v1;
use salient_proto::v1::worker_service_client::WorkerServiceClient;
use salient_proto::{MAX_MESSAGE_BYTES, PROTOCOL_VERSION};
use std::collections::{HashMap, HashSet};
use std::future::Future;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
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
}

/// Leases to ask for: up to `max` held, but one at a time while the last lease was fast PSS
/// (and before any lease came). A fast-PSS lease is the next cells the coordinator's ledger
/// needs; a second one would take cells before the outcomes that may label them arrive, and
/// measured slower (400×400 at t = 1e4 and 1e5: 0.94 and 3.9 s with one, 1.0–1.2 and 4.8 s with
/// two). Full-mode tiles carry no such risk, and a second one keeps the threads busy across the
/// round trip.
fn free_slots(held: usize, one_at_a_time: bool, max: usize) -> usize {
    let cap = if one_at_a_time { 1 } else { max };
    cap.saturating_sub(held)
}

/// CPU time of this process (user + system) in seconds, from /proc on Linux; NaN elsewhere.
pub fn process_cpu_seconds() -> f64 {
    let Ok(stat) = std::fs::read_to_string("/proc/self/stat") else {
        return f64::NAN;
    };
    // Fields after the command name (which may contain spaces) start after the last ')'.
    let Some(rest) = stat.rsplit_once(')').map(|(_, r)| r) else {
        return f64::NAN;
    };
    let fields: Vec<&str> = rest.split_whitespace().collect();
    // utime and stime are fields 14 and 15 of the whole line, 12 and 13 after ')'.
    let ticks = |i: usize| fields.get(i).and_then(|f| f.parse::<f64>().ok());
    match (ticks(11), ticks(12)) {
        (Some(u), Some(s)) => (u + s) / 100.0,
        _ => f64::NAN,
    }
}

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
}

/// Cells to skip and leases revoked, written by the network side, read between chunks; and
/// per run the claims through which a skip abandons an orbit already running.
#[derive(Default)]
struct Signals {
    /// By lease (job, run, tile, attempt).
    skips: HashMap<(u64, u32, u32, u32), HashSet<u32>>,
    revoked: HashSet<(u64, u32, u32, u32)>,
    claims: HashMap<(u64, u32), Arc<Claims>>,
}

fn compute_thread(
    pool: rayon::ThreadPool,
    work: std::sync::mpsc::Receiver<Work>,
    done: mpsc::UnboundedSender<Done>,
    signals: Arc<Mutex<Signals>>,
    draining: Arc<AtomicBool>,
) {
    // Built grids per (job, run), each tied to the spec it was built from (a coordinator on
    // another store reuses job ids), and few: a worker moves through runs in order.
    type Built = (Arc<JobSpec>, Grid, CellRun, Arc<Claims>);
    let mut runs: HashMap<(u64, u32), Built> = HashMap::new();
    while let Ok(w) = work.recv() {
        let key = w.lease.key();
        let lease_key = (key.0, key.1, key.2, w.lease.attempt);
        if draining.load(Ordering::Relaxed) {
            let _ = done.send(Done::Released(w.lease));
            continue;
        }
        if runs
            .get(&(key.0, key.1))
            .is_some_and(|b| !Arc::ptr_eq(&b.0, &w.spec))
            || (runs.len() >= MAX_BUILT_RUNS && !runs.contains_key(&(key.0, key.1)))
        {
            runs.clear();
            signals.lock().expect("signals").claims.clear();
        }
        let (_, grid, cell_run, claims) = runs.entry((key.0, key.1)).or_insert_with(|| {
            let grid = w.spec.grid();
            let claims = Arc::new(Claims::external(&grid));
            let mut s = signals.lock().expect("signals");
            s.claims.insert((key.0, key.1), claims.clone());
            (
                w.spec.clone(),
                grid,
                w.spec.cell_run(key.1 as usize),
                claims,
            )
        });
        {
            // The coordinator leases a cell only when it needs it: a claim left from an earlier
            // skip of this cell must not abandon it now.
            let s = signals.lock().expect("signals");
            let skips = s.skips.get(&lease_key);
            for &c in &w.cells {
                if skips.is_some_and(|sk| sk.contains(&c)) {
                    claims.claim(c);
                } else {
                    claims.unclaim(c);
                }
            }
        }
        let abandoned0 = claims.abandoned();
        let mode = w.spec.grid.mode;
        // Two batches per driver, in the lane count the executor will run this lease with.
        let chunk = (pool.current_num_threads() * lanes(mode, cell_run.config.tau) * 2).max(8);
        let mut rest = w.cells.as_slice();
        loop {
            let take = {
                let s = signals.lock().expect("signals");
                if s.revoked.contains(&lease_key) {
                    break;
                }
                let skip = s.skips.get(&lease_key);
                let (now, later) = rest.split_at(chunk.min(rest.len()));
                rest = later;
                now.iter()
                    .copied()
                    .filter(|c| !skip.is_some_and(|s| s.contains(c)))
                    .collect::<Vec<u32>>()
            };
            let cpu0 = process_cpu_seconds();
            let outcomes =
                pool.install(|| integrate_cells_with(grid, cell_run, mode, &take, Some(claims)));
            let cpu_ns = ((process_cpu_seconds() - cpu0).max(0.0) * 1e9) as u64;
            let finished = rest.is_empty();
            let abandoned = claims.abandoned();
            let report = v1::TileReport {
                lease: Some(w.lease),
                outcomes: outcomes.iter().map(v1::Outcome::from).collect(),
                finished,
                cpu_ns,
                // The lease's total, sent once with the finishing report.
                abandoned_orbits: if finished {
                    abandoned.0 - abandoned0.0
                } else {
                    0
                },
                abandoned_steps: if finished {
                    abandoned.1 - abandoned0.1
                } else {
                    0
                },
            };
            if (!report.outcomes.is_empty() || finished) && done.send(Done::Report(report)).is_err()
            {
                return;
            }
            if finished {
                break;
            }
        }
        let mut s = signals.lock().expect("signals");
        s.skips.remove(&lease_key);
        s.revoked.remove(&lease_key);
    }
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
                tracing::warn!(coordinator = %opts.coordinator, error = %e.message(), retry_in_ms = backoff.as_millis() as u64, "coordinator unreachable");
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
    let mut reg = register(&mut client, &opts).await?;
    let mut specs: HashMap<u64, (String, Arc<JobSpec>)> = HashMap::new();
    let mut held: Vec<v1::TileRef> = Vec::new();
    let mut one_at_a_time = true;
    let mut outbox: Vec<v1::TileReport> = Vec::new();
    let mut released: Vec<v1::TileRef> = Vec::new();
    let mut backoff = Duration::from_millis(100);
    tokio::pin!(drain);
    let mut drain_seen = false;
    // A worker with free slots and nothing leased polls soon again (the frontier moves as
    // others report), backing off to the coordinator's interval while nothing comes.
    let mut hungry = Duration::from_millis(2);
    loop {
        let busy = Duration::from_millis(reg.poll_ms.clamp(10, 5000) as u64);
        let idle = if !outbox.is_empty() {
            // Reports left over from a poll that carried its byte budget.
            Duration::ZERO
        } else if free_slots(held.len(), one_at_a_time, opts.max_leases) > 0
            && !draining.load(Ordering::Relaxed)
        {
            hungry.min(busy)
        } else {
            busy
        };
        tokio::select! {
            _ = &mut drain, if !drain_seen => {
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
                    }
                }
            }
            _ = tokio::time::sleep(idle) => {}
        }
        let draining_now = draining.load(Ordering::Relaxed);
        if draining_now && held.is_empty() && outbox.is_empty() {
            break;
        }
        let req = v1::PollRequest {
            worker_id: reg.worker_id.clone(),
            free_slots: if draining_now {
                0
            } else {
                free_slots(held.len(), one_at_a_time, opts.max_leases) as u32
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
        };
        // The reply answers the reports this poll carried: the first `sent` of the outbox.
        let sent = req.reports.len();
        match client.poll(req).await {
            Ok(reply) => {
                backoff = Duration::from_millis(100);
                let reply = reply.into_inner();
                let answered: HashSet<(u64, u32, u32, u32)> = reply
                    .acknowledged
                    .iter()
                    .chain(&reply.stale)
                    .map(|t| (t.job, t.run, t.tile, t.attempt))
                    .collect();
                // Everything sent was answered (the reply covers the whole request).
                let before = outbox.len();
                let mut k = 0;
                outbox.retain(|r| {
                    k += 1;
                    let l = r.lease.as_ref().expect("own reports carry their lease");
                    k > sent || !answered.contains(&(l.job, l.run, l.tile, l.attempt))
                });
                if outbox.len() == before && sent > 0 {
                    tracing::warn!(unanswered = sent, "reports not acknowledged; resending");
                }
                {
                    let mut s = signals.lock().expect("signals");
                    for skip in reply.skips {
                        if let Some(l) = skip.lease {
                            if let Some(c) = s.claims.get(&(l.job, l.run)) {
                                skip.cells.iter().for_each(|&cell| c.claim(cell));
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
                    one_at_a_time = spec.grid.mode == salient_grid::Mode::FastPss;
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
            }
            Err(e) if e.code() == Code::NotFound => {
                // The coordinator restarted and forgot us: register again, keep the outbox
                // and the leases; the next poll resends and re-adopts them.
                tracing::warn!(error = %e.message(), "coordinator does not know this worker");
                let again = register(&mut client, &opts).await?;
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
                }
                reg = again;
            }
            Err(e) if e.code() == Code::InvalidArgument && sent > 0 => {
                // The coordinator refuses what this poll carried (it changed nothing): drop
                // those reports rather than resend them forever; their tiles are leased again.
                tracing::error!(error = %e.message(), dropped_reports = sent, "the coordinator refused reports; dropping them");
                outbox.drain(..sent.min(outbox.len()));
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
                tracing::warn!(error = %e.message(), retry_in_ms = backoff.as_millis() as u64, pending_reports = outbox.len(), "poll failed");
                tokio::time::sleep(backoff).await;
                backoff = (backoff * 2).min(Duration::from_secs(5));
            }
        }
    }
    drop(work_tx);
    let _ = client
        .deregister(v1::DeregisterRequest {
            worker_id: reg.worker_id.clone(),
            released,
        })
        .await;
    let _ = tokio::task::spawn_blocking(move || compute.join()).await;
    tracing::info!("worker stopped");
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::free_slots;

    #[test]
    fn fast_pss_leases_are_held_one_at_a_time() {
        // Fast PSS (and before any lease): one at a time, whatever --leases says.
        assert_eq!(free_slots(0, true, 4), 1);
        assert_eq!(free_slots(1, true, 4), 0);
        // Full mode: up to --leases.
        assert_eq!(free_slots(0, false, 4), 4);
        assert_eq!(free_slots(3, false, 4), 1);
        assert_eq!(free_slots(5, false, 4), 0);
    }
}
