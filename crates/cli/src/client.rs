//! Client commands of the distributed mode: `submit`, `status`, `watch`, `results`, `cancel`.
//! `results` rebuilds each run's ledger from the coordinator's committed outcomes and writes
//! the same files as `salient run`, so both modes' outputs can be compared byte for byte.

use crate::cluster::runtime_for;
use crate::human::rounded;
use crate::output::Staged;
use crate::run::{write_run, write_sweep, RunResult};
use crate::spec::{self, JobSpec};
use crate::usage::{CliError, CliResult};
use clap::Args;
use indicatif::{MultiProgress, ProgressBar, ProgressStyle};
use salient_grid::Ledger;
use salient_proto::v1;
use salient_proto::v1::client_service_client::ClientServiceClient;
use salient_proto::{
    endpoint, explain_transport, outcome_from_wire, Expected, Token, MAX_MESSAGE_BYTES,
};
use salient_report::CELL_MAP_DPI;
use std::error::Error;
use std::io::IsTerminal;
use std::path::{Path, PathBuf};
use std::time::Duration;
use tonic::service::interceptor::InterceptedService;
use tonic::transport::Channel;
use tonic::Code;

#[derive(Args, Debug, Clone)]
pub struct Connection {
    /// Coordinator URL (http:// or https://).
    #[arg(
        long,
        env = "SALIENT_COORDINATOR",
        default_value = "http://127.0.0.1:50051"
    )]
    coordinator: String,
    /// Bearer token for the coordinator.
    #[arg(long, env = "SALIENT_TOKEN", hide_env_values = true)]
    token: Option<String>,
    /// Read the bearer token from this file (first line), out of sight of `ps`; it takes
    /// precedence over --token and $SALIENT_TOKEN.
    #[arg(long)]
    token_file: Option<PathBuf>,
    /// PEM of the CA that signed the coordinator's certificate (https only).
    #[arg(long)]
    tls_ca: Option<PathBuf>,
}

#[derive(Args, Debug)]
pub struct SubmitArgs {
    /// Job spec (TOML, or JSON with the same schema); validated here before it is sent.
    spec: PathBuf,
    #[command(flatten)]
    conn: Connection,
    /// Wait for the job to finish and print its result JSON.
    #[arg(long)]
    wait: bool,
    /// Print exactly one JSON object on stdout.
    #[arg(long)]
    json: bool,
    /// With --wait: also write the results' files here (without it, only the JSON summary).
    #[arg(long, requires = "wait")]
    out: Option<PathBuf>,
    /// Refuse specs whose grid holds more cells than this (the coordinator has its own cap).
    #[arg(long, default_value_t = spec::MAX_CELLS)]
    max_cells: usize,
}

#[derive(Args, Debug)]
pub struct StatusArgs {
    /// One job (default: every job).
    job: Option<u64>,
    #[command(flatten)]
    conn: Connection,
    /// Print exactly one JSON object on stdout.
    #[arg(long)]
    json: bool,
}

#[derive(Args, Debug)]
pub struct JobArgs {
    /// The job's id, as `salient submit` printed it.
    job: u64,
    #[command(flatten)]
    conn: Connection,
}

#[derive(Args, Debug)]
pub struct ResultsArgs {
    /// The job's id, as `salient submit` printed it.
    job: u64,
    #[command(flatten)]
    conn: Connection,
    /// Wait until the job has finished.
    #[arg(long)]
    wait: bool,
    /// Output folder (default: out/<spec name>); the same files as `salient run`.
    #[arg(long)]
    out: Option<PathBuf>,
    /// Resolution of the maps' PNG files (50..=600), as `salient run --dpi`.
    #[arg(long, default_value_t = CELL_MAP_DPI)]
    dpi: u32,
    /// Print exactly one JSON object on stdout.
    #[arg(long)]
    json: bool,
}

type Client = ClientServiceClient<InterceptedService<Channel, Token>>;

