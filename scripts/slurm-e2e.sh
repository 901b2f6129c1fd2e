#!/usr/bin/env bash
# End-to-end test of deploy/slurm/salient.sbatch on a real Slurm: a one-node cluster on this
# machine (munged, slurmctld and slurmd started here, in the background, with their state in a
# temporary folder; no systemd), then
#
#   1. the quick example through sbatch: coordinator and worker under Slurm; the results it
#      writes must equal those of `salient run` on the same spec (per-cell files byte for byte,
#      tables and run.json without the fields that measure the run);
#   2. a longer spec, stopped mid-run with `scancel --batch --signal=TERM` (what the time limit
#      does through `#SBATCH --signal=B:TERM@120`): the worker must drain (its log says
#      "draining" and "worker stopped", the coordinator's "worker left"), the job must end
#      within a bound, no salient process of it may be left, and the job's log must print the
#      command that resumes it;
#   3. that resume command, in a new allocation: the finished job must equal `salient run`;
#   4. the longer spec again, stopped mid-run with a plain `scancel`, which signals every
#      process of the job at once: the worker must start to drain, the batch script must end it,
#      copy the store and print the resume command before Slurm's SIGKILL, and no salient
#      process may be left.
#
# Then it stops the daemons it started and deletes the temporary folder (kept on a failure).
#
#   scripts/slurm-e2e.sh [--bin PATH] [--keep]
#
#   --bin PATH   the salient binary (default: $SALIENT_BIN, else target/release/salient); it is
#                not built here: `cargo build --release -p salient-cli` builds it
#   --keep       keep the temporary folder (Slurm's configuration and logs, the jobs' run
#                folders) after a success too
#
# Environment:
#   SALIENT_BIN         the binary (as --bin)
#   SLURM_E2E_TIMEOUT   seconds each Slurm job may take before the test fails (default: 300)
#   TMPDIR              where the temporary folder goes (default: /tmp)
#
# Runs as root: it installs the Debian packages slurm-wlm and munge with apt-get when sbatch,
# slurmctld, slurmd or munged is missing, and Slurm's daemons need root to start job steps.
# Slurm's cgroup plugins are left out (proctrack/linuxproc, task/none), so it also runs in a
# container without cgroup delegation.
#
# Exit status: 0 when every check passed, 1 when one failed, 2 on bad usage.
set -euo pipefail

usage() { sed -n '2,/^set -euo pipefail/p' "$0" | sed '$d; s/^# \{0,1\}//'; }
say() { echo "slurm-e2e: $*"; }
die() { echo "slurm-e2e: error: $*" >&2; exit 1; }
bad_usage() { usage >&2; echo "slurm-e2e: error: $*" >&2; exit 2; }

bin=${SALIENT_BIN:-} keep=0
while (($#)); do
  case $1 in
    --bin) (($# >= 2)) || bad_usage "--bin needs a PATH"; bin=$2; shift ;;
    --bin=*) bin=${1#*=} ;;
    --keep) keep=1 ;;
    -h | --help) usage; exit 0 ;;
    *) bad_usage "unexpected argument $1" ;;
  esac
  shift
done
timeout=${SLURM_E2E_TIMEOUT:-300}
[[ $timeout =~ ^[1-9][0-9]*$ ]] || bad_usage "SLURM_E2E_TIMEOUT=$timeout is not a whole number of seconds"

