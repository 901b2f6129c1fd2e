#!/usr/bin/env bash
# Start a Salient cluster on this host: one coordinator on a free loopback port and N workers,
# each logging to its own file in the run folder. Ctrl-C stops the workers first (SIGTERM: each
# finishes or releases its leases), then the coordinator; a second Ctrl-C kills them at once.
#
#   scripts/local-cluster.sh N [--release] [--fresh] [--submit SPEC]
#
#   N              number of workers (1 or more)
#   --release      (re)build the release binary before starting; without it the binary is
#                  built only when it is missing
#   --fresh        delete the run folder's database first; without it the coordinator reopens
#                  it and resumes the jobs left unfinished there
#   --submit SPEC  once the cluster answers, submit SPEC, wait for its results, write them to
#                  RUN_DIR/results/JOB/, then stop the cluster (exit status: that of `results`)
#
# Environment:
#   SALIENT_BIN            binary to use (default: target/release/salient, built if missing)
#   SALIENT_PORT           loopback port of the coordinator (default: a free one)
#   SALIENT_CLUSTER_DIR    run folder (default: local-cluster/ under the repository root)
#   SALIENT_THREADS        threads per worker (default: cores / N, at least 1)
#   SALIENT_TOKEN          shared token, passed to every process (default: none)
#   SALIENT_START_TIMEOUT  seconds to wait for the coordinator to answer (default: 30)
#   SALIENT_STOP_TIMEOUT   seconds to wait for the workers to drain before SIGKILL (default: 300)
#   SALIENT_COORDINATOR_ARGS  extra flags for the coordinator (e.g. --lease-cells-per-thread 4)
#   SALIENT_WORKER_ARGS    extra flags for every worker (e.g. --leases 1)
#   RUST_LOG               log filter for every process
#
# Run folder: salient.db (the coordinator's store), coordinator.log, worker-1.log ...,
# results/JOB/ (with --submit).
set -euo pipefail

usage() { sed -n '2,/^set -euo pipefail/p' "$0" | sed '$d; s/^# \{0,1\}//'; }
die() { echo "local-cluster: error: $*" >&2; exit 1; }
say() { echo "local-cluster: $*" >&2; }
bad_usage() { usage >&2; echo "local-cluster: error: $*" >&2; exit 2; }

workers="" rebuild=0 fresh=0 spec=""
while (($#)); do
  case $1 in
    --release) rebuild=1 ;;
    --fresh) fresh=1 ;;
    --submit) (($# >= 2)) || bad_usage "--submit needs a SPEC file"; spec=$2; shift ;;
    --submit=*) spec=${1#*=} ;;
    -h | --help) usage; exit 0 ;;
    -*) bad_usage "unknown option $1" ;;
    *) [[ -z $workers ]] || bad_usage "unexpected argument $1"; workers=$1 ;;
  esac
  shift
done
if [[ ! $workers =~ ^[1-9][0-9]*$ ]]; then bad_usage "give the number of workers N (1 or more)"; fi
if [[ -n $spec && ! -f $spec ]]; then die "spec $spec not found"; fi
start_timeout=${SALIENT_START_TIMEOUT:-30}
stop_timeout=${SALIENT_STOP_TIMEOUT:-300}

repo=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)

# --- the binary -------------------------------------------------------------------------------
if [[ -n ${SALIENT_BIN:-} ]]; then
  bin=$SALIENT_BIN
  [[ -x $bin ]] || die "SALIENT_BIN=$bin is not an executable file"