/// A gRPC failure as a CLI error: bad input (unknown job, invalid spec) is exit 2.
fn rpc_error(what: &str, e: tonic::Status) -> CliError {
    match e.code() {
        // "no job 99" says it all.
        Code::NotFound => CliError::Usage(e.message().to_string()),
        Code::InvalidArgument | Code::FailedPrecondition => {
            CliError::Usage(format!("{what}: {}", e.message()))
        }
        Code::Unauthenticated | Code::DataLoss => {
            CliError::Runtime(format!("{what}: {}", e.message()))
        }
        // Failures of the connection (no answer of the coordinator's) carry their causes and,
        // for the usual mistakes, a hint.
        Code::Unavailable | Code::Unknown | Code::Internal if e.source().is_some() => {
            CliError::Runtime(format!(
                "{what}: {}",
                explain_transport(coordinator_url(), &e)
            ))
        }
        _ => CliError::Runtime(format!("{what}: {} ({:?})", e.message(), e.code())),
    }
}

/// The coordinator this process talks to (one per command), set by [`connect`]: named in the
/// hints of [`rpc_error`] and the reconnection messages of [`Away`].
static COORDINATOR_URL: std::sync::OnceLock<String> = std::sync::OnceLock::new();

fn coordinator_url() -> &'static str {
    COORDINATOR_URL.get().map_or("", String::as_str)
}

async fn connect(c: &Connection) -> CliResult<Client> {
    let _ = COORDINATOR_URL.set(c.coordinator.clone());
    let ca =
        match &c.tls_ca {
            Some(p) => Some(std::fs::read(p).map_err(|e| {
                CliError::Usage(format!("--tls-ca: cannot read {}: {e}", p.display()))
            })?),
            None => None,
        };
    let token = crate::cluster::token(c.token.clone(), c.token_file.as_ref())?;
    let channel = endpoint(&c.coordinator, ca.as_deref())
        .map_err(CliError::Usage)?
        .connect()
        .await
        .map_err(|e| {
            CliError::Runtime(format!(
                "cannot reach the coordinator at {}: {}",
                c.coordinator,
                explain_transport(&c.coordinator, &e)
            ))
        })?;
    Ok(ClientServiceClient::with_interceptor(channel, Token(token))
        .max_decoding_message_size(MAX_MESSAGE_BYTES)
        .max_encoding_message_size(MAX_MESSAGE_BYTES))
}

/// The spec as the JSON the coordinator takes (a valid TOML spec converts losslessly).
pub(crate) fn spec_json(path: &Path, max_cells: usize) -> CliResult<(JobSpec, String)> {
    let job = spec::load(path, max_cells)?;
    let text = std::fs::read_to_string(path)
        .map_err(|e| CliError::Usage(format!("spec: cannot read {}: {e}", path.display())))?;
    let name = path
        .file_name()
        .map(|n| n.to_string_lossy())
        .unwrap_or_default();
    let json = if spec::is_json(&name, &text) {
        text
    } else {
        let table: toml::Table = text
            .parse()
            .map_err(|e| CliError::Usage(format!("spec: {e}")))?;
        serde_json::to_string(&table).expect("a TOML table is JSON")
    };
    Ok((job, json))
}

pub fn submit(args: SubmitArgs) -> CliResult<()> {
    let (job, json) = spec_json(&args.spec, args.max_cells)?;
    for w in &job.warnings {
        tracing::warn!("{w}");
    }
    // With --out the output folder is checked (and staged) before the job is sent.
    let staged = match &args.out {
        Some(out) => Some((out.clone(), Staged::begin(out, "--out")?)),
        None => None,
    };
    runtime_for(1)?.block_on(async {
        let mut client = connect(&args.conn).await?;
        let reply = client
            .submit(v1::SubmitRequest {
                spec_json: json.into_bytes(),
            })
            .await
            .map_err(|e| rpc_error("submit", e))?
            .into_inner();
        tracing::info!(job = reply.job, name = %job.name, "submitted");
        if !args.wait {
            if args.json {
                println!("{}", serde_json::json!({ "job": reply.job }));
            } else {
                println!("{}", reply.job);
            }
            return Ok(());
        }
        wait_finished(&mut client, reply.job).await?;
        fetch_and_write(&mut client, reply.job, staged, CELL_MAP_DPI, true).await
    })
}

fn status_row(j: &v1::JobStatus) -> Vec<String> {
    vec![
        j.job.to_string(),
        j.name.clone(),
        j.state.clone(),
        format!("{}/{}", j.runs_done, j.runs_total),
        format!("{:.1}", j.resolved_percent),
        format!("{:.0}", j.orbits_per_s),
        j.workers.to_string(),
    ]
}

