#!/usr/bin/env bash
# Soak test of the distributed mode on this host. A coordinator and 2 to N workers on loopback
# take many small random jobs while workers join, drain (SIGTERM), are SIGKILLed and
# SIGSTOPped, and the coordinator is SIGKILLed (then restarted on the same store, where it
# resumes the unfinished jobs) or SIGSTOPped. Then every job must finish within a deadline and
# its results must equal those of `salient run` on the same spec.
#
#   scripts/soak.sh [--seed N] [--jobs N] [--chaos-events N] [--bin PATH] [--keep] ...
#
#   --seed N           seed of the specs, the pauses and the chaos actions (default: a random
#                      one); printed first: the same seed replays the same sequence
#   --jobs N           jobs to submit (default: 40)
#   --chaos-events N   worker joins, leaves, kills and stops, coordinator kills and stops
#                      (default: twice the jobs)
#   --lease-seconds S  the coordinator's --lease-seconds, whole seconds (default: 2): how soon
#                      the tiles of a killed or stopped worker go to the others
#   --max-workers N    most workers at once, 2 or more (default: 6)
#   --deadline S       seconds every job has to finish once the chaos has ended (default: 300)
#   --bin PATH         the salient binary (default: $SALIENT_BIN, else target/release/salient,
#                      built with cargo if missing)
#   --keep             keep the work folder (specs, store, logs, outputs) after a success; it is
#                      always kept after a failure
#
# The order of the actions follows from the seed (a private generator, so replays agree across
# bash versions); when they land relative to the processes' progress does not, so a replay
# meets the same specs and the same actions at similar moments.
#
# Outputs compare byte for byte, file set included, except run.json, table.json, table.csv and
# table.md: they are compared without what measures the run rather than its result (CPU and
# wall seconds, dropped orbits and steps, out_dir, forecast_from).
#
# Exit status: 0 when every job finished with equal outputs and every process behaved; 1 on a
# failure, each named with its job, spec and the command that replays the run; 2 on bad usage.
set -euo pipefail

usage() { sed -n '2,/^set -euo pipefail/p' "$0" | sed '$d; s/^# \{0,1\}//'; }
die() { echo "soak: error: $*" >&2; exit 1; }
say() { echo "soak: $*"; }
bad_usage() { usage >&2; echo "soak: error: $*" >&2; exit 2; }

seed="" jobs=40 events="" lease=2 max_workers=6 deadline=300 bin=${SALIENT_BIN:-} keep=0
whole() { # whole FLAG VALUE: VALUE is a whole number
  [[ $2 =~ ^[0-9]{1,9}$ ]] || bad_usage "$1 needs a whole number below 10^9 (got '$2')"
}
while (($#)); do
  case $1 in
    --keep) keep=1; shift; continue ;;
    -h | --help) usage; exit 0 ;;
    --*=*) opt=${1%%=*} val=${1#*=}; shift ;;
    --*) (($# >= 2)) || bad_usage "$1 needs a value"; opt=$1 val=$2; shift 2 ;;
    *) bad_usage "unexpected argument $1" ;;
  esac
  case $opt in
    --seed) whole "$opt" "$val"; seed=$val ;;
    --jobs) whole "$opt" "$val"; jobs=$val ;;
    --chaos-events) whole "$opt" "$val"; events=$val ;;
    --lease-seconds) whole "$opt" "$val"; lease=$val ;;
    --max-workers) whole "$opt" "$val"; max_workers=$val ;;
    --deadline) whole "$opt" "$val"; deadline=$val ;;
    --bin) bin=$val ;;
    *) bad_usage "unknown option $opt" ;;
  esac
done
# Leading zeros would read as octal in arithmetic.
for v in seed jobs events lease max_workers deadline; do
  if [[ -n ${!v} ]]; then printf -v "$v" '%d' "$((10#${!v}))"; fi
done
((jobs >= 1)) || bad_usage "--jobs must be 1 or more"
((lease >= 1)) || bad_usage "--lease-seconds must be 1 or more"
((max_workers >= 2)) || bad_usage "--max-workers must be 2 or more"
((deadline >= 1)) || bad_usage "--deadline must be 1 or more"
if [[ -z $events ]]; then events=$((2 * jobs)); fi
if [[ -z $seed ]]; then seed=$(((RANDOM << 15 | RANDOM) % 1000000)); fi

