"""The cost model of a dataset job (svrobs_core.workload with ``data=DataShape``)
against measurement (docs/measured.md#workload).

    .venv/bin/python bench/measured_workload.py

Seeded rollouts of a 3-state, 2-input system; for each (stages, rollouts, steps,
repetitions) one unit holding the whole grid is run twice by
``svrobs_core.measured.run_measured_unit`` (the first warms the imports and
caches) and the second's CPU time (``time.process_time``) is printed beside
``estimate_unit`` and their ratio measured / estimate; the target is a factor of 3
either way. The machine is shared, so CPU times vary by some 20 %.
"""

from __future__ import annotations

import os
import sys
import time

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))

from svrobs_core import parse_spec  # noqa: E402
from svrobs_core.measured import MeasuredData, run_measured_unit  # noqa: E402
from svrobs_core.workload import DataShape, estimate_unit  # noqa: E402

A = np.array([[0.9, 0.2, 0.0], [0.0, 0.8, 0.1], [0.05, 0.0, 0.7]])
B = np.array([[1.0, 0.0], [0.0, 1.0], [0.5, 0.5]])
STAGES = {
    "estimate+bounds": ["estimate", "bounds"],
    "+gain+cost+cost_bound": ["estimate", "bounds", "gain", "cost", "cost_bound"],
    "+sls": ["estimate", "bounds", "gain", "cost", "cost_bound", "sls"],
}
SIZES = ((40, 50, 10), (200, 200, 5), (20, 1000, 20))  # (rollouts N, steps T, reps)


def rollouts(rng, R: int, T: int) -> MeasuredData:
    X, U = [], []
    for _ in range(R):
        u = rng.standard_normal((T, 2))
        x = np.zeros((T + 1, 3))
        x[0] = rng.standard_normal(3)
        for k in range(T):
            x[k + 1] = A @ x[k] + B @ u[k] + 0.1 * rng.standard_normal(3)
        X.append(x)
        U.append(u)
    return MeasuredData(X=X, U=U)


def main() -> int:
    rng = np.random.default_rng(0)
    print(
        f"{'stages':24} {'N':>4} {'T':>5} {'reps':>4} {'measured s':>10} {'estimate s':>10} ratio"
    )
    for label, stages in STAGES.items():
        for R, T, reps in SIZES:
            data = rollouts(rng, R + 2, T)
            spec = parse_spec(
                {
                    "dataset": 1,
                    "N": [R // 2, R],
                    "reps": reps,
                    "holdout": 2,
                    "gamma": [0.01, 0.1],
                    "stages": stages,
                }
            )
            unit = {"system": 0, "sigma_w": 0, "N": [R // 2, R], "reps": [0, reps]}
            run_measured_unit(spec, unit, data)
            t0 = time.process_time()
            run_measured_unit(spec, unit, data)
            cpu = time.process_time() - t0
            shape = DataShape(n=3, m=2, lengths=tuple(int(t) for t in data.lengths))
            est = estimate_unit(spec, unit, data=shape).cpu_seconds
            print(f"{label:24} {R:4d} {T:5d} {reps:4d} {cpu:10.3f} {est:10.3f} {cpu / est:5.2f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
