//! `salient coordinator` and `salient worker`: the long-running processes of the distributed
//! mode. Both stop cleanly on SIGTERM or Ctrl-C (the worker drains first).

use crate::usage::{runtime, CliError, CliResult};
use clap::Args;
use salient_coordinator::scheduler::Config;
use std::net::SocketAddr;
use std::path::PathBuf;
use std::time::Duration;

#[derive(Args, Debug)]
pub struct CoordinatorArgs {
    /// Address to serve gRPC on (use 0.0.0.0:50051 to accept other hosts).
    #[arg(long, default_value = "127.0.0.1:50051")]
    listen: SocketAddr,
    /// SQLite database holding jobs and committed outcomes (created if absent).
    #[arg(long, default_value = "salient.db")]
    db: PathBuf,
    /// Bearer token workers and clients must present.
    #[arg(long, env = "SALIENT_TOKEN", hide_env_values = true)]
    token: Option<String>,
    /// Read the bearer token from this file (first line), out of sight of `ps`; it takes
    /// precedence over --token and $SALIENT_TOKEN.
    #[arg(long)]
    token_file: Option<PathBuf>,
    /// Serve a non-loopback address without a token: anyone who reaches the port may submit
    /// and cancel jobs and report results. Refused without this flag.
    #[arg(long)]
    insecure: bool,
    /// PEM certificate chain for TLS (with --tls-key).
    #[arg(long, requires = "tls_key")]
    tls_cert: Option<PathBuf>,
    /// PEM private key for TLS (with --tls-cert).
    #[arg(long, requires = "tls_cert")]
    tls_key: Option<PathBuf>,
    /// Seconds a lease lives without a poll that renews it.
    #[arg(long, default_value_t = 30.0)]
    lease_seconds: f64,
    /// Seconds without a poll after which a worker is taken for dead and its leases go to
    /// other workers; at least 5 of --poll-ms.
    #[arg(long, default_value_t = 5.0)]
    worker_timeout_seconds: f64,
    /// Milliseconds between the polls of a busy worker, told to workers as they register
    /// (10–5000). Shorter: other workers hear of outcomes sooner and drop less work; each poll
    /// costs the coordinator CPU (`salient simulate --poll-ms` predicts the trade).
    #[arg(long, default_value_t = 200)]
    poll_ms: u64,
    /// Seconds between progress log lines of each running run.
    #[arg(long, default_value_t = 10.0)]
    progress_seconds: f64,
    /// Fast PSS: cells per worker thread in one lease for tangent-map methods (smaller:
    /// fresher claims, less dropped work; larger: fewer round trips); adaptive methods get a
    /// sixteenth of it per orbit a thread runs at once (2 at the default), at least 1.
    #[arg(long, default_value_t = salient_coordinator::scheduler::LEASE_CELLS_PER_THREAD)]
    lease_cells_per_thread: usize,
    /// Refuse submitted specs whose grid holds more cells than this.
    #[arg(long, default_value_t = salient_grid::spec::MAX_CELLS)]
    max_cells: usize,
    /// Refuse submitted specs whose cells × runs exceed this: the coordinator keeps every
    /// run's ledger in memory (about 25 bytes per cell and run).
    #[arg(long, default_value_t = salient_coordinator::scheduler::MAX_CELL_RUNS)]
    max_cell_runs: usize,
    /// Write the bound address to this file once listening (useful with port 0).
    #[arg(long)]
    address_file: Option<PathBuf>,
}

#[derive(Args, Debug)]
pub struct WorkerArgs {
    /// Coordinator URL (http:// or https://).
    #[arg(
        long,
        env = "SALIENT_COORDINATOR",
        default_value = "http://127.0.0.1:50051"
    )]
    coordinator: String,
    /// Integration threads (default: every core).
    #[arg(long)]
    threads: Option<usize>,
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
    /// Name shown in the coordinator's logs (default: host name and process id).
    #[arg(long)]
    name: Option<String>,
    /// Tile leases held at once (one running, the rest ready); fast-PSS leases are taken one
    /// at a time whatever this says (a second would speculate ahead of the claims).
    #[arg(long, default_value_t = 2)]
    leases: usize,
    /// Seconds a stopping worker (SIGTERM, Ctrl-C) may take to finish its lease in progress
    /// and hand in its reports; past them it stops anyway, its leases going to others.
    #[arg(long, default_value_t = 60.0)]
    drain_seconds: f64,
}