fn status_json(j: &v1::JobStatus) -> serde_json::Value {
    serde_json::json!({
        "job": j.job,
        "name": j.name,
        "state": j.state,
        "runs_done": j.runs_done,
        "runs_total": j.runs_total,
        "resolved_percent": j.resolved_percent,
        "orbits_per_s": j.orbits_per_s,
        "workers": j.workers,
        "stale_reports": j.stale_reports,
        "error": (!j.error.is_empty()).then_some(&j.error),
        "runs": j.runs.iter().map(|r| serde_json::json!({
            "run": r.run, "method": r.method, "tau": r.tau, "t_final": r.t_final,
            "delta": r.delta, "compatible": r.compatible, "resolved": r.resolved,
            "orbits": r.orbits, "dropped": r.dropped, "orbits_per_s": r.orbits_per_s,
            "eta_s": r.eta_s, "done": r.done, "wall_s": r.wall_s,
        })).collect::<Vec<_>>(),
    })
}

pub fn status(args: StatusArgs) -> CliResult<()> {
    runtime_for(1)?.block_on(async {
        let mut client = connect(&args.conn).await?;
        let reply = client
            .status(v1::StatusRequest { job: args.job })
            .await
            .map_err(|e| rpc_error("status", e))?
            .into_inner();
        if args.json {
            println!(
                "{}",
                serde_json::json!({
                    "workers": reply.workers,
                    "jobs": reply.jobs.iter().map(status_json).collect::<Vec<_>>(),
                })
            );
            return Ok(());
        }
        let mut t = salient_report::Table::new(&[
            "job",
            "name",
            "state",
            "runs done",
            "% cells resolved",
            "orbits/s",
            "workers",
        ]);
        for j in &reply.jobs {
            t.push(status_row(j));
        }
        print!("{}", t.to_markdown());
        println!("{} worker(s) connected", reply.workers);
        Ok(())
    })
}

fn run_label(r: &v1::RunProgress) -> String {
    let mut s = format!(
        "run {} {} τ={} t={:e}",
        r.run + 1,
        r.method,
        r.tau,
        r.t_final
    );
    if let Some(d) = r.delta {
        s.push_str(&format!(" δ={d:e}"));
    }
    s
}

pub fn watch(args: JobArgs) -> CliResult<()> {
    runtime_for(1)?.block_on(async {
        let mut client = connect(&args.conn).await?;
        let mut bars = Bars::new(std::io::stderr().is_terminal());
        let mut last: Option<v1::JobStatus> = None;
        let mut away = Away::default();
        // A coordinator that restarts ends the stream with an error: subscribe again.
        'subscribe: loop {
            let mut stream = match client.watch(v1::WatchRequest { job: args.job }).await {
                Ok(s) => s.into_inner(),
                Err(e) if is_transient(&e) => {
                    away.pause("watch", e).await?;
                    continue;
                }
                Err(e) => return Err(rpc_error("watch", e)),
            };
            loop {
                match stream.message().await {
                    Ok(Some(msg)) => {
                        away.back();
                        bars.show(&msg);
                        last = Some(msg);
                    }
                    Ok(None) => break 'subscribe,
                    Err(e) if is_transient(&e) => {
                        away.pause("watch", e).await?;
                        continue 'subscribe;
                    }
                    Err(e) => return Err(rpc_error("watch", e)),
                }
            }
        }
        bars.finish();
        let Some(last) = last else {
            return Err(CliError::Runtime(
                "the coordinator closed the stream".into(),
            ));
        };
        println!("job {} {}", last.job, last.state);
        match last.state.as_str() {
            "done" => Ok(()),
            other => Err(CliError::Runtime(format!("job {} ended {other}", last.job))),
        }
    })
}

/// `watch`'s display: one progress bar per run on a terminal, progress log lines otherwise.
struct Bars {
    tty: bool,
    multi: MultiProgress,
    bars: Vec<ProgressBar>,
}

impl Bars {
    fn new(tty: bool) -> Bars {
        Bars {
            tty,
            multi: MultiProgress::new(),
            bars: Vec::new(),
        }
    }

