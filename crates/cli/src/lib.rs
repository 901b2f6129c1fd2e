//! `salient`: the one command-line tool. It parses flags into validated specs and calls the
//! libraries; the numerics live in `salient-core`, plots and tables in `salient-report`.
//! Everything but the binary's entry point is this library: it needs only the metadata of the
//! crates it calls, so it compiles while salient-grid's engines are still being optimised.

mod client;
mod cluster;
mod human;
mod orbit;
mod output;
mod precision;
mod run;
mod spec;
mod usage;

use clap::{Parser, Subcommand};
use std::io::IsTerminal;
use std::process::ExitCode;
use tracing::Level;
use tracing_subscriber::filter::Targets;
use tracing_subscriber::layer::SubscriberExt;
use tracing_subscriber::util::SubscriberInitExt;
use tracing_subscriber::Layer;

#[derive(Parser)]
#[command(
    name = "salient",
    version,
    about = "Map order and chaos in Hamiltonian systems"
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
    /// Log lines on stderr as text or JSON (default: $SALIENT_LOG_FORMAT, else text).
    #[arg(long, global = true, value_enum)]
    log_format: Option<LogFormat>,
}

#[derive(Subcommand)]
enum Command {
    /// Integrate one orbit with its deviation vectors and report SALI, GALI, mLE and energy error.
    Orbit(orbit::OrbitArgs),
    /// Classify a grid of initial conditions on the surface of section for every member of a
    /// sweep (embedded: everything in this process).
    Run(run::RunArgs),
    /// Speed against error: every method over a ladder of τ or δ on one orbit, against a
    /// double-double Taylor reference.
    Precision(precision::PrecisionArgs),
    /// Serve jobs to workers over gRPC, with a durable store (distributed mode).
    Coordinator(cluster::CoordinatorArgs),
    /// Integrate tiles leased from a coordinator.
    Worker(cluster::WorkerArgs),
    /// Send a job spec to the coordinator; prints the job id.
    Submit(client::SubmitArgs),
    /// Jobs on the coordinator: state, runs done, cells resolved, orbits/s, workers.
    Status(client::StatusArgs),
    /// Live progress of a job, one bar per run.
    Watch(client::JobArgs),
    /// Fetch a finished job's results and write the same files as `salient run`.
    Results(client::ResultsArgs),
    /// Cancel a job.
    Cancel(client::JobArgs),
}

#[derive(Clone, Copy, Debug, clap::ValueEnum)]
enum LogFormat {
    Text,
    Json,
}

/// Runs the command line of this process.
pub fn main() -> ExitCode {
    let cli = Cli::parse();
    // Progress and diagnostics go to stderr through tracing; RUST_LOG (a level, or
    // `target=level` pairs after an optional default level, comma-separated) overrides the
    // level and SALIENT_LOG_FORMAT=json makes the lines machine-readable.
    let filter: Targets = std::env::var("RUST_LOG")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or_else(|| Targets::new().with_default(Level::INFO));
    let layer = tracing_subscriber::fmt::layer()
        .with_writer(std::io::stderr)
        .with_target(false)
        .with_ansi(std::io::stderr().is_terminal());
    let json = match cli.log_format {
        Some(f) => matches!(f, LogFormat::Json),
        None => std::env::var("SALIENT_LOG_FORMAT").as_deref() == Ok("json"),
    };
    let registry = tracing_subscriber::registry();
    if json {
        registry.with(layer.json().with_filter(filter)).init();
    } else {
        registry.with(layer.with_filter(filter)).init();
    }
    let result = match cli.command {
        Command::Orbit(args) => orbit::run(args),
        Command::Run(args) => run::run(args),
        Command::Precision(args) => precision::run(args),
        Command::Coordinator(args) => cluster::coordinator(args),
        Command::Worker(args) => cluster::worker(args),
        Command::Submit(args) => client::submit(args),
        Command::Status(args) => client::status(args),
        Command::Watch(args) => client::watch(args),
        Command::Results(args) => client::results(args),
        Command::Cancel(args) => client::cancel(args),
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e}");
            ExitCode::from(e.exit_code())
        }
    }
}
