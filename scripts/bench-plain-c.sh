#!/usr/bin/env bash
# Measures `salient run` against the plain single-threaded C implementation of the same fast-PSS
# rule (scripts/plain-c/fastpss.c), side by side on this host: issue 4 states its speed aims
# against that C program ("≈ 1.7 s here" at τ = 0.5, "≈ 75 s" at τ = 0.01), so the ratio says
# whether an aim is met on a host faster or slower than the one the aims were written on.
#   scripts/bench-plain-c.sh            # τ = 0.5, t = 1e4, 400×400, 3 rounds
#   scripts/bench-plain-c.sh 0.01 1     # τ = 0.01 (the C run takes about a minute), 1 round
# Prints one line per run: program, threads, wall, regular / sticky / chaotic %, work done.
set -euo pipefail
cd "$(dirname "$0")/.."
tau=${1:-0.5}
rounds=${2:-3}
t_final=1e4
cargo build --release -q -p salient-cli
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
cc -O2 -o "$work/fastpss" scripts/plain-c/fastpss.c -lm
sed -e 's/^method = .*/method = ["tm-sbab2c"]/' -e "s/^tau = .*/tau = [$tau]/" \
    -e "s/^t_final = .*/t_final = [$t_final]/" examples/table2.toml > "$work/spec.toml"
cat > "$work/row.py" <<'PY'
import json, sys
who, threads = sys.argv[1], sys.argv[2]
r = json.load(sys.stdin)
if who == "salient":
    r = r["runs"][0]
    work = "%d orbits, %.3e lane-steps (%d orbits dropped)" % (
        r["orbits_integrated"], r["steps_total"], r["orbits_dropped"])
else:
    work = "%d orbits, %.3e orbit-steps" % (r["orbits_integrated"], r["orbit_steps"])
p = r["percent"]
print("%-8s %s thread(s) %8.3f s   %.2f / %.2f / %.2f %%   %s" % (
    who, threads, r["wall_s"], p["regular"], p["sticky"], p["chaotic"], work))
PY
# Each program's JSON goes to a file and is read after it exits: a reader started beside it
# (python3 at the end of a pipe) takes one of the two cores while its interpreter starts, and
# that cost a 2-thread run ~50 ms of its ~0.17 s (alternated: 0.206-0.235 s through a pipe,
# 0.162-0.180 s to a file).
for round in $(seq "$rounds"); do
  "$work/fastpss" "$tau" "$t_final" > "$work/c.json"
  python3 "$work/row.py" "plain C" 1 < "$work/c.json"
  for threads in 1 2; do
    ./target/release/salient run "$work/spec.toml" --threads "$threads" --json \
        --out "$work/out" > "$work/salient.json" 2>/dev/null
    python3 "$work/row.py" salient "$threads" < "$work/salient.json"
  done
done
