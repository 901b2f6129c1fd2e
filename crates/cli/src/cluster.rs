//! `salient coordinator` and `salient worker`: the long-running processes of the distributed
//! mode. Both stop cleanly on SIGTERM or Ctrl-C (the worker drains first).

use crate::usage::{positive, runtime, CliError, CliResult};
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
    /// PEM certificate chain for TLS (with --tls-key).
    #[arg(long, requires = "tls_key")]
    tls_cert: Option<PathBuf>,
    /// PEM private key for TLS (with --tls-cert).
    #[arg(long, requires = "tls_cert")]
    tls_key: Option<PathBuf>,
    /// Seconds a lease lives without a poll that renews it.
    #[arg(long, default_value_t = 30.0)]
    lease_seconds: f64,
    /// Seconds between progress log lines of each running run.
    #[arg(long, default_value_t = 10.0)]
    progress_seconds: f64,
    /// Fast PSS: cells per worker thread in one lease for tangent-map methods (smaller:
    /// fresher claims, less dropped work; larger: fewer round trips); adaptive methods, one
    /// orbit per thread instead of a batch of 4, get a quarter of it.
    #[arg(long, default_value_t = 8)]
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
}

fn read(path: &PathBuf, flag: &str) -> CliResult<Vec<u8>> {
    std::fs::read(path)
        .map_err(|e| CliError::Usage(format!("{flag}: cannot read {}: {e}", path.display())))
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
    let lease = positive("--lease-seconds", args.lease_seconds)?;
    let progress = positive("--progress-seconds", args.progress_seconds)?;
    let tls = match (&args.tls_cert, &args.tls_key) {
        (Some(c), Some(k)) => Some((read(c, "--tls-cert")?, read(k, "--tls-key")?)),
        _ => None,
    };
    if !(1..=100_000).contains(&args.lease_cells_per_thread) {
        return Err(CliError::Usage(format!(
            "--lease-cells-per-thread must be in 1..=100000 (got {})",
            args.lease_cells_per_thread
        )));
    }
    if args.token.as_deref() == Some("") {
        return Err(CliError::Usage("--token must not be empty".into()));
    }
    let opts = salient_coordinator::Options {
        listen: args.listen,
        db: args.db,
        token: args.token,
        tls,
        config: Config {
            lease: Duration::from_secs_f64(lease),
            poll: Duration::from_millis(200),
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
    // Bad addresses are bad input (exit 2), found before anything starts.
    salient_worker::endpoint(&args.coordinator, None).map_err(CliError::Usage)?;
    let tls_ca = args
        .tls_ca
        .as_ref()
        .map(|p| read(p, "--tls-ca"))
        .transpose()?;
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
        token: args.token,
        tls_ca,
        max_leases: args.leases,
    };
    let rt = runtime_for(1)?;
    rt.block_on(salient_worker::run(opts, terminated()))
        .map_err(CliError::Runtime)
}
