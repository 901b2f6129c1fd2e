//! The coordinator: the gRPC services for workers and clients (tonic), and one event loop on
//! its own thread that owns the [`scheduler::Scheduler`] — jobs, runs, ledgers, tile leases —
//! whose SQLite store commits on a thread of its own. Handlers only turn requests into
//! [`Event`]s and wait for the loop's answer, so every state change happens in one place, in
//! arrival order, and nothing is acknowledged before it is committed (a poll's reply goes out
//! at once, carrying only acknowledgements already durable). It never integrates an orbit.

pub mod scheduler;
mod writer;

use salient_proto::v1;
use salient_proto::v1::client_service_server::{ClientService, ClientServiceServer};
use salient_proto::v1::worker_service_server::{WorkerService, WorkerServiceServer};
use salient_proto::MAX_MESSAGE_BYTES;
use scheduler::{Config, Scheduler};
use std::future::Future;
use std::net::SocketAddr;
use std::path::PathBuf;
use std::pin::Pin;
use std::time::{Duration, Instant};
use tokio::sync::{mpsc, oneshot};
use tokio_stream::wrappers::{ReceiverStream, TcpListenerStream};
use tonic::transport::{Identity, Server, ServerTlsConfig};
use tonic::{Request, Response, Status};
use writer::Deferred;

type Reply<T> = oneshot::Sender<Result<T, Status>>;

/// Everything that changes or reads the scheduler's state.
pub enum Event {
    /// Submit a job spec; the reply is the job id and the spec's warnings.
    Submit(String, Reply<(u64, Vec<String>)>),
    /// A worker registers.
    Register(v1::RegisterRequest, Reply<v1::RegisterReply>),
    /// A worker's poll: reports, renewals, crossings and free slots for leases.
    Poll(v1::PollRequest, Reply<v1::PollReply>),
    /// A worker renews the leases it holds.
    Renew(v1::RenewRequest, Reply<v1::RenewReply>),
    /// A worker reports outcomes.
    Report(v1::ReportRequest, Reply<v1::ReportReply>),
    /// A worker leaves, releasing its leases.
    Deregister(v1::DeregisterRequest, Reply<()>),
    /// Status of one job, or of every job.
    Status(Option<u64>, Reply<v1::StatusReply>),
    /// Stream a job's status to the sender until the job ends.
    Watch(u64, mpsc::Sender<Result<v1::JobStatus, Status>>),
    /// The results stream of a job.
    Results(u64, Reply<Vec<v1::ResultsChunk>>),
    /// Cancel a job; the reply is its state.
    Cancel(u64, Reply<String>),
    /// The periodic tick: silent workers, expired leases, progress logs and watchers.
    Tick,
}

/// How the coordinator is run.
pub struct Options {
    /// Address to listen on.
    pub listen: SocketAddr,
    /// Path of the SQLite store.
    pub db: PathBuf,
    /// Bearer token required from workers and clients.
    pub token: Option<String>,
    /// PEM certificate chain and key for TLS.
    pub tls: Option<(Vec<u8>, Vec<u8>)>,
    /// Timing of leases and polls.
    pub config: Config,
    /// Interval of the per-run progress log lines.
    pub progress_every: Duration,
}

/// Outcomes per results message: far below the message size limit even with long visited
/// lists.
const RESULTS_BATCH: usize = 256;

/// Events handled in one store transaction at most.
const GROUP: usize = 64;

type Watchers = Vec<(u64, mpsc::Sender<Result<v1::JobStatus, Status>>)>;

fn defer<T: Send + 'static>(tx: Reply<T>, r: Result<T, Status>) -> Deferred {
    Box::new(move || drop(tx.send(r)))
}

/// The loop: owns the scheduler, answers events in arrival order. Events that queued up while
/// it worked are handled together in one store transaction (group commit: one fsync for a
/// burst of reports and leases), and their answers go out only after it is committed. The
/// commit happens on the store thread ([`writer`]), so the loop goes on with the next events
/// meanwhile.
fn event_loop(mut s: Scheduler, mut rx: mpsc::Receiver<Event>, progress_every: Duration) {
    let mut watchers: Watchers = Vec::new();
    let mut last_progress = Instant::now();
    while let Some(first) = rx.blocking_recv() {
        let mut batch = vec![first];
        while batch.len() < GROUP {
            match rx.try_recv() {
                Ok(ev) => batch.push(ev),
                Err(_) => break,
            }
        }
        s.begin_group();
        let mut answers: Vec<Deferred> = Vec::with_capacity(batch.len());
        for ev in batch {
            handle(
                &mut s,
                ev,
                &mut watchers,
                &mut answers,
                &mut last_progress,
                progress_every,
            );
        }
        s.commit_group(answers);
    }
}

