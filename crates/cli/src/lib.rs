//! `salient`: the one command-line tool. It parses flags into validated specs and calls the
//! libraries; the numerics live in `salient-core`, plots and tables in `salient-report`.
//! Everything but the binary's entry point is this library: it needs only the metadata of the
//! crates it calls, so it compiles while salient-core's engines are still being optimised.

mod checkpoint;
#[cfg(feature = "distributed")]
mod client;
#[cfg(feature = "distributed")]
mod cluster;
mod dataset;
mod grid_precision;
mod human;
mod ladder;
mod maps;
mod orbit;
mod output;
mod precision;
mod run;
#[cfg(feature = "distributed")]
mod simulate;
mod spec;
mod system;
mod usage;

use clap::{Parser, Subcommand};
use std::io::IsTerminal;
use std::process::ExitCode;
use tracing::Level;
use tracing_subscriber::filter::Targets;
use tracing_subscriber::layer::SubscriberExt;
use tracing_subscriber::util::SubscriberInitExt;
use tracing_subscriber::Layer;
use usage::{CliError, CliResult};

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
    /// double-double Taylor reference; or, with --grid, every run of a sweep cell by cell
    /// against a reference run of the same grid.
    Precision(precision::PrecisionArgs),
    #[cfg(feature = "distributed")]
    #[command(flatten)]
    Distributed(Distributed),
    /// A build without the distributed mode takes any other command name and refuses it
    /// plainly (exit 2) instead of calling it unknown.
    #[cfg(not(feature = "distributed"))]
    #[command(external_subcommand)]
    Other(Vec<String>),
}

/// The distributed mode's commands (cargo feature `distributed`, on by default).
#[cfg(feature = "distributed")]
#[derive(Subcommand)]
enum Distributed {
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
    /// Predict how a job scales over many workers: the real scheduler against simulated
    /// workers in virtual time (table and speedup plot).
    Simulate(simulate::SimulateArgs),
}

#[cfg(feature = "distributed")]
fn distributed(command: Distributed) -> CliResult<()> {
    match command {
        Distributed::Coordinator(args) => cluster::coordinator(args),
        Distributed::Worker(args) => cluster::worker(args),
        Distributed::Submit(args) => client::submit(args),
        Distributed::Status(args) => client::status(args),
        Distributed::Watch(args) => client::watch(args),
        Distributed::Results(args) => client::results(args),
        Distributed::Cancel(args) => client::cancel(args),
        Distributed::Simulate(args) => simulate::simulate(args),
    }
}

/// The names of the distributed mode's commands, for a build without them (a test checks them
/// against `Distributed`).
#[cfg_attr(feature = "distributed", allow(dead_code))]
const DISTRIBUTED: [&str; 8] = [
    "coordinator",
    "worker",
    "submit",
    "status",
    "watch",
    "results",
    "cancel",
    "simulate",
];

/// The refusal of a command name that a build without the distributed mode does not have
/// (compiled in every build, so that the tests check it).
#[cfg_attr(feature = "distributed", allow(dead_code))]
fn not_in_this_build(words: Vec<String>) -> CliResult<()> {
    let name = words.first().map_or("", String::as_str);
    Err(CliError::Usage(if DISTRIBUTED.contains(&name) {
        format!(
            "`{name}` belongs to the distributed mode, which this build leaves out (built with \
             --no-default-features): `cargo build --release -p salient-cli` builds it"
        )
    } else {
        format!("unknown command `{name}` (commands: run, orbit, precision)")
    }))
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
    // Engine choices (speed only, never results) from the environment, handed to the
    // libraries as configuration: SALIENT_SIMD=pinned runs the AVX2 copies only,
    // SALIENT_FORECAST=0 turns forecasts off.
    salient_core::engine::configure(salient_core::engine::EngineChoices {
        pinned_simd: std::env::var("SALIENT_SIMD").as_deref() == Ok("pinned"),
        forecasts: std::env::var("SALIENT_FORECAST").as_deref() != Ok("0"),
    });
    let result = match cli.command {
        Command::Orbit(args) => orbit::run(args),
        Command::Run(args) => run::run(args),
        Command::Precision(args) => precision::run(args),
        #[cfg(feature = "distributed")]
        Command::Distributed(command) => distributed(command),
        #[cfg(not(feature = "distributed"))]
        Command::Other(words) => not_in_this_build(words),
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e}");
            ExitCode::from(e.exit_code())
        }
    }
}

#[cfg(test)]
mod tests {
    use super::not_in_this_build;

    /// The names a build without the distributed mode refuses are its commands, all of them.
    #[cfg(feature = "distributed")]
    #[test]
    fn the_refused_names_are_the_distributed_commands() {
        use super::{Distributed, DISTRIBUTED};
        let cmd = <Distributed as clap::Subcommand>::augment_subcommands(clap::Command::new("x"));
        let names: Vec<&str> = cmd.get_subcommands().map(|c| c.get_name()).collect();
        assert_eq!(names, DISTRIBUTED);
    }

    /// A build without the distributed mode names what it left out for the distributed
    /// commands, calls other names unknown, and exits 2 for both.
    #[test]
    fn a_build_without_the_distributed_mode_refuses_its_commands_plainly() {
        let refusal = |name: &str| not_in_this_build(vec![name.to_string(), "--help".into()]);
        let e = refusal("worker").unwrap_err();
        assert_eq!(e.exit_code(), 2);
        assert!(e.to_string().contains("distributed mode"), "{e}");
        assert!(
            e.to_string()
                .contains("cargo build --release -p salient-cli"),
            "{e}"
        );
        let e = refusal("bogus").unwrap_err();
        assert_eq!(e.exit_code(), 2);
        assert_eq!(
            e.to_string(),
            "unknown command `bogus` (commands: run, orbit, precision)"
        );
    }
}
