//! `salient`: the one command-line tool. It parses flags into validated specs and calls the
//! libraries; the numerics live in `salient-core`, plots and tables in `salient-report`.

mod orbit;
mod precision;
mod run;
mod spec;
mod usage;

use clap::{Parser, Subcommand};
use std::io::IsTerminal;
use std::process::ExitCode;

#[derive(Parser)]
#[command(
    name = "salient",
    version,
    about = "Map order and chaos in Hamiltonian systems"
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
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
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    // Progress and diagnostics go to stderr through tracing; RUST_LOG overrides the level and
    // SALIENT_LOG_FORMAT=json makes the lines machine-readable.
    let filter = tracing_subscriber::EnvFilter::try_from_default_env()
        .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("info"));
    let builder = tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_writer(std::io::stderr)
        .with_target(false)
        .with_ansi(std::io::stderr().is_terminal());
    if std::env::var("SALIENT_LOG_FORMAT").as_deref() == Ok("json") {
        builder.json().init();
    } else {
        builder.init();
    }
    let result = match cli.command {
        Command::Orbit(args) => orbit::run(args),
        Command::Run(args) => run::run(args),
        Command::Precision(args) => precision::run(args),
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e}");
            ExitCode::from(e.exit_code())
        }
    }
}