fn handle(
    s: &mut Scheduler,
    ev: Event,
    watchers: &mut Watchers,
    answers: &mut Vec<Deferred>,
    last_progress: &mut Instant,
    progress_every: Duration,
) {
    match ev {
        Event::Submit(spec, tx) => answers.push(defer(tx, s.submit(&spec))),
        Event::Register(r, tx) => answers.push(defer(tx, s.register(&r))),
        // A poll's reply acknowledges only reports already committed (the others' answers
        // are owed to a later reply, see `Scheduler::poll`), so it goes out before the
        // group's commit: a worker waiting for cells waits for no fsync. Its leases' attempts
        // may thus be lost in a crash; the scheduler never numbers one again after a restart.
        Event::Poll(r, tx) => drop(tx.send(s.poll(&r))),
        Event::Renew(r, tx) => answers.push(defer(tx, s.renew_only(&r))),
        Event::Report(r, tx) => answers.push(defer(tx, s.report(&r))),
        Event::Deregister(r, tx) => answers.push(defer(tx, s.deregister(&r))),
        Event::Status(j, tx) => answers.push(defer(tx, s.status(j))),
        Event::Results(j, tx) => answers.push(defer(tx, s.results(j, RESULTS_BATCH))),
        Event::Cancel(j, tx) => answers.push(defer(tx, s.cancel(j))),
        Event::Watch(j, tx) => match s.status(Some(j)) {
            Ok(st) => {
                let finished = st.jobs.first().is_some_and(|j| is_terminal(&j.state));
                if let Some(first) = st.jobs.into_iter().next() {
                    let _ = tx.try_send(Ok(first));
                }
                if !finished {
                    watchers.push((j, tx));
                }
            }
            Err(e) => drop(tx.try_send(Err(e))),
        },
        Event::Tick => {
            s.tick();
            if last_progress.elapsed() >= progress_every {
                *last_progress = Instant::now();
                s.log_progress();
            }
            watchers.retain(|(job, tx)| {
                if tx.is_closed() {
                    return false;
                }
                match s.status(Some(*job)) {
                    Ok(st) => {
                        let Some(js) = st.jobs.into_iter().next() else {
                            return false;
                        };
                        let finished = is_terminal(&js.state);
                        // A slow watcher misses intermediate states, never the last one.
                        let sent = tx.try_send(Ok(js)).is_ok();
                        !(finished && sent)
                    }
                    Err(e) => {
                        let _ = tx.try_send(Err(e));
                        false
                    }
                }
            });
            s.retire_finished();
        }
    }
}

fn is_terminal(state: &str) -> bool {
    matches!(state, "done" | "cancelled" | "failed")
}

#[derive(Clone)]
struct Handle(mpsc::Sender<Event>);

impl Handle {
    async fn ask<T>(&self, make: impl FnOnce(Reply<T>) -> Event) -> Result<T, Status> {
        let (tx, rx) = oneshot::channel();
        self.0
            .send(make(tx))
            .await
            .map_err(|_| Status::unavailable("coordinator is shutting down"))?;
        rx.await
            .map_err(|_| Status::unavailable("coordinator is shutting down"))?
    }
}

#[tonic::async_trait]
impl WorkerService for Handle {
    async fn register(
        &self,
        r: Request<v1::RegisterRequest>,
    ) -> Result<Response<v1::RegisterReply>, Status> {
        self.ask(|tx| Event::Register(r.into_inner(), tx))
            .await
            .map(Response::new)
    }
    async fn poll(&self, r: Request<v1::PollRequest>) -> Result<Response<v1::PollReply>, Status> {
        self.ask(|tx| Event::Poll(r.into_inner(), tx))
            .await
            .map(Response::new)
    }
    async fn renew(
        &self,
        r: Request<v1::RenewRequest>,
    ) -> Result<Response<v1::RenewReply>, Status> {
        self.ask(|tx| Event::Renew(r.into_inner(), tx))
            .await
            .map(Response::new)
    }
    async fn report(
        &self,
        r: Request<v1::ReportRequest>,
    ) -> Result<Response<v1::ReportReply>, Status> {
        self.ask(|tx| Event::Report(r.into_inner(), tx))
            .await
            .map(Response::new)
    }
    async fn deregister(
        &self,
        r: Request<v1::DeregisterRequest>,
    ) -> Result<Response<v1::DeregisterReply>, Status> {
        self.ask(|tx| Event::Deregister(r.into_inner(), tx))
            .await
            .map(|()| Response::new(v1::DeregisterReply {}))
    }
}