    fn show(&mut self, msg: &v1::JobStatus) {
        if !self.tty {
            for r in msg.runs.iter().filter(|r| !r.done && r.orbits > 0) {
                tracing::info!(job = msg.job, run = %run_label(r), resolved = r.resolved, compatible = r.compatible, orbits = r.orbits, orbits_per_s = rounded(r.orbits_per_s, 0), eta_s = rounded(r.eta_s.unwrap_or(f64::NAN), 1), workers = msg.workers, "progress");
            }
            return;
        }
        while self.bars.len() < msg.runs.len() {
            let r = &msg.runs[self.bars.len()];
            let b = self.multi.add(ProgressBar::new(r.compatible));
            b.set_style(
                ProgressStyle::with_template("{prefix} {bar:30} {pos}/{len} cells  {msg}")
                    .expect("template"),
            );
            b.set_prefix(run_label(r));
            self.bars.push(b);
        }
        for (b, r) in self.bars.iter().zip(&msg.runs) {
            b.set_position(r.resolved);
            b.set_message(format!(
                "{} orbits, {:.0}/s, ETA {}{}",
                r.orbits,
                r.orbits_per_s,
                r.eta_s.map_or("—".into(), |e| format!("{e:.0} s")),
                if r.done { ", done" } else { "" }
            ));
        }
    }

    fn finish(self) {
        for b in self.bars {
            b.finish();
        }
    }
}

pub fn cancel(args: JobArgs) -> CliResult<()> {
    runtime_for(1)?.block_on(async {
        let mut client = connect(&args.conn).await?;
        let reply = client
            .cancel(v1::CancelRequest { job: args.job })
            .await
            .map_err(|e| rpc_error("cancel", e))?
            .into_inner();
        println!("job {} {}", args.job, reply.state);
        Ok(())
    })
}

/// The job's status as the coordinator answers it; `None` when it knows no such job.
async fn job_status(client: &mut Client, job: u64) -> Result<Option<v1::JobStatus>, tonic::Status> {
    let reply = client
        .status(v1::StatusRequest { job: Some(job) })
        .await?
        .into_inner();
    Ok(reply.jobs.into_iter().next())
}

/// The job's status, an unknown job being bad input.
async fn known_job(client: &mut Client, job: u64) -> CliResult<v1::JobStatus> {
    job_status(client, job)
        .await
        .map_err(|e| rpc_error("status", e))?
        .ok_or_else(|| CliError::Usage(format!("no job {job}")))
}

/// How long the commands that wait (`results --wait`, `submit --wait`, `watch`) keep trying
/// to reach a coordinator that went away: a restart takes seconds, a move to another host
/// minutes.
const RECONNECT_FOR: Duration = Duration::from_secs(300);

/// Failures of the connection rather than answers of the coordinator: worth trying again.
fn is_transient(e: &tonic::Status) -> bool {
    matches!(
        e.code(),
        Code::Unavailable | Code::Unknown | Code::Cancelled | Code::DeadlineExceeded
    )
}

/// Tracks how long the coordinator has been out of reach while a command waits on it.
#[derive(Default)]
struct Away {
    since: Option<std::time::Instant>,
}

impl Away {
    /// After a transient failure: waits a moment before the next try, or gives up once the
    /// coordinator has been away for [`RECONNECT_FOR`].
    async fn pause(&mut self, what: &str, e: tonic::Status) -> CliResult<()> {
        let url = coordinator_url();
        let since = *self.since.get_or_insert_with(|| {
            tracing::warn!(coordinator = url, error = %e.message(), "coordinator out of reach; trying again");
            std::time::Instant::now()
        });
        if since.elapsed() > RECONNECT_FOR {
            return Err(CliError::Runtime(format!(
                "{what}: the coordinator at {url} has been out of reach for {} s: {}",
                RECONNECT_FOR.as_secs(),
                e.message()
            )));
        }
        tokio::time::sleep(Duration::from_millis(500)).await;
        Ok(())
    }

    fn back(&mut self) {
        if self.since.take().is_some() {
            tracing::info!(coordinator = coordinator_url(), "coordinator reached again");
        }
    }
}

/// Waits until the job is done (an error if it ends otherwise), riding out coordinator
/// restarts.
async fn wait_finished(client: &mut Client, job: u64) -> CliResult<()> {
    let mut away = Away::default();
    loop {
        let state = match job_status(client, job).await {
            Ok(status) => {
                away.back();
                status
                    .ok_or_else(|| CliError::Usage(format!("no job {job}")))?
                    .state
            }
            Err(e) if is_transient(&e) => {
                away.pause("status", e).await?;
                continue;
            }
            Err(e) => return Err(rpc_error("status", e)),
        };
        match state.as_str() {
            "done" => return Ok(()),
            s @ ("cancelled" | "failed") => {
                return Err(CliError::Runtime(format!("job {job} ended {s}")))
            }
            _ => tokio::time::sleep(Duration::from_millis(300)).await,
        }
    }
}

