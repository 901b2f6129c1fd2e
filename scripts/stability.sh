#!/usr/bin/env bash
# Long numerical stability tests (tests/tests/hard_cases_numerics.rs, the #[ignore]d ones): the
# sticky orbit C2 to t = 1e7, R1 to t = 1e7 at δ = 1e-5 and 1e-14 (the seed paper's Fig. 8),
# C1's Lyapunov exponent with renormalisation intervals up to τ = 5000. Each test runs on its
# own, one thread, so the wall times printed are the test's own; every test prints what it
# measured (docs/hard-cases.md records the numbers). About two minutes in all.
#
#   scripts/stability.sh            # every ignored test
#   scripts/stability.sh fig8       # only those whose name contains "fig8"
set -euo pipefail
cd "$(dirname "$0")/.."

cargo_test=(cargo test --release -p salient-tests --test integration)
"${cargo_test[@]}" --no-run

filter="${1:-}"
mapfile -t tests < <("${cargo_test[@]}" -q -- --ignored --list hard_cases_numerics:: 2>/dev/null |
    sed -n 's/: test$//p' | grep -F -- "$filter" || true)
if [ "${#tests[@]}" -eq 0 ]; then
    echo "no ignored test matches '$filter'" >&2
    exit 2
fi

now() { date +%s.%N; }
summary=()
failed=0
all_start=$(now)
for t in "${tests[@]}"; do
    echo
    echo "=== $t"
    start=$(now)
    if "${cargo_test[@]}" -q -- --ignored --nocapture --exact --test-threads=1 "$t"; then
        result=ok
    else
        result=FAILED
        failed=1
    fi
    secs=$(awk -v a="$start" -v b="$(now)" 'BEGIN { print b - a }')
    summary+=("$(printf '%-66s %-6s %7.1f s' "$t" "$result" "$secs")")
done
total=$(awk -v a="$all_start" -v b="$(now)" 'BEGIN { print b - a }')

echo
echo "=== wall times (release build, one test at a time)"
printf '%s\n' "${summary[@]}"
printf '%-66s %-6s %7.1f s\n' "total" "" "$total"
exit "$failed"
