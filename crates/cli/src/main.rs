//! `salient`: the one command-line tool. It parses flags into validated specs and calls the
//! libraries; the numerics live in `salient-core`, plots and tables in `salient-report`.

mod orbit;
mod precision;
mod usage;

use clap::{Parser, Subcommand};
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
    /// Speed against error: every method over a ladder of τ or δ on one orbit, against a
    /// double-double Taylor reference.
    Precision(precision::PrecisionArgs),
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    let result = match cli.command {
        Command::Orbit(args) => orbit::run(args),
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
