#!/usr/bin/env bash
# The project's test command (README, .ci/run). End-to-end tests run the real `salient`
# binary, which cargo does not build for another package's tests, so build it first with the
# same (optimised) profile the tests use, then run every test of the workspace.
set -euo pipefail
cd "$(dirname "$0")/.."
cargo build --locked --profile test -p salient-cli --bin salient
cargo test --locked --workspace "$@"
