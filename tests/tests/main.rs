//! End-to-end tests of the `salient` binary and numerical hard cases, one module per subject,
//! built as one test binary (each binary would link the whole gRPC and SQLite stack anew).

#[path = "../../crates/core/tests/common/mod.rs"]
mod common;
mod distributed_cli;
mod docs_check;
mod docs_examples;
mod hard_cases_cli;
mod hard_cases_numerics;
mod hardening_cli;
mod indicators_cli;
mod maps_cli;
mod orbit_cli;
mod plain_c_cli;
mod polynomial_cli;
mod polynomial_grid_cli;
mod precision_cli;
mod readme_cli;
mod results_nc_cli;
mod resume_cli;
mod run_cli;
mod simulate_cli;
mod soak_cli;
mod table2_script;
