#!/usr/bin/env bash
# Side-by-side per-step cost of Salient's Taylor integrator and heyoka (LLVM-JIT Taylor) on the
# same system: Hénon-Heiles orbit R1 plus 2 deviation vectors (12 ODEs), natural steps to
# t = 1e4, best of 5 runs each. heyoka is a peer tool, installed into a throw-away venv here
# (PyPI); nothing of it is part of Salient.
set -euo pipefail
cd "$(dirname "$0")/.."
venv=${HEYOKA_VENV:-/tmp/salient-heyoka-venv}
[ -x "$venv/bin/python" ] || { python3 -m venv "$venv" && "$venv/bin/pip" install -q heyoka numpy; }
cargo build -q --release -p salient-core --example taylor_steps
for tol in 1e-10 1e-15; do
  ./target/release/examples/taylor_steps "$tol"
  "$venv/bin/python" - "$tol" <<'PY'
import sys, time, math
import heyoka as hy
tol = float(sys.argv[1])
q1, q2, p1, p2, u1, u2, v1, v2, w1, w2, z1, z2 = hy.make_vars(*"q1 q2 p1 p2 u1 u2 v1 v2 w1 w2 z1 z2".split())
# Orbit and two deviation vectors (u, v) = (δq, δp), (w, z) = (δq, δp) of the variational equations.
sys_ = [(q1, p1), (q2, p2), (p1, -q1 - 2.0 * q1 * q2), (p2, -q2 - q1 * q1 + q2 * q2),
        (u1, v1), (u2, v2), (v1, -(1.0 + 2.0 * q2) * u1 - 2.0 * q1 * u2), (v2, -2.0 * q1 * u1 - (1.0 - 2.0 * q2) * u2),
        (w1, z1), (w2, z2), (z1, -(1.0 + 2.0 * q2) * w1 - 2.0 * q1 * w2), (z2, -2.0 * q1 * w1 - (1.0 - 2.0 * q2) * w2)]
Q2 = 0.558
P1 = math.sqrt(0.25 - Q2 * Q2 + 2.0 * Q2 ** 3 / 3.0)
init = [0.0, Q2, P1, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0]
ta = hy.taylor_adaptive(sys_, init, tol=tol)
best, steps = float("inf"), 0
for _ in range(5):
    ta.time = 0.0
    ta.state[:] = init
    t0 = time.perf_counter()
    res = ta.propagate_until(1e4)
    best = min(best, time.perf_counter() - t0)
    steps = res[3]
s = ta.state
h = 0.5 * (s[2] ** 2 + s[3] ** 2) + 0.5 * (s[0] ** 2 + s[1] ** 2) + s[0] ** 2 * s[1] - s[1] ** 3 / 3.0
print(f"heyoka {hy.__version__} tol {tol:e} order {ta.order:>2}  steps {steps}  {best*1e3:.3f} ms  {best*1e9/steps:.0f} ns/step  |dH/H| {abs(h-0.125)/0.125:.1e}")
PY
done
