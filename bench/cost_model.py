"""The cost model of svrobs_core.workload per stage, against measurement, for several n.

    .venv/bin/python bench/cost_model.py [--n 2 10 20 30] [--reps 2]

For each n, one fresh subprocess (BLAS on one thread) runs the units of the
same spec with the stages added one at a time (estimate, bounds, gain, cost,
cost_bound; sls on estimate + bounds) and reports the CPU seconds
(``time.process_time``) of each, imports excluded and the SLS program's cache
and the true system's cache cleared before each spec (every unit compiles and
computes them, as the model assumes), after a warm-up spec at n = 2. A
stage's row is what adding it costs: the difference to the spec without it,
measured and estimated (``estimate_job``); the target is a factor of 3 either
way. A row under 0.1 s measured is printed without a ratio: it is within the
noise of the spec it is measured against (the shared machine's, some 20 %).
About 25 CPU seconds with the defaults.
"""

from __future__ import annotations

import argparse
import os
import sys

sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))

from bench.child import run_child  # noqa: E402
from svrobs_core import parse_spec  # noqa: E402
from svrobs_core.workload import estimate_job  # noqa: E402

# (stage, its stages, the stages it is measured against)
PREFIXES = [
    ("estimate", ["estimate"], None),
    ("bounds", ["estimate", "bounds"], ["estimate"]),
    ("gain", ["estimate", "bounds", "gain"], ["estimate", "bounds"]),
    ("cost", ["estimate", "bounds", "gain", "cost"], ["estimate", "bounds", "gain"]),
    (
        "cost_bound",
        ["estimate", "bounds", "gain", "cost", "cost_bound"],
        ["estimate", "bounds", "gain", "cost"],
    ),
    ("sls", ["estimate", "bounds", "sls"], ["estimate", "bounds"]),
]
SMALL = 0.1  # seconds: below this a measured difference is noise

_CHILD = r"""
import json, sys, time
from svrobs_core import parse_spec, plan_units, run_unit_result
from svrobs_core import observer_stages, sls
import cvxpy  # noqa: F401  (an import, not the units' work)
specs = json.loads(sys.argv[1])
warm = parse_spec(specs.pop("warm-up"))  # the code paths' first calls, not measured
for u in plan_units(warm):
    run_unit_result(warm, u).json_lines()
out = {}
for key, obj in specs.items():
    spec = parse_spec(obj)
    sls.clear_cache()  # every unit compiles the SLS program and costs the true system
    observer_stages._truth_cached.cache_clear()
    t = time.process_time()
    for u in plan_units(spec):
        run_unit_result(spec, u).json_lines()
    out[key] = time.process_time() - t
print(json.dumps(out))
"""


def _system(n: int) -> dict:
    A = [[0.5 if i == j else (0.02 if j == i + 1 else 0.0) for j in range(n)] for i in range(n)]
    return {"name": f"diag-{n}", "A": A, "B": [[1.0]] * n}


def _spec(n: int, stages: list[str], reps: int) -> dict:
    return {
        "systems": [_system(n)],
        "sigma_w": [0.1],
        "N": [50],
        "T0": 11,
        "reps": reps,
        "estimators": ["ols"],
        "stages": stages,
        "mc_reps": 1,
        "mc_runs": 50,
        "horizon": 50,
        "sls": {"T_fir": 5},
    }


def measure(specs: dict[str, dict]) -> dict[str, float]:
    return run_child(_CHILD, specs)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", nargs="*", type=int, default=[2, 10, 20, 30])
    ap.add_argument("--reps", type=int, default=2)
    args = ap.parse_args(argv)
    print(f"{'n':>3s} {'stage':10s} {'est s':>8s} {'meas s':>8s} {'est/meas':>8s}")
    worst = 1.0
    for n in args.n:
        keys = {",".join(st): st for _, st, _ in PREFIXES}
        specs = {k: _spec(n, st, args.reps) for k, st in keys.items()}
        got = measure({"warm-up": _spec(2, PREFIXES[4][1] + ["sls"], 1), **specs})
        est = {k: estimate_job(parse_spec(obj)).cpu_seconds for k, obj in specs.items()}
        for stage, st, base in PREFIXES:
            k, b = ",".join(st), ",".join(base) if base else None
            m = got[k] - (got[b] if b else 0.0)
            e = est[k] - (est[b] if b else 0.0)
            if m < SMALL:
                ratio = "   noise"
            else:
                r = e / m
                worst = max(worst, r, 1 / r)
                ratio = f"{r:8.2f}"
            print(f"{n:3d} {stage:10s} {e:8.3f} {m:8.3f} {ratio}", flush=True)
    print(f"worst factor: {worst:.2f} (target <= 3)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