type Stream<T> = Pin<Box<dyn tokio_stream::Stream<Item = Result<T, Status>> + Send>>;

#[tonic::async_trait]
impl ClientService for Handle {
    async fn submit(
        &self,
        r: Request<v1::SubmitRequest>,
    ) -> Result<Response<v1::SubmitReply>, Status> {
        let text = String::from_utf8(r.into_inner().spec_json)
            .map_err(|e| Status::invalid_argument(format!("spec_json is not UTF-8 text: {e}")))?;
        let (job, warnings) = self.ask(|tx| Event::Submit(text, tx)).await?;
        Ok(Response::new(v1::SubmitReply { job, warnings }))
    }
    async fn status(
        &self,
        r: Request<v1::StatusRequest>,
    ) -> Result<Response<v1::StatusReply>, Status> {
        self.ask(|tx| Event::Status(r.into_inner().job, tx))
            .await
            .map(Response::new)
    }
    type WatchStream = Stream<v1::JobStatus>;
    async fn watch(
        &self,
        r: Request<v1::WatchRequest>,
    ) -> Result<Response<Self::WatchStream>, Status> {
        let (tx, rx) = mpsc::channel(16);
        self.0
            .send(Event::Watch(r.into_inner().job, tx))
            .await
            .map_err(|_| Status::unavailable("coordinator is shutting down"))?;
        Ok(Response::new(Box::pin(ReceiverStream::new(rx))))
    }
    type ResultsStream = Stream<v1::ResultsChunk>;
    async fn results(
        &self,
        r: Request<v1::ResultsRequest>,
    ) -> Result<Response<Self::ResultsStream>, Status> {
        let chunks = self
            .ask(|tx| Event::Results(r.into_inner().job, tx))
            .await?;
        Ok(Response::new(Box::pin(tokio_stream::iter(
            chunks.into_iter().map(Ok),
        ))))
    }
    async fn cancel(
        &self,
        r: Request<v1::CancelRequest>,
    ) -> Result<Response<v1::CancelReply>, Status> {
        let state = self.ask(|tx| Event::Cancel(r.into_inner().job, tx)).await?;
        Ok(Response::new(v1::CancelReply { state }))
    }
}

/// The gRPC method of a request (its path), put where the token check can name it: an
/// interceptor sees metadata and extensions, not the URI.
#[derive(Clone)]
struct MethodPath(tonic::codegen::http::uri::PathAndQuery);

/// Runs for every request (workers poll every few milliseconds): the path is shared, not
/// copied (cloning a `PathAndQuery` bumps a reference count).
fn tag_method<B>(mut req: tonic::codegen::http::Request<B>) -> tonic::codegen::http::Request<B> {
    if let Some(path) = req.uri().path_and_query().cloned() {
        req.extensions_mut().insert(MethodPath(path));
    }
    req
}

/// Requires `authorization: Bearer <token>` when a token is configured. A refused request is
/// logged with the peer's address and the method, never with what it presented.
fn check_token(
    token: Option<String>,
) -> impl Fn(Request<()>) -> Result<Request<()>, Status> + Clone {
    move |req: Request<()>| {
        let Some(want) = &token else {
            return Ok(req);
        };
        let got = req
            .metadata()
            .get("authorization")
            .and_then(|v| v.to_str().ok())
            .and_then(|v| v.strip_prefix("Bearer "));
        if got.is_some_and(|g| constant_time_eq(g.as_bytes(), want.as_bytes())) {
            return Ok(req);
        }
        let peer = req
            .remote_addr()
            .map_or_else(|| "unknown".to_string(), |a| a.to_string());
        let method = req
            .extensions()
            .get::<MethodPath>()
            .map_or("unknown", |m| m.0.path());
        let presented = if got.is_some() {
            "a wrong token"
        } else {
            "no token"
        };
        tracing::warn!(%peer, method, presented, "authentication failed");
        Err(Status::unauthenticated(
            "a valid bearer token is required (--token, --token-file or $SALIENT_TOKEN)",
        ))
    }
}