repo=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
replay="scripts/soak.sh --seed $seed --jobs $jobs --chaos-events $events --lease-seconds $lease --max-workers $max_workers"
# First, so that a run cut short can still be replayed.
say "seed $seed (replay: $replay)"

# --- the binary -------------------------------------------------------------------------------
if [[ -z $bin ]]; then
  target=${CARGO_TARGET_DIR:-target}
  [[ $target == /* ]] || target=$repo/$target
  bin=$target/release/salient
  if [[ ! -x $bin ]]; then
    say "building $bin (cargo build --release -p salient-cli)"
    (cd "$repo" && cargo build --release -p salient-cli)
  fi
fi
if [[ $bin != */* ]]; then bin=$(command -v "$bin" || echo "$bin"); fi
[[ -x $bin ]] || die "$bin is not an executable file"
bin=$(cd "$(dirname "$bin")" && pwd)/$(basename "$bin")
command -v timeout >/dev/null 2>&1 || die "needs timeout(1) (GNU coreutils)"

# --- the seeded sequence ----------------------------------------------------------------------
# A 31-bit linear congruential generator. Every draw happens in this shell (never in a $(...)
# subshell, whose draws would be lost) and none depends on timing, so the sequence of specs and
# actions is a function of the seed alone.
rng=$seed
rand() { # rand N: R = the next number in 0..N-1 (N at most 32768)
  rng=$(((rng * 1103515245 + 12345) & 0x7fffffff))
  R=$(((rng >> 16) % $1))
}
pick() { # pick WORD...: P = one of the words
  rand $#
  shift "$R"
  P=$1
}
for _ in 1 2 3; do rand 2; done

# --- the work folder and the processes ----------------------------------------------------------
work="" db="" tag=""
coord_pid="" coord_state=down url="" listen=127.0.0.1:0 coord_starts=0
wpid=() wstate=() wresume=() wname=() nworkers=0
failures=()

# A worker silent this long is taken for dead, its leases going to others, where the
# coordinator has that setting; otherwise the lease alone decides.
coordinator_args=()
if "$bin" coordinator --help 2>/dev/null | grep -q -- '--worker-timeout-seconds'; then
  coordinator_args=(--worker-timeout-seconds "$lease")
fi

fail() {
  failures+=("$*")
  echo "soak: FAILURE: $*" >&2
}

# Whether PID is still the process of ours whose arguments include WORD: never signal a pid
# that was reused by another process after ours exited (a zombie has no arguments).
is_ours() { # is_ours PID WORD
  [[ -n $1 ]] || return 1
  if [[ ! -d /proc/self ]]; then kill -0 "$1" 2>/dev/null; return; fi
  local args
  args=$(tr '\0' '\n' 2>/dev/null <"/proc/$1/cmdline") || return 1
  grep -qxF -- "$2" <<<"$args"
}
# Between fork and exec a child still shows this script's arguments: wait (bounded) until it
# shows its own, so that is_ours never takes a starting process for one that exited.
await_exec() { # await_exec PID WORD
  local i
  for ((i = 0; i < 500; i++)); do
    if is_ours "$1" "$2" || ! kill -0 "$1" 2>/dev/null; then return 0; fi
    sleep 0.01
  done
}
signal() { # signal SIG PID WORD
  if is_ours "$2" "$3"; then kill -s "$1" "$2" 2>/dev/null || true; fi
}
reap() { # reap PID: its exit status in W (bash keeps it for children already gone)
  W=0
  wait "$1" 2>/dev/null || W=$?
}

