#!/usr/bin/env bash
# Regenerates crates/proto/src/generated/salient.v1.rs after a change to
# proto/salient/v1/salient.proto (salient-proto's tests fail until it is run). The generator is
# a workspace of its own (crates/proto/gen), so builds of Salient never compile protox.
set -euo pipefail
cd "$(dirname "$0")/.."
cargo run --locked --quiet --manifest-path crates/proto/gen/Cargo.toml --target-dir target/proto-gen
