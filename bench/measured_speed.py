"""Benchmark: the measured path against the simulated path on the same grid.

Run: PYTHONPATH=. .venv/bin/python bench/measured_speed.py

250 datasets of 20 rollouts of 25 steps (the system of
tests/core/test_measured_coverage.py; N0 = 500), estimators OLS, SVR and shrunk
OLS at one gamma, stages estimate + bounds + gain (self-normalized box, C = I):
``run_datasets`` (one repetition per dataset) against a simulated job of the
same shape (250 repetitions, N = 20, T0 = 26), CPU seconds, best of 5, one process.
"""

from __future__ import annotations

import sys
import time

sys.path.insert(0, "tests/core")

import test_measured_coverage as mc  # noqa: E402

from svrobs_core import parse_spec, plan_units, run_unit_result  # noqa: E402
from svrobs_core.measured import run_datasets  # noqa: E402


def best(fn, runs=5) -> float:
    out = []
    for _ in range(runs):
        t = time.process_time()
        fn()
        out.append(time.process_time() - t)
    return min(out)


if __name__ == "__main__":
    system = {"name": "bench", "A": mc.A2.tolist(), "B": mc.B2.tolist(), "sigma_v": 1.0}
    sim = parse_spec(
        {
            "systems": [system],
            "sigma_w": [mc.SIGMA],
            "N": [20],
            "T0": 26,
            "reps": mc.D,
            "estimators": ["ols", "svr", "shrunk-ols"],
            "gamma": [0.5],
            "delta": mc.DELTA,
            "stages": ["estimate", "bounds", "gain"],
            "bounds_method": "self-normalized",
        }
    )
    units = plan_units(sim)
    datasets, _, _ = mc.state_datasets(1)
    meas = parse_spec({**mc.SPEC, "sigma_w": mc.SIGMA})
    t_sim = best(lambda: [run_unit_result(sim, u) for u in units])
    t_meas = best(lambda: run_datasets(meas, datasets))
    cells = 3 * mc.D
    print(f"simulated: {t_sim:.3f} s ({1e6 * t_sim / cells:.0f} us/cell)")
    print(
        f"measured:  {t_meas:.3f} s ({1e6 * t_meas / cells:.0f} us/cell), ratio {t_meas / t_sim:.2f}"
    )
