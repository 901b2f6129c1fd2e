#!/usr/bin/env bash
# Reproduces the seed paper's Table 2 from examples/table2.toml, one sweep per τ and t_final
# (the four methods together: every run after the first takes the labellers of the run before
# it as a scheduling forecast, same results with far less speculative work). Each sweep writes
# its own folder, and a sweep whose folder holds its table.json is finished and skipped, so the
# script can be stopped at any time and run again to go on where it stopped (a sweep stopped part
# way resumes from its checkpoint: `salient run --resume`).
#
#   scripts/reproduce-table2.sh [OPTIONS] [METHOD [T_FINAL]]
#
#   METHOD      one method's rows only (tm-sbab2c, dop853, taylor, taylor-dd); default (or all):
#               all four
#   T_FINAL     one t_final only (1e4, 1e5, 1e6); default (or all): all three
#   --tau T     one τ only (0.5 or 0.01); default: both
#   --out DIR   where the sweeps and the assembled table go (default: out/table2)
#   --energy-check salient|paper|both
#               salient: orbits whose |ΔH/H| exceeds 1e-2 stop as `energy-drift` (the default);
#               paper: no such stop, drifting orbits are classified as the paper's were; both
#   --cells N   an N×N grid instead of 400×400 (a quick look, or a test)
#   --bin PATH  the salient binary (default: $SALIENT_BIN, else target/release/salient built now)
#
# Writes DIR/CHECK/tau<τ>-t<t_final>[-METHOD]/ (the `salient run` output of each sweep) and
# DIR/table2.md (every finished sweep's table of the selection, cheapest first), and prints it.
# Hours on 2 cores for the whole table (docs/performance.md).
set -euo pipefail
cd "$(dirname "$0")/.."

out=out/table2
checks=salient
cells=400
bin=${SALIENT_BIN:-}
method=""
t_only=""
tau_only=""
usage() { sed -n '2,23p' "$0" | sed 's/^# \{0,1\}//' >&2; exit "$1"; }
while [ $# -gt 0 ]; do
  case $1 in
    --out) out=${2:?--out needs a folder}; shift 2 ;;
    --energy-check)
      case ${2:-} in
        salient|paper) checks=$2 ;;
        both) checks="salient paper" ;;
        *) echo "--energy-check must be salient, paper or both (got '${2:-}')" >&2; exit 2 ;;
      esac
      shift 2 ;;
    --cells)
      cells=${2:-}
      if ! [[ $cells =~ ^[0-9]+$ ]] || [ "$cells" -lt 2 ] || [ "$cells" -gt 4000 ]; then
        echo "--cells must be a whole number in 2..4000 (got '$cells')" >&2; exit 2
      fi
      shift 2 ;;
    --bin) bin=${2:?--bin needs a path}; shift 2 ;;
    --tau)
      case ${2:-} in
        0.5|0.01) tau_only=$2 ;;
        *) echo "--tau must be 0.5 or 0.01 (got '${2:-}')" >&2; exit 2 ;;
      esac
      shift 2 ;;
    -h|--help) usage 0 ;;
    -*) echo "unknown option $1" >&2; usage 2 ;;
    *)
      if [ -z "$method" ]; then method=$1
      elif [ -z "$t_only" ]; then t_only=$1
      else echo "unexpected argument $1" >&2; usage 2
      fi
      shift ;;
  esac
done
[ "$method" = all ] && method=""
[ "$t_only" = all ] && t_only=""
case ${method:-all} in
  all|tm-sbab2c|dop853|taylor|taylor-dd) ;;
  *) echo "METHOD must be tm-sbab2c, dop853, taylor or taylor-dd (got '$method')" >&2; exit 2 ;;
esac
case ${t_only:-all} in
  all|1e4|1e5|1e6) ;;
  *) echo "T_FINAL must be 1e4, 1e5 or 1e6 (got '$t_only')" >&2; exit 2 ;;
esac

if [ -z "$bin" ]; then
  cargo build --release -q -p salient-cli
  bin=target/release/salient
fi
tile=$(( cells < 20 ? cells : 20 ))
# A sweep's folder names its method when the rows are one method's.
suffix=${method:+-$method}

# One sweep's spec: examples/table2.toml reduced to one τ and t_final (and one method if asked),
# with the grid size and energy check asked for.
spec_of() {
  local tau=$1 t=$2 check=$3 methods='["tm-sbab2c", "dop853", "taylor", "taylor-dd"]'
  [ -n "$method" ] && methods="[\"$method\"]"
  sed -e "s/^method = .*/method = $methods/" -e "s/^tau = .*/tau = [$tau]/" \
      -e "s/^t_final = .*/t_final = [$t]/" -e "s/^cells = .*/cells = [$cells, $cells]/" \
      -e "s/^tile = .*/tile = [$tile, $tile]/" examples/table2.toml
  if [ "$check" = paper ]; then
    printf '\n[classify]\nenergy_drift = 1e300      # the paper'"'"'s conditions: no energy check\n'
  fi
}

mkdir -p "$out"
spec=$(mktemp --suffix=.toml)
trap 'rm -f "$spec"' EXIT
for check in $checks; do
  for t in 1e4 1e5 1e6; do
    [ -n "$t_only" ] && [ "$t" != "$t_only" ] && continue
    for tau in 0.5 0.01; do
      [ -n "$tau_only" ] && [ "$tau" != "$tau_only" ] && continue
      dir=$out/$check/tau$tau-t$t$suffix
      if [ -f "$dir/table.json" ]; then
        echo "finished already: $dir" >&2
        continue
      fi
      # A sweep stopped part way goes on from its checkpoint.
      resume=()
      if [ -d "$dir/.salient-checkpoint" ]; then
        resume=(--resume)
        echo "resuming: $dir" >&2
      else
        echo "running: $dir" >&2
      fi
      spec_of "$tau" "$t" "$check" > "$spec"
      "$bin" run "$spec" --out "$dir" "${resume[@]}"
    done
  done
done

# Every finished sweep's table under a heading that names it (the columns differ: a sweep with
# energy-drift cells has a column for them).
table=$out/table2.md
for check in salient paper; do
  for t in 1e4 1e5 1e6; do
    for tau in 0.5 0.01; do
      dir=$out/$check/tau$tau-t$t$suffix
      [ -f "$dir/table.json" ] || continue
      label=$([ "$check" = paper ] && echo "off (the paper's conditions)" || echo "1e-2")
      printf '### τ = %s, t_final = %s, energy check %s\n\n' "$tau" "$t" "$label"
      cat "$dir/table.md"
      echo
    done
  done
done > "$table"
cat "$table"
