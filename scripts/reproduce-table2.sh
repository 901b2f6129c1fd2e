#!/usr/bin/env bash
# Reproduces the seed paper's Table 2 with `salient run examples/table2.toml`, or a subset:
#   scripts/reproduce-table2.sh                 # the whole table (hours on 2 cores)
#   scripts/reproduce-table2.sh tm-sbab2c 1e4   # rows of one method and t_final
# Writes out/table2[-METHOD-T]/table.md and prints it. The whole table runs as one sweep, in
# which every run after the first of its tau and t_final takes the labellers of the run before
# it as a scheduling forecast (same results, far less speculative work); rows of one method
# have no such predecessor.
set -euo pipefail
cd "$(dirname "$0")/.."
cargo build --release -q -p salient-cli
spec=examples/table2.toml
out=out/table2
if [ $# -ge 1 ]; then
  method=$1; t_final=${2:-1e4}
  out=out/table2-$method-$t_final
  spec=$(mktemp --suffix=.toml)
  trap 'rm -f "$spec"' EXIT
  sed -e "s/^method = .*/method = [\"$method\"]/" -e "s/^t_final = .*/t_final = [$t_final]/" \
      examples/table2.toml > "$spec"
fi
./target/release/salient run "$spec" --out "$out"
