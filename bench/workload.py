"""The cost model of svrobs_core.workload against measurement.

    .venv/bin/python bench/workload.py [--only NAME ...]

For each spec below, one fresh subprocess imports the core (and cvxpy when
the spec needs it: imports are not part of a unit's estimate), runs every
unit of ``plan_units(spec)`` and reports its CPU time (``time.process_time``
around the units) and its peak resident size (``ru_maxrss``). The table
prints the estimate of ``estimate_job`` next to it and the ratio
estimate / measured; the target is a factor of 3 either way. The machine is
shared, so CPU times vary by some 20 %.
"""

from __future__ import annotations

import argparse
import os
import sys

sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))

from bench.child import run_child  # noqa: E402
from svrobs_core import parse_spec  # noqa: E402
from svrobs_core.workload import estimate_job  # noqa: E402

BASE = {"systems": ["paper-stable"], "sigma_w": [0.1], "estimators": ["ols", "svr"]}
CUSTOM_C = {
    "name": "custom-2x1",
    "A": [[0.9, 0.2], [0.0, 0.7]],
    "B": [[0.0], [1.0]],
    "C": [[1.0, 0.0]],
    "sigma_v": 0.5,
}


def _big_system(n: int) -> dict:
    A = [
        [0.5 if i == j else (0.02 if abs(i - j) == 1 else 0.0) for j in range(n)] for i in range(n)
    ]
    return {"name": f"diag-{n}", "A": A, "B": [[1.0]] * n}


CASES = {
    "estimate N=2000 reps=200": {"N": [2000], "reps": 200},
    "bounds N=10..200 reps=500": {
        "N": [10, 50, 200],
        "reps": 500,
        "stages": ["estimate", "bounds"],
    },
    "T0=1000 N=200 reps=20": {"N": [200], "T0": 1000, "reps": 20},
    "svr only reps=500 gammas=4": {
        "N": [50],
        "reps": 500,
        "estimators": ["svr"],
        "gamma": [0.01, 0.05, 0.1, 0.5],
    },
    "svr QR path (cond 1e17) reps=20": {
        "systems": ["paper-unstable"],
        "sigma_w": [1.0],
        "N": [3],
        "T0": 1000,
        "reps": 20,
        "estimators": ["svr"],
    },
    "bootstrap B=20 reps=10 N=50": {
        "N": [50],
        "reps": 10,
        "bounds_method": "bootstrap",
        "boot_reps": 20,
        "stages": ["estimate", "bounds"],
    },
    "bootstrap B=100 reps=10 N=300": {
        "N": [300],
        "reps": 10,
        "bounds_method": "bootstrap",
        "boot_reps": 100,
        "stages": ["estimate", "bounds"],
    },
    "self-normalized reps=1000": {
        "N": [20],
        "reps": 1000,
        "bounds_method": "self-normalized",
        "stages": ["estimate", "bounds", "gain"],
    },
    "gain reps=2000 gammas=5": {
        "N": [20],
        "reps": 2000,
        "gamma": [0.01, 0.02, 0.05, 0.1, 0.2],
        "stages": ["estimate", "bounds", "gain"],
    },
    "cost mc=1000x200 reps=10": {
        "N": [20],
        "reps": 10,
        "stages": ["estimate", "bounds", "gain", "cost"],
    },
    "cost mc=20000x500 reps=2": {
        "N": [20],
        "reps": 2,
        "stages": ["estimate", "bounds", "gain", "cost"],
        "mc_runs": 20000,
        "horizon": 500,
    },
    "cost_bound reps=1000 mc=0": {
        "N": [20],
        "reps": 1000,
        "stages": ["estimate", "bounds", "gain", "cost", "cost_bound"],
        "mc_reps": 0,
    },
    "general C gain reps=50": {
        "systems": [CUSTOM_C],
        "N": [20],
        "reps": 50,
        "stages": ["estimate", "bounds", "gain"],
    },
    "sls T_fir=30 reps=20": {
        "N": [20],
        "reps": 20,
        "estimators": ["ols"],
        "stages": ["estimate", "bounds", "gain", "cost", "sls"],
        "mc_reps": 0,
    },
    "sls without cost reps=20": {
        "N": [20],
        "reps": 20,
        "estimators": ["ols"],
        "stages": ["estimate", "bounds", "sls"],
    },
    "sls T_fir=200 reps=5": {
        "N": [20],
        "reps": 5,
        "estimators": ["ols"],
        "stages": ["estimate", "bounds", "gain", "cost", "sls"],
        "mc_reps": 0,
        "sls": {"T_fir": 200},
    },
    "n=20 gain+cost reps=20": {
        "systems": [_big_system(20)],
        "N": [50],
        "reps": 20,
        "stages": ["estimate", "bounds", "gain", "cost"],
        "mc_reps": 1,
        "mc_runs": 200,
    },
}

_CHILD = r"""
import json, resource, sys, time
obj = json.loads(sys.argv[1])
from svrobs_core import parse_spec, plan_units, run_unit_result
from svrobs_core.gains import is_orthogonal
spec = parse_spec(obj)
if spec.has("sls") or (spec.has("gain") and not all(is_orthogonal(s.C) for s in spec.systems)):
    import cvxpy  # noqa: F401  (an import, not the unit's work)
t = time.process_time()
for u in plan_units(spec):
    run_unit_result(spec, u).json_lines()
cpu = time.process_time() - t
print(json.dumps({"cpu": cpu, "rss": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024}))
"""


def measure(obj: dict) -> dict:
    return run_child(_CHILD, obj)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--only", nargs="*", help="case names (substrings) to run")
    args = ap.parse_args(argv)
    print(
        f"{'spec':30s} {'units':>5s} {'cpu est':>8s} {'cpu meas':>8s} {'ratio':>6s}"
        f" {'MB est':>7s} {'MB meas':>7s} {'ratio':>6s}"
    )
    worst = 1.0
    for name, extra in CASES.items():
        if args.only and not any(s in name for s in args.only):
            continue
        obj = {**BASE, **extra}
        est = estimate_job(parse_spec(obj))
        got = measure(obj)
        rc = est.cpu_seconds / max(got["cpu"], 1e-9)
        rm = est.peak_unit_bytes / got["rss"]
        worst = max(worst, rc, 1 / rc, rm, 1 / rm)
        print(
            f"{name:30s} {est.n_units:5d} {est.cpu_seconds:8.3f} {got['cpu']:8.3f} {rc:6.2f}"
            f" {est.peak_unit_bytes / 2**20:7.0f} {got['rss'] / 2**20:7.0f} {rm:6.2f}",
            flush=True,
        )
    print(f"worst factor: {worst:.2f} (target <= 3)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
