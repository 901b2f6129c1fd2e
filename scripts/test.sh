#!/usr/bin/env bash
# The project's test command (README, .ci/run). The tests run in the release profile, so they
# share every compiled crate with the README's first command (`cargo run --release`), and the
# end-to-end tests run the `salient` binary of the default build (with the distributed mode).
# One `cargo build` builds that binary and every test binary, so that cargo schedules them
# together on every core (cargo test builds no binary of another package for its tests); the
# `cargo test` after it only runs them. Examples and benchmarks are left to
# `cargo clippy --all-targets` and their own commands. The scaling simulator's check against
# real runs on loopback compares walls, so it runs last, alone, when the whole suite runs.
set -euo pipefail
cd "$(dirname "$0")/.."
cargo build --locked --release --workspace --bins --tests
cargo test --locked --release --workspace --tests "$@"
if (($# == 0)); then
  # --workspace, as above: one package alone unifies features otherwise and rebuilds crates.
  cargo test --locked --release --workspace --tests -- --ignored --exact \
    simulate_cli::the_simulator_predicts_loopback_runs_of_one_and_two_workers
fi