cleanup() {
  local rc=$? n
  trap '' INT TERM HUP
  # Stopped processes cannot die until they are continued. (bash's "Killed" notices muted.)
  {
    for n in "${!wpid[@]}"; do signal CONT "${wpid[n]}" "${wname[n]}"; done
    signal CONT "$coord_pid" "$db"
    for n in "${!wpid[@]}"; do signal KILL "${wpid[n]}" "${wname[n]}"; done
    signal KILL "$coord_pid" "$db"
    for n in "${!wpid[@]}"; do reap "${wpid[n]}"; done
    if [[ -n $coord_pid ]]; then reap "$coord_pid"; fi
  } 2>/dev/null
  if [[ -z $work ]]; then
    :
  elif ((rc != 0 || keep)); then
    say "work folder kept: $work"
  else
    rm -rf "$work"
  fi
  exit "$rc"
}
trap cleanup EXIT
trap 'exit 130' INT
trap 'exit 143' TERM
trap 'exit 129' HUP

work=$(mktemp -d "${TMPDIR:-/tmp}/salient-soak.XXXXXX")
db=$work/salient.db tag=${work##*.}
mkdir -p "$work/specs" "$work/dist" "$work/emb"
export SALIENT_TOKEN=soak-$tag
export RUST_LOG=${RUST_LOG:-info}
unset SALIENT_COORDINATOR

now_ms() { # T = milliseconds since the epoch
  local t=${EPOCHREALTIME:-}
  if [[ -n $t ]]; then T=$((10#${t//[.,]/} / 1000)); else T=$(date +%s%3N); fi
}
sleep_ms() { sleep "$(($1 / 1000)).$(printf '%03d' $(($1 % 1000)))"; }
client() { # client SECONDS ARGS...: a client command bounded in time
  local limit=$1
  shift
  timeout -k 5 "$limit" "$bin" "$@" --coordinator "$url"
}
tail_log() { echo "--- last lines of $1:" >&2; tail -n "${2:-20}" "$1" >&2 || true; }

start_coordinator() {
  local log addr_file=$work/coordinator.addr limit line tries=0
  # The first start takes a free port; restarts reuse it, since the workers know that address.
  # While it was free, a connect() elsewhere may have taken it as its local port (a worker
  # retrying may even connect to itself): then the restart finds it in use, and tries again.
  while :; do
    coord_starts=$((coord_starts + 1)) tries=$((tries + 1))
    log=$work/coordinator-$coord_starts.log
    rm -f "$addr_file"
    "$bin" coordinator --listen "$listen" --db "$db" --lease-seconds "$lease" \
      ${coordinator_args[@]+"${coordinator_args[@]}"} --address-file "$addr_file" >"$log" 2>&1 </dev/null &
    coord_pid=$! coord_state=up
    await_exec "$coord_pid" "$db"
    limit=$((SECONDS + 30))
    # `read` succeeds only on a whole line: the file is written at once, ending in a newline.
    until IFS= read -r line 2>/dev/null <"$addr_file" && [[ $line == *:* ]]; do
      if ! is_ours "$coord_pid" "$db"; then break; fi
      ((SECONDS < limit)) || { tail_log "$log"; die "the coordinator did not listen within 30 s"; }
      sleep 0.05
    done
    if is_ours "$coord_pid" "$db"; then break; fi
    reap "$coord_pid"
    coord_state=down
    if ((tries < 10)) && grep -q 'in use' "$log"; then
      say "step $step: port ${listen##*:} is in use; starting the coordinator again"
      sleep 0.5
      continue
    fi
    tail_log "$log"
    die "the coordinator exited before it listened (status $W; seed $seed; replay: $replay)"
  done
  listen=$line url=http://$line
  until client 5 status >/dev/null 2>&1; do
    if ! is_ours "$coord_pid" "$db"; then tail_log "$log"; die "the coordinator exited before it answered (seed $seed; replay: $replay)"; fi
    ((SECONDS < limit)) || { tail_log "$log"; die "the coordinator did not answer on $url within 30 s"; }
    sleep 0.1
  done
}

worker_joins=0 worker_leaves=0 worker_kills=0 worker_stops=0 coord_kills=0 coord_stops=0
start_worker() {
  nworkers=$((nworkers + 1))
  local n=$nworkers threads leases
  rand 2; threads=$((1 + R))
  rand 3; leases=$((1 + R))
  wname[n]=soak-$tag-w$n
  "$bin" worker --coordinator "$url" --threads "$threads" --leases "$leases" \
    --name "${wname[n]}" >"$work/worker-$n.log" 2>&1 </dev/null &
  wpid[n]=$! wstate[n]=run
  await_exec "${wpid[n]}" "${wname[n]}"
  worker_joins=$((worker_joins + 1))
  say "step $step: worker $n joins (threads $threads, leases $leases)"
}

# Workers by state, in number order (so that draws over them are reproducible).
running=() live=()
census() {
  running=() live=()
  local n
  for n in "${!wstate[@]}"; do
    case ${wstate[n]} in
      run) running+=("$n"); live+=("$n") ;;
      stopped) live+=("$n") ;;
    esac
  done
}

# A process of ours that exits without being told to is a failure.
check_processes() {
  local n
  if [[ $coord_state != down ]] && ! is_ours "$coord_pid" "$db"; then
    reap "$coord_pid"
    tail_log "$work/coordinator-$coord_starts.log" 40
    die "the coordinator exited by itself (status $W) at step $step (seed $seed; replay: $replay)"
  fi
  for n in "${!wstate[@]}"; do
    if [[ ${wstate[n]} == run || ${wstate[n]} == stopped ]] && ! is_ours "${wpid[n]}" "${wname[n]}"; then
      reap "${wpid[n]}"
      wstate[n]=dead
      tail_log "$work/worker-$n.log"
      fail "worker $n exited by itself (status $W) by step $step; log: $work/worker-$n.log"
    fi
  done
}

resume_due() { # continue the workers whose stop has lasted its steps
  local n
  for n in "${!wstate[@]}"; do
    if [[ ${wstate[n]} == stopped ]] && ((wresume[n] <= step)); then
      signal CONT "${wpid[n]}" "${wname[n]}"
      wstate[n]=run
      say "step $step: worker $n continues"
    fi
  done
}

# --- random specs -----------------------------------------------------------------------------
declare -A spec_of=() submit_at=() done_at=() state_of=()
job_ids=()
write_spec() { # write_spec K FILE: the K-th job's spec, drawn from the sequence
  local k=$1 file=$2 nq np tq tp mode energy m1 m2 methods t1 t2 taus f1 f2 tfinals delta=""
  local adaptive=0 extra=""
  rand 33; nq=$((8 + R))
  rand 33; np=$((8 + R))
  # Tiles from a sixth of the axis to all of it: a few to a few dozen tiles per run.
  rand $((nq - (nq + 5) / 6 + 1)); tq=$(((nq + 5) / 6 + R))
  rand $((np - (np + 5) / 6 + 1)); tp=$(((np + 5) / 6 + R))
  rand 10; if ((R < 6)); then mode=fast-pss; else mode=full; fi
  pick 0.08 0.1 0.11 0.125 0.14 0.155; energy=$P
  pick tm-sbab2c tm-saba2c tm-aba864 tm-srkn14a tm-sbab1 dop853; m1=$P
  rand 3
  if ((R == 0)); then
    pick tm-sbab2c tm-aba864 tm-srkn14a dop853 taylor; m2=$P
    if [[ $m2 == "$m1" ]]; then m2=""; fi
  else
    m2=""
  fi
  methods="\"$m1\"${m2:+, \"$m2\"}"
  if [[ $m1 == dop853 || $m2 == dop853 || $m2 == taylor ]]; then adaptive=1; fi
  # Full mode integrates an orbit from every cell; fast PSS labels many cells with each orbit,
  # so it affords longer runs.
  if [[ $mode == full ]]; then
    pick 0.1 0.2 0.5; t1=$P
    pick 200 400 800; f1=$P
  else
    pick 0.05 0.1 0.2 0.5; t1=$P
    pick 500 1000 2000 5000; f1=$P
  fi
  taus=$t1 tfinals=$f1
  rand 3
  if ((R == 0)); then
    pick 0.1 0.25 0.5; t2=$P
    if [[ $t2 != "$t1" ]]; then taus="$t1, $t2"; fi
  elif ((R == 1)); then
    pick 100 300 600; f2=$P
    if [[ $f2 != "$f1" ]]; then tfinals="$f1, $f2"; fi
  fi
  if ((adaptive)) && [[ $mode == full ]]; then
    pick "1e-6" "1e-8"; delta="delta = [$P]"
  elif ((adaptive)); then
    pick "1e-6" "1e-8" "1e-6, 1e-9"; delta="delta = [$P]"
  fi
  rand 5
  if ((R == 0)); then
    extra=$'\n[integration]\nprotocol = "free"\ndeviation = "random"\nseed = '"$k"
  elif ((R == 1)); then
    extra=$'\n[classify]\nearly_stop = false'
  fi
  cat >"$file" <<EOF
# soak seed $seed, job $k
name = "soak-$k"
[system]
kind = "henon-heiles"
energy = $energy
[grid]
cells = [$nq, $np]
tile = [$tq, $tp]
mode = "$mode"
[sweep]
method = [$methods]
tau = [$taus]
t_final = [$tfinals]
$delta$extra
EOF
}

submit_next() {
  submitted=$((submitted + 1))
  local k=$submitted spec=$work/specs/job-$submitted.toml out
  write_spec "$k" "$spec"
  out=$(client 60 submit "$spec" 2>"$work/specs/job-$k.submit.log") || {
    cat "$work/specs/job-$k.submit.log" >&2
    die "salient submit $spec failed at step $step (seed $seed; replay: $replay)"
  }
  [[ $out =~ ^[0-9]+$ ]] || die "salient submit $spec printed no job id: $out"
  now_ms
  job_ids+=("$out")
  spec_of[$out]=$spec submit_at[$out]=$T state_of[$out]=queued
  say "step $step: submitted job $out: $(sed -n 's/^\(cells\|mode\|method\|tau\|t_final\|delta\) = /\1 /p' "$spec" | tr '\n' ' ')"
}

# The named columns of `salient status`'s table, found by their headers.
status_rows() { # status_rows COLUMN...
  awk -F'|' -v want="$*" '
    function trim(s) { gsub(/^ +| +$/, "", s); return s }
    NR == 1 { for (i = 2; i < NF; i++) col[trim($i)] = i; n = split(want, w, " "); next }
    NR == 2 || NF < 3 { next }
    { line = ""; for (k = 1; k <= n; k++) line = line (k > 1 ? " " : "") trim($(col[w[k]])); print line }'
}

# Records the moment each job is first seen done; a failed or cancelled job is a failure.
poll_status() {
  local out id state
  out=$(client 10 status 2>/dev/null) || return 0
  now_ms
  while read -r id state; do
    [[ $id =~ ^[0-9]+$ && -n ${spec_of[$id]:-} ]] || continue
    if [[ $state == "done" && -z ${done_at[$id]:-} ]]; then done_at[$id]=$T; fi
    if [[ $state != "${state_of[$id]}" && ($state == failed || $state == cancelled) ]]; then
      fail "job $id ended $state (spec ${spec_of[$id]})"
    fi
    state_of[$id]=$state
  done < <(status_rows job state <<<"$out")
}

# --- chaos ------------------------------------------------------------------------------------
chaos() {
  census
  local kind n ms
  rand 100
  if ((R < 16)); then kind="join"
  elif ((R < 28)); then kind=leave
  elif ((R < 50)); then kind=wkill
  elif ((R < 70)); then kind=wstop
  elif ((R < 85)); then kind=ckill
  else kind=cstop
  fi
  # Worker actions need a running worker to act on and joins need room; otherwise the other.
  if [[ $kind == join ]] && ((${#live[@]} >= max_workers)); then kind=wkill; fi
  if [[ $kind == leave || $kind == wkill || $kind == wstop ]] && ((${#running[@]} < 2)); then
    if ((${#live[@]} < max_workers)); then kind="join"; else kind=cstop; fi
  fi
  case $kind in
    join) start_worker ;;
    leave | wkill | wstop)
      pick "${running[@]}"; n=$P
      case $kind in
        leave)
          signal TERM "${wpid[n]}" "${wname[n]}"
          wstate[n]=leaving worker_leaves=$((worker_leaves + 1))
          say "step $step: worker $n leaves (SIGTERM)"
          ;;
        wkill)
          signal KILL "${wpid[n]}" "${wname[n]}"
          reap "${wpid[n]}"
          wstate[n]=dead worker_kills=$((worker_kills + 1))
          say "step $step: worker $n killed (SIGKILL)"
          ;;
        wstop)
          # Half short, half long: past the lease (its tiles go to others) and past three
          # leases (the coordinator forgets it), then it comes back with stale work.
          rand 2
          if ((R == 0)); then rand 3; else rand 22; R=$((R + 3)); fi
          wresume[n]=$((step + 1 + R))
          signal STOP "${wpid[n]}" "${wname[n]}"
          wstate[n]=stopped worker_stops=$((worker_stops + 1))
          say "step $step: worker $n stopped (SIGSTOP) until step ${wresume[n]}"
          ;;
      esac
      ;;
    ckill)
      rand 16; ms=$((R * 100))
      signal KILL "$coord_pid" "$db"
      reap "$coord_pid"
      coord_state=down coord_kills=$((coord_kills + 1))
      say "step $step: coordinator killed (SIGKILL); restart in ${ms} ms"
      sleep_ms "$ms"
      start_coordinator
      say "step $step: coordinator restarted on the same store"
      ;;
    cstop)
      rand 21; ms=$((200 + R * (lease * 2000 + 1000) / 20))
      signal STOP "$coord_pid" "$db"
      coord_state=stopped coord_stops=$((coord_stops + 1))
      say "step $step: coordinator stopped (SIGSTOP) for ${ms} ms"
      sleep_ms "$ms"
      signal CONT "$coord_pid" "$db"
      coord_state=up
      ;;
  esac
}

# --- the run ----------------------------------------------------------------------------------
say "work folder $work; binary $bin"
say "$jobs jobs, $events chaos events, lease ${lease} s, 2 to $max_workers workers"
start_wall=$SECONDS
step=0 submitted=0 events_done=0
start_coordinator
say "coordinator on $url"
start_worker
start_worker
while ((submitted < jobs || events_done < events)); do
  step=$((step + 1))
  resume_due
  check_processes
  left_jobs=$((jobs - submitted)) left_events=$((events - events_done))
  submit=0
  if ((left_events == 0)); then
    submit=1
  elif ((left_jobs > 0)); then
    rand $((left_jobs + left_events))
    if ((R < left_jobs)); then submit=1; fi
  fi
  if ((submit)); then
    # Sometimes a burst, so that jobs queue up behind one another.
    rand 3
    for ((burst = 0; burst <= R && submitted < jobs; burst++)); do submit_next; done
  else
    chaos
    events_done=$((events_done + 1))
  fi
  # At least two workers exist (running or stopped) at all times.
  census
  while ((${#live[@]} < 2)); do start_worker; census; done
  poll_status
  rand 10
  sleep_ms $((50 + R * 75))
done
chaos_end=$SECONDS

# --- every job finishes -----------------------------------------------------------------------
say "chaos over after $((chaos_end - start_wall)) s; continuing stopped workers, waiting up to $deadline s for the jobs"
step=$((step + 1))
for n in "${!wstate[@]}"; do
  if [[ ${wstate[n]} == stopped ]]; then wresume[n]=0; fi
done
resume_due
census
while ((${#running[@]} < 2)); do start_worker; census; done
limit=$((SECONDS + deadline))
while :; do
  check_processes
  poll_status
  pending=()
  for id in "${job_ids[@]}"; do
    if [[ -z ${done_at[$id]:-} && ${state_of[$id]} != failed && ${state_of[$id]} != cancelled ]]; then
      pending+=("$id")
    fi
  done
  ((${#pending[@]})) || break
  if ((SECONDS >= limit)); then
    for id in "${pending[@]}"; do
      fail "job $id is ${state_of[$id]} $deadline s after the chaos ended (spec ${spec_of[$id]}):"
      sed 's/^/    /' "${spec_of[$id]}" >&2
    done
    client 10 status >&2 || true
    break
  fi
  sleep 0.5
done
finish_wall=$SECONDS

# The coordinator knows exactly the jobs submitted (none lost, none doubled).
if known=$(client 10 status 2>/dev/null); then
  known=$(status_rows job <<<"$known" | sort -n | tr '\n' ' ')
  expected=$(printf '%s\n' "${job_ids[@]}" | sort -n | tr '\n' ' ')
  if [[ $known != "$expected" ]]; then fail "the coordinator lists jobs [$known], submitted were [$expected]"; fi
else
  fail "salient status failed after the chaos"
fi

# --- outputs equal those of salient run -------------------------------------------------------
# shellcheck source=scripts/compare-outputs.sh
source "$repo/scripts/compare-outputs.sh"

compared=0
for id in "${job_ids[@]}"; do
  [[ -n ${done_at[$id]:-} ]] || continue
  spec=${spec_of[$id]} dist=$work/dist/$id emb=$work/emb/$id
  if ! client 300 results "$id" --wait --out "$dist" >"$dist.log" 2>&1; then
    tail_log "$dist.log"
    fail "salient results $id failed (spec $spec)"
    continue
  fi
  if ! timeout -k 5 600 "$bin" run "$spec" --out "$emb" >"$emb.log" 2>&1; then
    tail_log "$emb.log"
    fail "salient run $spec failed (job $id)"
    continue
  fi
  if ! diffs=$(compare_outputs "$emb" "$dist" | sed 's/^/    /'); then
    fail "job $id: the results differ from salient run's (spec $spec):"
    echo "$diffs" >&2
    sed 's/^/    /' "$spec" >&2
  fi
  compared=$((compared + 1))
done
say "compared $compared job(s) with salient run"

# --- the workers drain and exit ---------------------------------------------------------------
# A worker handles SIGTERM once registered (before, the signal's default action ends it): wait
# for that, so that each is asked to drain.
census
limit=$((SECONDS + 60))
for n in "${running[@]}"; do
  until grep -q 'registered' "$work/worker-$n.log" 2>/dev/null || ((SECONDS >= limit)); do sleep 0.1; done
  signal TERM "${wpid[n]}" "${wname[n]}"
  wstate[n]=leaving
done
for n in "${!wstate[@]}"; do
  [[ ${wstate[n]} == leaving ]] || continue
  while is_ours "${wpid[n]}" "${wname[n]}" && ((SECONDS < limit)); do sleep 0.1; done
  if is_ours "${wpid[n]}" "${wname[n]}"; then
    tail_log "$work/worker-$n.log"
    fail "worker $n did not exit within 60 s of SIGTERM with the coordinator up"
  else
    reap "${wpid[n]}"
    if ((W != 0)); then fail "worker $n exited with status $W after SIGTERM; log: $work/worker-$n.log"; fi
  fi
  wstate[n]=gone
done

# No panic in any log.
if panics=$(grep -l 'panicked' "$work"/coordinator-*.log "$work"/worker-*.log 2>/dev/null); then
  fail "a process panicked; see: $(echo "$panics" | tr '\n' ' ')"
fi

# --- summary ----------------------------------------------------------------------------------
worst=0 worst_job=""
for id in "${job_ids[@]}"; do
  if [[ -n ${done_at[$id]:-} ]] && ((done_at[$id] - submit_at[$id] > worst)); then
    worst=$((done_at[$id] - submit_at[$id])) worst_job=$id
  fi
done
elapsed=$((finish_wall - start_wall))
((elapsed > 0)) || elapsed=1
done_jobs=0
for id in "${job_ids[@]}"; do if [[ -n ${done_at[$id]:-} ]]; then done_jobs=$((done_jobs + 1)); fi; done
rate=$(awk -v j="$done_jobs" -v s="$elapsed" 'BEGIN { printf "%.2f", j / s }')
worst_s=$(awk -v ms="$worst" 'BEGIN { printf "%.1f", ms / 1000 }')
say "summary: seed $seed, jobs $done_jobs/$submitted done, workers $worker_joins joined $worker_leaves left $worker_kills killed $worker_stops stopped, coordinator $coord_kills killed $coord_stops stopped, kills $((worker_kills + coord_kills)), stops $((worker_stops + coord_stops)), elapsed ${elapsed} s, ${rate} jobs/s, worst submit-to-done ${worst_s} s${worst_job:+ (job $worst_job)}"
if ((${#failures[@]})); then
  echo "soak: FAILED with ${#failures[@]} failure(s) (seed $seed; replay: $replay):" >&2
  printf '  - %s\n' "${failures[@]}" >&2
  exit 1
fi
say "PASS"