fn constant_time_eq(a: &[u8], b: &[u8]) -> bool {
    a.len() == b.len() && a.iter().zip(b).fold(0u8, |acc, (x, y)| acc | (x ^ y)) == 0
}

/// Opens the store, resumes unfinished jobs, binds, and serves until `shutdown` resolves.
/// `bound` receives the address actually bound (useful with port 0).
pub async fn serve(
    opts: Options,
    bound: impl FnOnce(SocketAddr),
    shutdown: impl Future<Output = ()> + Send + 'static,
) -> Result<(), String> {
    let store = salient_store::Store::open(&opts.db)
        .map_err(|e| format!("opening the store {}: {e}", opts.db.display()))?;
    let scheduler = Scheduler::new(store, opts.config)?;
    let (tx, rx) = mpsc::channel::<Event>(1024);
    let progress_every = opts.progress_every;
    let loop_thread = std::thread::Builder::new()
        .name("scheduler".into())
        .spawn(move || {
            // A panic here would leave every RPC answering "shutting down" forever: stop the
            // process instead, so a supervisor restarts it from the store.
            let run = std::panic::AssertUnwindSafe(|| event_loop(scheduler, rx, progress_every));
            if std::panic::catch_unwind(run).is_err() {
                tracing::error!("the scheduler loop panicked; stopping");
                std::process::exit(1);
            }
        })
        .map_err(|e| format!("starting the scheduler thread: {e}"))?;
    let ticker = {
        let tx = tx.clone();
        tokio::spawn(async move {
            let mut every = tokio::time::interval(Duration::from_millis(250));
            loop {
                every.tick().await;
                if tx.send(Event::Tick).await.is_err() {
                    break;
                }
            }
        })
    };
    let listener = tokio::net::TcpListener::bind(opts.listen)
        .await
        .map_err(|e| format!("binding {}: {e}", opts.listen))?;
    let addr = listener
        .local_addr()
        .map_err(|e| format!("reading the bound address: {e}"))?;
    bound(addr);
    tracing::info!(%addr, db = %opts.db.display(), tls = opts.tls.is_some(), token = opts.token.is_some(), "coordinator listening");

    let (health, health_service) = tonic_health::server::health_reporter();
    health.set_serving::<WorkerServiceServer<Handle>>().await;
    health.set_serving::<ClientServiceServer<Handle>>().await;
    let handle = Handle(tx);
    let auth = check_token(opts.token.clone());
    let workers = tonic::service::interceptor::InterceptedService::new(
        WorkerServiceServer::new(handle.clone())
            .max_decoding_message_size(MAX_MESSAGE_BYTES)
            .max_encoding_message_size(MAX_MESSAGE_BYTES),
        auth.clone(),
    );
    let clients = tonic::service::interceptor::InterceptedService::new(
        ClientServiceServer::new(handle)
            .max_decoding_message_size(MAX_MESSAGE_BYTES)
            .max_encoding_message_size(MAX_MESSAGE_BYTES),
        auth,
    );
    // Small request/reply pairs: without TCP_NODELAY, Nagle's algorithm and delayed ACKs
    // hold every reply ~40 ms (measured: a lease every 50 ms instead of every few ms).
    let incoming = tokio_stream::StreamExt::map(TcpListenerStream::new(listener), |s| {
        if let Ok(s) = &s {
            let _ = s.set_nodelay(true);
        }
        s
    });
    let mut builder = Server::builder();
    if let Some((cert, key)) = &opts.tls {
        builder = builder
            .tls_config(ServerTlsConfig::new().identity(Identity::from_pem(cert, key)))
            .map_err(|e| {
                format!(
                    "TLS configuration: {e} (--tls-cert must hold the PEM certificate chain, \
                     the coordinator's own certificate first, and --tls-key the PEM private \
                     key of that certificate)"
                )
            })?;
    }
    let result = builder
        .layer(tower::util::MapRequestLayer::new(tag_method))
        .add_service(health_service)
        .add_service(workers)
        .add_service(clients)
        .serve_with_incoming_shutdown(incoming, shutdown)
        .await
        .map_err(|e| format!("serving: {e}"));
    ticker.abort();
    // The handlers' senders are gone with the server; the loop ends once the ticker's is too.
    let _ = ticker.await;
    let _ = tokio::task::spawn_blocking(move || loop_thread.join()).await;
    tracing::info!("coordinator stopped");
    result
}
