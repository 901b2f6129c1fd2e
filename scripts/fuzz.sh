#!/usr/bin/env bash
# Fuzzes the job-spec parser and the coordinator's request handlers (proptest: arbitrary
# bytes, token-level edits of a good spec, random structured reports) with many more cases
# than the test suite runs. No corpus is kept: failures are shrunk by proptest and written to
# the tests' *.proptest-regressions files, which are committed so they are re-run forever.
#
#   scripts/fuzz.sh [CASES]      (default 20000 per property)
set -euo pipefail
cd "$(dirname "$0")/.."
cases=${1:-20000}
[[ $cases =~ ^[1-9][0-9]*$ ]] || { echo "fuzz: CASES must be a positive integer" >&2; exit 2; }
export PROPTEST_CASES=$cases
time cargo test --release -p salient-grid --test integration spec_fuzz::
time cargo test --release -p salient-coordinator --test integration wire_fuzz::