repo=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
sbatch_script=$repo/deploy/slurm/salient.sbatch
if [[ -z $bin ]]; then bin=$repo/target/release/salient; fi
[[ $bin == /* ]] || bin=$PWD/$bin
[[ -x $bin && -f $bin ]] || die "no salient binary at $bin: build it with \`cargo build --release -p salient-cli\`, or give --bin PATH"
[[ -f $sbatch_script ]] || die "$sbatch_script not found"
((EUID == 0)) || die "run as root: the test installs packages and starts Slurm's daemons"
started=$SECONDS

# --- Slurm and munge from Debian's packages ---------------------------------------------------
have_slurm() {
  local c
  for c in sbatch srun squeue scancel scontrol sinfo slurmctld slurmd munged munge; do
    command -v "$c" >/dev/null 2>&1 || return 1
  done
}
if ! have_slurm; then
  command -v apt-get >/dev/null 2>&1 || die "Slurm is not installed and there is no apt-get to install it (Debian's slurm-wlm and munge)"
  say "installing slurm-wlm and munge (apt-get)"
  # The packages' maintainer scripts would start munged and the Slurm daemons with the
  # system's configuration; policy-rc.d (Debian's switch for that) keeps them from starting
  # anything while the packages install.
  policy=/usr/sbin/policy-rc.d policy_made=0
  if [[ ! -e $policy ]]; then
    printf '#!/bin/sh\nexit 101\n' >"$policy" && chmod 0755 "$policy" && policy_made=1
  fi
  install_rc=0
  {
    apt-get update -q &&
      DEBIAN_FRONTEND=noninteractive apt-get install -y -q --no-install-recommends slurm-wlm munge
  } >"${TMPDIR:-/tmp}/slurm-e2e-apt.log" 2>&1 || install_rc=$?
  if ((policy_made)); then rm -f "$policy"; fi
  if ((install_rc)); then
    tail -n 20 "${TMPDIR:-/tmp}/slurm-e2e-apt.log" >&2
    die "apt-get failed (exit $install_rc); its log: ${TMPDIR:-/tmp}/slurm-e2e-apt.log"
  fi
  rm -f "${TMPDIR:-/tmp}/slurm-e2e-apt.log"
  have_slurm || die "slurm-wlm and munge installed, yet a Slurm or munge command is still missing"
  say "installed in $((SECONDS - started)) s"
fi

# --- the temporary folder and the cleanup -----------------------------------------------------
work=$(mktemp -d "${TMPDIR:-/tmp}/slurm-e2e.XXXXXX")
mkdir -p "$work"/{munge,state,spool,jobs,emb,tmp}
# munged refuses a socket that other users cannot reach (clients of any user connect to it);
# the key stays readable by root alone.
chmod 0755 "$work" "$work/munge"
# The batch script keeps its store in ${TMPDIR:-/tmp}/salient-JOBID; job ids restart at 1 in
# every test cluster, so keep those folders in the temporary folder too (sbatch passes it on).
export TMPDIR=$work/tmp

munged_pid="" slurmctld_pid="" slurmd_pid="" job_ids=() failures=0 passes=0
pass() { passes=$((passes + 1)); say "ok: $*"; }
fail() { failures=$((failures + 1)); say "FAIL: $*"; }

stop_pid() { # stop_pid NAME PID: SIGTERM, then SIGKILL after 15 s
  local name=$1 pid=$2 deadline
  [[ -n $pid ]] && kill -0 "$pid" 2>/dev/null || return 0
  kill -TERM "$pid" 2>/dev/null || true
  deadline=$((SECONDS + 15))
  while kill -0 "$pid" 2>/dev/null; do
    if ((SECONDS >= deadline)); then
      say "$name did not stop within 15 s: SIGKILL"
      kill -KILL "$pid" 2>/dev/null || true
      break
    fi
    sleep 0.2
  done
}

# The pids of the salient processes of Slurm job $1: its workers carry the name
# slurm-JOBID-HOST; its coordinator and client name the store or the run folder, salient-JOBID.
salient_pids_of() {
  local id=$1 pid cmd
  for pid in $(pgrep -x salient 2>/dev/null || true); do
    cmd=$(tr '\0' ' ' <"/proc/$pid/cmdline" 2>/dev/null || true)
    case $cmd in
      *"slurm-$id-"* | *"/salient-$id/"*) echo "$pid" ;;
    esac
  done
}

cleanup() {
  local rc=$? id pid
  trap '' INT TERM
  if [[ -n $slurmctld_pid ]] && kill -0 "$slurmctld_pid" 2>/dev/null; then
    for id in "${job_ids[@]}"; do scancel "$id" 2>/dev/null || true; done
    # slurmd leaves running job steps alone when it stops: let Slurm end them first.
    local deadline=$((SECONDS + 60))
    while ((SECONDS < deadline)) && [[ -n $(squeue --noheader 2>/dev/null) ]]; do sleep 0.5; done
  fi
  for id in "${job_ids[@]}"; do
    for pid in $(salient_pids_of "$id"); do kill -KILL "$pid" 2>/dev/null || true; done
  done
  stop_pid slurmd "$slurmd_pid"
  stop_pid slurmctld "$slurmctld_pid"
  stop_pid munged "$munged_pid"
  if ((rc == 0 && failures == 0 && !keep)); then
    rm -rf "$work"
  else
    say "kept $work (slurm.conf, *.log, jobs/salient-JOBID*)"
  fi
  exit "$rc"
}
trap cleanup EXIT
trap 'exit 130' INT
trap 'exit 143' TERM

# --- munge ------------------------------------------------------------------------------------
dd if=/dev/urandom of="$work/munge/munge.key" bs=1024 count=1 status=none
chmod 0400 "$work/munge/munge.key"
socket=$work/munge/munge.socket
munged --foreground --key-file="$work/munge/munge.key" --socket="$socket" \
  --pid-file="$work/munge/munged.pid" --log-file="$work/munged.log" \
  --seed-file="$work/munge/munged.seed" >>"$work/munged.log" 2>&1 &
munged_pid=$!
deadline=$((SECONDS + 20))
until munge --socket="$socket" -n 2>/dev/null | unmunge --socket="$socket" >/dev/null 2>&1; do
  kill -0 "$munged_pid" 2>/dev/null || { tail -n 20 "$work/munged.log" >&2; die "munged exited (see $work/munged.log)"; }
  ((SECONDS < deadline)) || die "munged did not answer within 20 s (see $work/munged.log)"
  sleep 0.2
done

# --- slurm.conf: this machine as the one node -------------------------------------------------
free_port() {
  python3 -c 'import socket; s = socket.socket(); s.bind(("127.0.0.1", 0)); print(s.getsockname()[1])' 2>/dev/null ||
    echo $((30000 + RANDOM % 20000))
}
node=$(hostname -s)
# `slurmd -C` prints this machine's node line (CPUs, sockets, cores, threads, RealMemory) as
# slurmd will see it; a node declared larger than it is would be drained at registration.
node_line=$(slurmd -C 2>/dev/null | grep -m1 '^NodeName=' || true)
if [[ -n $node_line ]]; then
  node_spec=${node_line#NodeName=* }
else
  node_spec="CPUs=$(nproc) RealMemory=$(($(awk '/^MemTotal:/ { print $2 }' /proc/meminfo) * 9 / 10240))"
fi
cpus=$(grep -o 'CPUs=[0-9]*' <<<"$node_spec" | cut -d= -f2)
[[ $cpus =~ ^[1-9][0-9]*$ ]] || die "could not read this machine's CPU count from: $node_spec"

export SLURM_CONF=$work/slurm.conf
cat >"$SLURM_CONF" <<EOF
ClusterName=salient-e2e
SlurmctldHost=$node(127.0.0.1)
SlurmctldPort=$(free_port)
SlurmdPort=$(free_port)
SlurmUser=root
SlurmdUser=root
AuthType=auth/munge
CredType=cred/munge
AuthInfo=socket=$socket
StateSaveLocation=$work/state
SlurmdSpoolDir=$work/spool
SlurmctldPidFile=$work/slurmctld.pid
SlurmdPidFile=$work/slurmd.pid
SlurmctldLogFile=$work/slurmctld.log
SlurmdLogFile=$work/slurmd.log
SlurmctldDebug=info
SlurmdDebug=info
# No cgroups: a container rarely has them delegated, and nothing here needs them.
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
JobAcctGatherType=jobacct_gather/none
AccountingStorageType=accounting_storage/none
JobCompType=jobcomp/none
MpiDefault=none
SwitchType=switch/none
SchedulerType=sched/backfill
SelectType=select/cons_tres
SelectTypeParameters=CR_CPU
ReturnToService=2
InactiveLimit=0
MinJobAge=600
# The SIGKILL of a plain scancel comes KillWait seconds after its SIGTERM (30 s by default):
# shorter, so that the test waits less, and still far longer than the batch script's cleanup.
KillWait=10
NodeName=$node NodeAddr=127.0.0.1 $node_spec State=UNKNOWN
PartitionName=e2e Nodes=$node Default=YES MaxTime=INFINITE State=UP
EOF

slurmctld -D -f "$SLURM_CONF" >>"$work/slurmctld.log" 2>&1 &
slurmctld_pid=$!
slurmd -D -f "$SLURM_CONF" >>"$work/slurmd.log" 2>&1 &
slurmd_pid=$!
deadline=$((SECONDS + 60))
until [[ $(sinfo --noheader --nodes="$node" --format=%T 2>/dev/null) == idle ]]; do
  kill -0 "$slurmctld_pid" 2>/dev/null || { tail -n 20 "$work/slurmctld.log" >&2; die "slurmctld exited (see $work/slurmctld.log)"; }
  kill -0 "$slurmd_pid" 2>/dev/null || { tail -n 20 "$work/slurmd.log" >&2; die "slurmd exited (see $work/slurmd.log)"; }
  if ((SECONDS >= deadline)); then
    sinfo --long --Node >&2 || true
    die "node $node is not idle within 60 s (see $work/slurmctld.log and $work/slurmd.log)"
  fi
  sleep 0.5
done
say "Slurm $(sinfo --version | awk '{ print $2 }') up: node $node, $cpus CPUs, partition e2e (set up in $((SECONDS - started)) s)"

# --- helpers ----------------------------------------------------------------------------------
# A known token, so that this script can ask the job's coordinator for progress from outside the
# allocation (sbatch passes the environment on).
export SALIENT_TOKEN
SALIENT_TOKEN=$(od -An -N16 -tx1 /dev/urandom | tr -d ' \n')
export SALIENT_BIN=$bin

# submit VAR SBATCH-ARGS...: submits from the jobs folder and sets VAR to the Slurm job id (not
# printed: a command substitution would lose the job_ids the cleanup cancels).
submit() {
  local var=$1 out
  shift
  out=$(cd "$work/jobs" && sbatch --parsable --nodes=1 --cpus-per-task="$cpus" --time=30 "$@") ||
    die "sbatch $* failed"
  job_ids+=("${out%%;*}")
  printf -v "$var" '%s' "${out%%;*}"
}
job_field() { # job_field ID FIELD: FIELD=value of `scontrol show job`
  scontrol show job "$1" 2>/dev/null | tr ' ' '\n' | sed -n "s/^$2=//p" | head -n 1
}
# Wait until Slurm job $1 has ended, at most $2 seconds; 1 on timeout.
wait_ended() {
  local deadline=$((SECONDS + $2)) state
  while :; do
    state=$(job_field "$1" JobState)
    case $state in
      PENDING | RUNNING | CONFIGURING | COMPLETING | SUSPENDED | "") ;;
      *) return 0 ;;
    esac
    ((SECONDS < deadline)) || return 1
    sleep 0.5
  done
}
show_job_logs() { # show_job_logs ID: the tail of each log of the job, on a failure
  local f
  for f in "$work/jobs/salient-$1.out" "$work/jobs/salient-$1"/*.log; do
    [[ -f $f ]] || continue
    echo "--- $f" >&2
    tail -n 15 "$f" >&2
  done
}

# Outputs of `salient run` and `salient results` compared (compare_outputs), and at least one
# cells.csv among them.
# shellcheck source=scripts/compare-outputs.sh
source "$repo/scripts/compare-outputs.sh"
compare() { # compare A B: prints the differences; 1 when there are any
  local bad=0
  compare_outputs "$1" "$2" || bad=1
  if [[ -z $(find "$1" -name cells.csv -print -quit) ]]; then echo "no cells.csv in $1"; bad=1; fi
  return "$bad"
}
check_same() { # check_same WHAT EMBEDDED DISTRIBUTED
  local diffs
  if diffs=$(compare "$2" "$3"); then
    pass "$1: salient results equals salient run ($(cd "$3" && find . -type f | wc -l) files; cells.csv, class.npy, sali.npy, map.png byte for byte)"
  else
    fail "$1: salient results differs from salient run:"
    while IFS= read -r line; do echo "    $line"; done <<<"$diffs"
  fi
}
first() { echo "$1"; } # the first match of a glob (the one node's worker log)
# 0 when file $2 holds the fixed string $3 (check named $1).
check_log() {
  if [[ -f $2 ]] && grep -qF -- "$3" "$2"; then pass "$1"; else fail "$1: no \"$3\" in $2"; fi
}

# --- 1. the quick example, to the end ---------------------------------------------------------
spec=$repo/examples/quick.toml
say "1. sbatch deploy/slurm/salient.sbatch examples/quick.toml"
t0=$SECONDS
submit id "$sbatch_script" "$spec"
if ! wait_ended "$id" "$timeout"; then
  fail "Slurm job $id (quick) did not end within $timeout s"
  show_job_logs "$id"
else
  state=$(job_field "$id" JobState) code=$(job_field "$id" ExitCode)
  if [[ $state == COMPLETED && $code == 0:0 ]]; then
    pass "Slurm job $id (quick) COMPLETED in $((SECONDS - t0)) s"
  else
    fail "Slurm job $id (quick) ended $state with exit code $code"
    show_job_logs "$id"
  fi
  run_dir=$work/jobs/salient-$id
  "$bin" run "$spec" --threads "$cpus" --out "$work/emb/quick" >"$work/emb/quick.log" 2>&1 ||
    die "salient run $spec failed (see $work/emb/quick.log)"
  if [[ -d $run_dir/results ]]; then
    check_same "quick" "$work/emb/quick" "$run_dir/results"
  else
    fail "quick: no results folder in $run_dir"
  fi
  check_log "quick: the worker registered" "$run_dir/coordinator.log" "worker registered"
  check_log "quick: the worker stopped after the job" "$(first "$run_dir"/worker-*.log)" "worker stopped"
  check_log "quick: the store was copied into the run folder" "$work/jobs/salient-$id.out" "store copied to"
fi

# --- 2. a longer spec, stopped mid-run the graceful way ---------------------------------------
# About 12 s of one worker with two threads: long enough to stop in the middle.
long=$work/long.toml
cat >"$long" <<'EOF'
name = "long"
[system]
kind = "henon-heiles"
energy = 0.125
[grid]
cells = [200, 200]
tile = [20, 20]
mode = "fast-pss"
[sweep]
method = ["tm-sbab2c"]
tau = [0.01]
t_final = [1e5]
EOF

# Submits the long spec and waits until it is mid-run: the coordinator reports cells resolved
# and the job is not done. Sets id (Slurm's job), job (salient's) and run_dir; 1 when the
# allocation never got there.
start_long() {
  local deadline=$((SECONDS + timeout)) st state resolved=""
  submit id "$sbatch_script" "$long"
  run_dir=$work/jobs/salient-$id job=""
  # The batch script's default port; the token is this script's (sbatch passes it on).
  export SALIENT_COORDINATOR=http://127.0.0.1:$((20000 + id % 20000))
  while :; do
    if [[ -f $run_dir/job ]]; then
      job=$(<"$run_dir/job")
      st=$("$bin" status "$job" --json 2>/dev/null || true)
      resolved=$(grep -o '"resolved"[[:space:]]*:[[:space:]]*[0-9]*' <<<"$st" | grep -o '[0-9]*$' | head -n 1 || true)
      if [[ -n $resolved ]] && ((resolved > 0)); then break; fi
    fi
    if wait_ended "$id" 0 || ((SECONDS >= deadline)); then break; fi
    sleep 0.5
  done
  state=$(job_field "$id" JobState)
  if [[ $state != RUNNING || -z $resolved || $resolved == 0 ]]; then
    fail "Slurm job $id (long) was not running with progress to stop (state $state, cells resolved ${resolved:-unknown})"
    show_job_logs "$id"
    return 1
  fi
  say "Slurm job $id: salient job $job has $resolved cells resolved"
}
check_gone() { # check_gone WHAT: no salient process of Slurm job $id is left
  local left
  left=$(salient_pids_of "$id" | tr '\n' ' ')
  if [[ -z $left ]]; then
    pass "$1: no salient process of Slurm job $id is left"
  else
    fail "$1: salient processes of Slurm job $id still run: $left"
  fi
}

say "2. sbatch ... long.toml, then scancel --batch --signal=TERM mid-run"
if start_long; then
  t0=$SECONDS
  say "scancel --batch --signal=TERM $id"
  scancel --batch --signal=TERM "$id"
  # The worker drains within the script's SALIENT_DRAIN_TIMEOUT (90 s); allow for the rest.
  if wait_ended "$id" 150; then
    pass "graceful stop: Slurm job $id ended $(job_field "$id" JobState) $((SECONDS - t0)) s after scancel"
  else
    fail "graceful stop: Slurm job $id still $(job_field "$id" JobState) 150 s after scancel"
  fi
  check_gone "graceful stop"
  worker_log=$(first "$run_dir"/worker-*.log)
  check_log "graceful stop: the worker drained" "$worker_log" "draining: finishing the lease in progress"
  check_log "graceful stop: the worker stopped" "$worker_log" "worker stopped"
  if grep -qF "drain deadline passed" "$worker_log" 2>/dev/null; then
    fail "graceful stop: the worker hit its drain deadline"
  fi
  check_log "graceful stop: the coordinator saw the worker leave" "$run_dir/coordinator.log" "worker left"
  check_log "graceful stop: the coordinator stopped cleanly" "$run_dir/coordinator.log" "coordinator stopped"
  check_log "graceful stop: the batch script got SIGTERM" "$work/jobs/salient-$id.out" "SIGTERM received"
  check_log "graceful stop: the batch script printed how to resume" "$work/jobs/salient-$id.out" \
    "SALIENT_JOB=$job sbatch deploy/slurm/salient.sbatch"

  # --- 3. resume it in a new allocation, as the log says --------------------------------------
  say "3. SALIENT_DB=.../salient-$id/salient.db SALIENT_JOB=$job sbatch deploy/slurm/salient.sbatch"
  t0=$SECONDS
  rid=""
  SALIENT_DB=$run_dir/salient.db SALIENT_JOB=$job submit rid "$sbatch_script"
  if ! wait_ended "$rid" "$timeout"; then
    fail "resume: Slurm job $rid did not end within $timeout s"
    show_job_logs "$rid"
  else
    state=$(job_field "$rid" JobState) code=$(job_field "$rid" ExitCode)
    if [[ $state == COMPLETED && $code == 0:0 ]]; then
      pass "resume: Slurm job $rid (salient job $job) COMPLETED in $((SECONDS - t0)) s"
    else
      fail "resume: Slurm job $rid ended $state with exit code $code"
      show_job_logs "$rid"
    fi
    check_log "resume: the coordinator resumed the unfinished job" "$work/jobs/salient-$rid.out" "resuming job $job"
    "$bin" run "$long" --threads "$cpus" --out "$work/emb/long" >"$work/emb/long.log" 2>&1 ||
      die "salient run $long failed (see $work/emb/long.log)"
    if [[ -d $work/jobs/salient-$rid/results ]]; then
      check_same "long, stopped and resumed" "$work/emb/long" "$work/jobs/salient-$rid/results"
    else
      fail "resume: no results folder in $work/jobs/salient-$rid"
    fi
  fi
fi

# --- 4. the long spec again, stopped mid-run by a plain scancel -------------------------------
# SIGTERM reaches every process of the job at once, the coordinator included, and SIGKILL
# follows after KillWait: the batch script must end the workers, copy the store and print the
# resume command before that.
say "4. sbatch ... long.toml, then a plain scancel mid-run"
if start_long; then
  t0=$SECONDS
  say "scancel $id"
  scancel "$id"
  if wait_ended "$id" 60; then
    pass "plain scancel: Slurm job $id ended $(job_field "$id" JobState) $((SECONDS - t0)) s after scancel"
  else
    fail "plain scancel: Slurm job $id still $(job_field "$id" JobState) 60 s after scancel"
  fi
  check_gone "plain scancel"
  out=$work/jobs/salient-$id.out
  check_log "plain scancel: the worker began to drain" "$(first "$run_dir"/worker-*.log)" "draining: finishing the lease in progress"
  check_log "plain scancel: the coordinator stopped cleanly" "$run_dir/coordinator.log" "coordinator stopped"
  check_log "plain scancel: the batch script saw the coordinator gone and ended the workers" "$out" "the coordinator has stopped"
  check_log "plain scancel: the store was copied before SIGKILL" "$out" "store copied to"
  check_log "plain scancel: the batch script printed how to resume" "$out" "SALIENT_JOB=$job sbatch deploy/slurm/salient.sbatch"
fi

# --- summary ----------------------------------------------------------------------------------
if ((failures)); then
  say "FAIL: $failures of $((passes + failures)) checks failed ($((SECONDS - started)) s)"
  exit 1
fi
say "PASS: $passes checks in $((SECONDS - started)) s"
