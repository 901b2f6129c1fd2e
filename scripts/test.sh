#!/usr/bin/env bash
# The project's test command (README, .ci/run). The tests run in the release profile, so they
# share every compiled crate with the README's first command (`cargo run --release`), and the
# end-to-end tests run the very `salient` binary that command builds (cargo builds another
# package's binary for no test, so it is built first). Examples and benchmarks are left to
# `cargo clippy --all-targets` and their own commands: the suite neither runs them nor waits
# for their builds.
set -euo pipefail
cd "$(dirname "$0")/.."
cargo build --locked --release -p salient-cli --bin salient
cargo test --locked --release --workspace --tests "$@"
