#!/usr/bin/env bash
# The project's test command (README, .ci/run). The tests run in the release profile, so they
# share every compiled crate with the README's first command (`cargo run --release`), and the
# end-to-end tests run the `salient` binary of the default build (with the distributed mode).
# One `cargo build` builds that binary and every test binary, so that cargo schedules them
# together on every core (cargo test builds no binary of another package for its tests); the
# `cargo test` after it only runs them. Examples and benchmarks are left to
# `cargo clippy --all-targets` and their own commands.
set -euo pipefail
cd "$(dirname "$0")/.."
cargo build --locked --release --workspace --bins --tests
cargo test --locked --release --workspace --tests "$@"