fn read(path: &PathBuf, flag: &str) -> CliResult<Vec<u8>> {
    std::fs::read(path)
        .map_err(|e| CliError::Usage(format!("{flag}: cannot read {}: {e}", path.display())))
}

/// The token given by value or by file (its first line, without surrounding white space); an
/// empty one is refused, as it would match a request that sends an empty token.
pub fn token(value: Option<String>, file: Option<&PathBuf>) -> CliResult<Option<String>> {
    let token = match (value, file) {
        (_, Some(path)) => {
            let text = String::from_utf8(read(path, "--token-file")?).map_err(|_| {
                CliError::Usage(format!("--token-file {}: not UTF-8 text", path.display()))
            })?;
            let first = text.lines().next().unwrap_or("").trim().to_string();
            if first.is_empty() {
                return Err(CliError::Usage(format!(
                    "--token-file {}: the first line is empty",
                    path.display()
                )));
            }
            Some(first)
        }
        (value, None) => value,
    };
    if token.as_deref() == Some("") {
        return Err(CliError::Usage("--token must not be empty".into()));
    }
    Ok(token)
}

/// Reads a PEM file and checks it holds what `flag` asks for (`what`: "CERTIFICATE" or
/// "PRIVATE KEY"), so a swapped or wrong file is named before TLS sees it.
fn read_pem(path: &PathBuf, flag: &str, what: &str) -> CliResult<Vec<u8>> {
    let bytes = read(path, flag)?;
    let text = String::from_utf8_lossy(&bytes);
    let holds = |kind: &str| {
        text.lines().any(|l| {
            l.starts_with("-----BEGIN ") && l.trim_end().ends_with(&format!("{kind}-----"))
        })
    };
    if holds(what) {
        return Ok(bytes);
    }
    let found = if holds("PRIVATE KEY") {
        "a private key"
    } else if holds("CERTIFICATE") {
        "a certificate"
    } else {
        "no PEM block"
    };
    Err(CliError::Usage(format!(
        "{flag} {}: expected a PEM {what}, found {found}{}",
        path.display(),
        if found == "no PEM block" {
            " (a DER file must be converted: openssl x509 -in F -inform der -out F.pem)"
        } else {
            " (are --tls-cert and --tls-key swapped?)"
        }
    )))
}

/// A duration flag in `[min, one day]`: beyond that it is a mistake, and far beyond it a
/// duration cannot even be represented.
fn seconds_in(flag: &str, v: f64, min: f64) -> CliResult<f64> {
    const DAY: f64 = 86_400.0;
    if (min..=DAY).contains(&v) {
        Ok(v)
    } else {
        Err(CliError::Usage(format!(
            "{flag} must be in [{min}, {DAY}] seconds (got {v})"
        )))
    }
}

/// Refuses to serve a non-loopback address without a token unless the operator accepted it
/// with `--insecure`; warns where a token would cross the network in clear.
fn check_exposure(listen: SocketAddr, token: bool, tls: bool, insecure: bool) -> CliResult<()> {
    if listen.ip().is_loopback() {
        return Ok(());
    }
    if !token && !insecure {
        return Err(CliError::Usage(format!(
            "--listen {listen} accepts other hosts, and without a token anyone who reaches it \
             may submit, cancel and report: give --token-file (or --token / $SALIENT_TOKEN), \
             ideally with --tls-cert and --tls-key, or say --insecure to accept that"
        )));
    }
    if token && !tls {
        tracing::warn!(%listen, "serving without TLS: the token crosses the network in clear");
    }
    Ok(())
}

/// Resolves on Ctrl-C or SIGTERM.
pub async fn terminated() {
    let ctrl_c = async {
        let _ = tokio::signal::ctrl_c().await;
    };
    #[cfg(unix)]
    {
        use tokio::signal::unix::{signal, SignalKind};
        match signal(SignalKind::terminate()) {
            Ok(mut term) => {
                tokio::select! {
                    _ = ctrl_c => {}
                    _ = term.recv() => {}
                }
            }
            Err(_) => ctrl_c.await,
        }
    }
    #[cfg(not(unix))]
    ctrl_c.await;
}

pub fn runtime_for(threads: usize) -> CliResult<tokio::runtime::Runtime> {
    tokio::runtime::Builder::new_multi_thread()
        .worker_threads(threads)
        .enable_all()
        .build()
        .map_err(|e| runtime("starting the async runtime", e))
}