pub fn results(args: ResultsArgs) -> CliResult<()> {
    runtime_for(1)?.block_on(async {
        let mut client = connect(&args.conn).await?;
        let out = match args.out {
            Some(o) => o,
            None => Path::new("out").join(known_job(&mut client, args.job).await?.name),
        };
        // Checked before waiting: a folder that cannot be written fails now, not after the job.
        let dpi = crate::run::map_dpi(args.dpi)?;
        let staged = Staged::begin(&out, "--out")?;
        if args.wait {
            wait_finished(&mut client, args.job).await?;
        } else {
            let state = known_job(&mut client, args.job).await?.state;
            if state != "done" {
                return Err(CliError::Runtime(format!(
                    "job {} is {state}; results exist once it is done (use --wait)",
                    args.job
                )));
            }
        }
        fetch_and_write(&mut client, args.job, Some((out, staged)), dpi, args.json).await
    })
}

/// Streams a finished job's results, rebuilds each run's ledger from its committed outcomes
/// (the labels follow from them exactly), and writes what `salient run` writes.
async fn fetch_and_write(
    client: &mut Client,
    job: u64,
    to: Option<(PathBuf, Staged)>,
    dpi: u32,
    json: bool,
) -> CliResult<()> {
    use v1::results_chunk::Part;
    let mut stream = client
        .results(v1::ResultsRequest { job })
        .await
        .map_err(|e| rpc_error("results", e))?
        .into_inner();
    let bad = |m: String| CliError::Runtime(format!("results of job {job}: {m}"));
    let mut spec: Option<JobSpec> = None;
    // Per run: its header, the ledger being rebuilt, the checkpoint count outcomes carry, and
    // its grid (the spec's cells at the run's energy).
    let mut runs: Vec<(v1::RunHeader, Ledger, Expected, salient_grid::Grid)> = Vec::new();
    while let Some(chunk) = stream
        .message()
        .await
        .map_err(|e| rpc_error("results", e))?
    {
        match chunk.part {
            Some(Part::Header(h)) => {
                let s = spec::parse(&h.spec_json, true)
                    .map_err(|e| bad(format!("the stored spec: {e}")))?;
                spec = Some(s);
            }
            Some(Part::Run(h)) => {
                let s = spec
                    .as_ref()
                    .ok_or_else(|| bad("run before header".into()))?;
                if h.run as usize >= s.runs.len() {
                    return Err(bad(format!("run {} is not in the spec", h.run)));
                }
                let expected = Expected::of_run(&s.cell_run(h.run as usize));
                let grid = s.grid(h.run as usize);
                let mode = s.mode(h.run as usize);
                runs.push((h, Ledger::new(&grid, mode), expected, grid));
            }
            Some(Part::Outcomes(batch)) => {
                let (_, ledger, expected, grid) = runs
                    .iter_mut()
                    .find(|(h, ..)| h.run == batch.run)
                    .ok_or_else(|| bad(format!("outcomes of unknown run {}", batch.run)))?;
                for o in &batch.outcomes {
                    ledger.offer(outcome_from_wire(o, grid, *expected).map_err(bad)?);
                }
            }
            None => return Err(bad("an empty message".into())),
        }
    }
    let job_spec = spec.ok_or_else(|| bad("no header".into()))?;
    let mut results = Vec::new();
    for (h, mut ledger, _, grid) in runs {
        if !ledger.done() {
            return Err(bad(format!("run {} is incomplete", h.run)));
        }
        // Rebuilt from committed outcomes only: the coordinator's dropped work is reported.
        ledger.dropped = h.orbits_dropped;
        ledger.dropped_steps = h.steps_dropped;
        let r = RunResult::new(
            &job_spec,
            h.run as usize,
            grid,
            ledger,
            h.cpu_s,
            h.wall_s,
            to.as_ref().map_or(Path::new(""), |(out, _)| out.as_path()),
        );
        if let Some((_, staged)) = &to {
            write_run(&job_spec, &r, staged.path(), dpi)?;
        }
        results.push(r);
    }
    match to {
        Some((out, staged)) => write_sweep(&results, Some((&out, staged)), Some(job), json),
        None => write_sweep(&results, None, Some(job), json),
    }
}