else
  target=${CARGO_TARGET_DIR:-target}
  [[ $target == /* ]] || target=$repo/$target
  bin=$target/release/salient
  if ((rebuild)) || [[ ! -x $bin ]]; then
    say "building $bin (cargo build --release -p salient-cli)"
    (cd "$repo" && cargo build --release -p salient-cli)
  fi
  [[ -x $bin ]] || die "$bin was not built"
fi

# --- the run folder ---------------------------------------------------------------------------
dir=${SALIENT_CLUSTER_DIR:-$repo/local-cluster}
mkdir -p "$dir"
dir=$(cd "$dir" && pwd)
# The default folder lies inside the repository: keep it out of git without touching .gitignore.
if [[ -z ${SALIENT_CLUSTER_DIR:-} && ! -e $dir/.gitignore ]]; then printf '*\n' >"$dir/.gitignore"; fi
if [[ -f $dir/coordinator.pid ]]; then
  old=$(<"$dir/coordinator.pid")
  if [[ $old =~ ^[0-9]+$ ]] && kill -0 "$old" 2>/dev/null; then
    die "a cluster already runs from $dir (coordinator pid $old); stop it or set SALIENT_CLUSTER_DIR"
  fi
fi
db=$dir/salient.db
if ((fresh)); then rm -f "$db" "$db-wal" "$db-shm"; fi

# --- a free loopback port ---------------------------------------------------------------------
port_in_use() { (exec 3<>"/dev/tcp/127.0.0.1/$1") 2>/dev/null; }
if [[ -n ${SALIENT_PORT:-} ]]; then
  port=$SALIENT_PORT
  [[ $port =~ ^[0-9]+$ ]] || die "SALIENT_PORT=$port is not a port number"
  if port_in_use "$port"; then die "port $port on 127.0.0.1 is already in use (SALIENT_PORT)"; fi
else
  port=""
  if command -v python3 >/dev/null 2>&1; then
    port=$(python3 -c 'import socket; s = socket.socket(); s.bind(("127.0.0.1", 0)); print(s.getsockname()[1])' 2>/dev/null || true)
  fi
  if [[ -z $port ]]; then
    for _ in $(seq 200); do
      p=$((20000 + RANDOM % 40000))
      if ! port_in_use "$p"; then port=$p; break; fi
    done
  fi
  [[ -n $port ]] || die "found no free port on 127.0.0.1; set SALIENT_PORT"
fi
export SALIENT_COORDINATOR=http://127.0.0.1:$port

# --- threads per worker -----------------------------------------------------------------------
if [[ -n ${SALIENT_THREADS:-} ]]; then
  threads=$SALIENT_THREADS
else
  cores=$(nproc 2>/dev/null || getconf _NPROCESSORS_ONLN 2>/dev/null || echo 1)
  threads=$((cores / workers))
  ((threads >= 1)) || threads=1
fi

# --- process management -----------------------------------------------------------------------
# Each process is detached from the terminal (setsid) so that a Ctrl-C in the terminal reaches only this
# script, which then stops the workers before the coordinator: workers that drain need it.
detach=()
if command -v setsid >/dev/null 2>&1; then detach=(setsid); fi
start() { # start LOG CMD...: run CMD in the background with stdout and stderr to LOG
  local log=$1
  shift
  ${detach[@]+"${detach[@]}"} "$@" >"$log" 2>&1 </dev/null &
}

coord_pid="" worker_pids=() force=0
alive() { local p; for p in "$@"; do if kill -0 "$p" 2>/dev/null; then echo "$p"; fi; done; }
stop() { # stop NAME TIMEOUT PID...: SIGTERM, wait up to TIMEOUT seconds, then SIGKILL
  local name=$1 timeout=$2 deadline p
  shift 2
  local pids=()
  mapfile -t pids < <(alive "$@")
  ((${#pids[@]})) || return 0
  say "stopping $name (SIGTERM)"
  kill -TERM "${pids[@]}" 2>/dev/null || true
  deadline=$((SECONDS + timeout))
  while mapfile -t pids < <(alive "${pids[@]}") && ((${#pids[@]})); do
    if ((force || SECONDS >= deadline)); then
      say "killing $name (SIGKILL): ${pids[*]}"
      kill -KILL "${pids[@]}" 2>/dev/null || true
      break
    fi
    sleep 0.2 || true
  done
  for p in "$@"; do wait "$p" 2>/dev/null || true; done
}
cleanup() {
  local rc=$?
  trap 'force=1' INT TERM HUP
  if ((${#worker_pids[@]})); then stop "the workers" "$stop_timeout" "${worker_pids[@]}"; fi
  if [[ -n $coord_pid ]]; then stop "the coordinator" 60 "$coord_pid"; fi
  rm -f "$dir/coordinator.pid"
  if [[ -n $coord_pid ]]; then say "stopped; logs in $dir"; fi
  exit "$rc"
}
trap cleanup EXIT
trap 'exit 130' INT
trap 'exit 143' TERM
trap 'exit 129' HUP

# --- start ------------------------------------------------------------------------------------
# Extra flags, word-split on purpose (e.g. SALIENT_COORDINATOR_ARGS="--lease-cells-per-thread 4").
read -r -a coordinator_args <<<"${SALIENT_COORDINATOR_ARGS:-}"
read -r -a worker_args <<<"${SALIENT_WORKER_ARGS:-}"
start "$dir/coordinator.log" "$bin" coordinator --listen "127.0.0.1:$port" --db "$db" \
  ${coordinator_args[@]+"${coordinator_args[@]}"}
coord_pid=$!
echo "$coord_pid" >"$dir/coordinator.pid"

deadline=$((SECONDS + start_timeout))
until "$bin" status >/dev/null 2>&1; do
  if ! kill -0 "$coord_pid" 2>/dev/null; then
    coord_pid=""
    echo "--- last lines of $dir/coordinator.log:" >&2
    tail -n 20 "$dir/coordinator.log" >&2 || true
    die "the coordinator exited before it answered"
  fi
  if ((SECONDS >= deadline)); then
    die "the coordinator did not answer on $SALIENT_COORDINATOR within ${start_timeout}s (SALIENT_START_TIMEOUT); see $dir/coordinator.log"
  fi
  sleep 0.2
done

for i in $(seq "$workers"); do
  start "$dir/worker-$i.log" "$bin" worker --coordinator "$SALIENT_COORDINATOR" \
    --threads "$threads" --name "local-$i" ${worker_args[@]+"${worker_args[@]}"}
  worker_pids+=("$!")
done

cat <<EOF
Salient cluster: coordinator on $SALIENT_COORDINATOR, $workers worker(s) x $threads thread(s)
Run folder: $dir (salient.db, coordinator.log, worker-N.log)

  export SALIENT_COORDINATOR=$SALIENT_COORDINATOR

  $bin submit examples/quick.toml --wait
  $bin status
  $bin watch JOB
  $bin results JOB --out out/JOB

EOF

# --- --submit: one job, then stop -------------------------------------------------------------
# The job id is read from `salient submit --json`: its "job_id" (or "job", or "id") field.
job_id_from_json() {
  local key id
  for key in job_id job id; do
    id=$(printf '%s' "$1" | tr -d '\n' \
      | grep -o "\"$key\"[[:space:]]*:[[:space:]]*\"\{0,1\}[A-Za-z0-9._:-]*" | head -n 1 \
      | sed 's/^[^:]*:[[:space:]]*"\{0,1\}//' || true)
    if [[ -n $id ]]; then printf '%s\n' "$id"; return 0; fi
  done
  return 1
}
if [[ -n $spec ]]; then
  submitted=$("$bin" submit "$spec" --json) || die "salient submit $spec failed"
  job=$(job_id_from_json "$submitted") || die "no job id in the output of salient submit --json: $submitted"
  say "submitted $spec as job $job (progress: $bin watch $job)"
  mkdir -p "$dir/results"
  rc=0
  "$bin" results "$job" --wait --out "$dir/results/$job" || rc=$?
  if ((rc == 0)); then say "results of job $job in $dir/results/$job"; fi
  exit "$rc"
fi

# --- otherwise: run until Ctrl-C --------------------------------------------------------------
echo "Ctrl-C stops the workers (they drain), then the coordinator."
reported=()
while :; do
  if ! kill -0 "$coord_pid" 2>/dev/null; then
    wait "$coord_pid" && rc=0 || rc=$?
    coord_pid=""
    echo "--- last lines of $dir/coordinator.log:" >&2
    tail -n 20 "$dir/coordinator.log" >&2 || true
    die "the coordinator exited (status $rc)"
  fi
  for i in "${!worker_pids[@]}"; do
    if [[ -z ${reported[i]:-} ]] && ! kill -0 "${worker_pids[i]}" 2>/dev/null; then
      reported[i]=1
      say "worker $((i + 1)) exited; see $dir/worker-$((i + 1)).log"
    fi
  done
  sleep 1
done