pub fn coordinator(args: CoordinatorArgs) -> CliResult<()> {
    let lease = seconds_in("--lease-seconds", args.lease_seconds, 0.01)?;
    let worker_timeout = seconds_in("--worker-timeout-seconds", args.worker_timeout_seconds, 1.0)?;
    let progress = seconds_in("--progress-seconds", args.progress_seconds, 0.01)?;
    let tls = match (&args.tls_cert, &args.tls_key) {
        (Some(c), Some(k)) => Some((
            read_pem(c, "--tls-cert", "CERTIFICATE")?,
            read_pem(k, "--tls-key", "PRIVATE KEY")?,
        )),
        _ => None,
    };
    let token = token(args.token, args.token_file.as_ref())?;
    check_exposure(args.listen, token.is_some(), tls.is_some(), args.insecure)?;
    if !(10..=5000).contains(&args.poll_ms) {
        return Err(CliError::Usage(format!(
            "--poll-ms must be in 10..=5000 (got {})",
            args.poll_ms
        )));
    }
    if worker_timeout * 1e3 < 5.0 * args.poll_ms as f64 {
        return Err(CliError::Usage(format!(
            "--worker-timeout-seconds must be at least 5 polls of --poll-ms ({} s; got {})",
            5.0 * args.poll_ms as f64 / 1e3,
            args.worker_timeout_seconds
        )));
    }
    if !(1..=100_000).contains(&args.lease_cells_per_thread) {
        return Err(CliError::Usage(format!(
            "--lease-cells-per-thread must be in 1..=100000 (got {})",
            args.lease_cells_per_thread
        )));
    }
    let opts = salient_coordinator::Options {
        listen: args.listen,
        db: args.db,
        token,
        tls,
        config: Config {
            lease: Duration::from_secs_f64(lease),
            poll: Duration::from_millis(args.poll_ms),
            worker_timeout: Duration::from_secs_f64(worker_timeout),
            lease_cells_per_thread: args.lease_cells_per_thread,
            max_cells: args.max_cells,
            max_cell_runs: args.max_cell_runs,
        },
        progress_every: Duration::from_secs_f64(progress),
    };
    let address_file = args.address_file;
    let rt = runtime_for(2)?;
    rt.block_on(salient_coordinator::serve(
        opts,
        move |addr| {
            if let Some(f) = address_file {
                if let Err(e) = std::fs::write(&f, format!("{addr}\n")) {
                    tracing::error!(file = %f.display(), error = %e, "cannot write the address file");
                }
            }
        },
        terminated(),
    ))
    .map_err(CliError::Runtime)
}

pub fn worker(args: WorkerArgs) -> CliResult<()> {
    let threads = match args.threads {
        Some(n @ 1..=1024) => n,
        Some(n) => {
            return Err(CliError::Usage(format!(
                "--threads must be in 1..=1024 (got {n})"
            )))
        }
        None => std::thread::available_parallelism().map_or(1, |n| n.get()),
    };
    if !(1..=64).contains(&args.leases) {
        return Err(CliError::Usage(format!(
            "--leases must be in 1..=64 (got {})",
            args.leases
        )));
    }
    let drain = seconds_in("--drain-seconds", args.drain_seconds, 0.0)?;
    // Bad addresses are bad input (exit 2), found before anything starts.
    salient_proto::endpoint(&args.coordinator, None).map_err(CliError::Usage)?;
    let tls_ca = args
        .tls_ca
        .as_ref()
        .map(|p| read_pem(p, "--tls-ca", "CERTIFICATE"))
        .transpose()?;
    let token = token(args.token, args.token_file.as_ref())?;
    let name = args.name.unwrap_or_else(|| {
        let host = std::fs::read_to_string("/proc/sys/kernel/hostname")
            .map(|h| h.trim().to_string())
            .unwrap_or_else(|_| "worker".into());
        format!("{host}-{}", std::process::id())
    });
    let opts = salient_worker::Options {
        coordinator: args.coordinator,
        threads,
        name,
        token,
        tls_ca,
        max_leases: args.leases,
        drain_timeout: Duration::from_secs_f64(drain),
    };
    let rt = runtime_for(1)?;
    rt.block_on(salient_worker::run(opts, terminated()))
        .map_err(CliError::Runtime)
}
