"""Benchmark: the cost of the sound uncertainty sets (docs/uncertainty.md).

Run: PYTHONPATH=. .venv/bin/python bench/bounds.py [--quick]

1. The Section 6 estimation grid (the paper preset's E2: both systems, sigma_w in
   {0.1, 1, 10}, N = 10..450, 45 repetitions, OLS and SVR at four gammas, stages
   estimate + bounds) with bounds_method "paper" and "self-normalized": CPU
   seconds each (best of a few runs, one process) and the ratio. The target
   is a ratio under 1.10: the self-normalized box uses one eigendecomposition of
   Z Z^T per dataset, shared by every gamma.
2. bounds_method "bootstrap" with 100 resamples: seconds per cell (one cell =
   one (repetition, estimator, gamma)) at N = 10, 100 and 450 on the stable
   system, sigma_w = 1, 45 repetitions batched in one call, minus the time of
   the same grid with the paper's bounds.

``--quick`` uses 9 repetitions and a coarser N grid (a smoke run, about 20 s).
"""

from __future__ import annotations

import sys
import time

from svrobs_core.paper import paper_specs
from svrobs_core.parsing import parse_spec
from svrobs_core.runner import run_spec


def _discard(result):
    return len(result)


def run_seconds(spec_obj: dict, repeat: int) -> tuple[float, int]:
    """Best CPU time of this process running every unit (BLAS single-threaded, as the
    runner sets it), and the cell count. CPU time, not wall time: the benchmark
    machine is shared, and wall times there vary by 2x from run to run."""
    spec = parse_spec(spec_obj)
    best = float("inf")
    for _ in range(repeat):
        t = time.process_time()
        cells = sum(run_spec(spec, post=_discard))
        best = min(best, time.process_time() - t)
    return best, cells


def main(quick: bool = False) -> None:
    grid = paper_specs("full")["E2"]
    if quick:
        grid = {**grid, "reps": 9, "N": {"start": 10, "stop": 450, "step": 40}}
    repeat = 2 if quick else 5
    t_paper, cells = run_seconds(grid, repeat)
    t_sn, _ = run_seconds({**grid, "bounds_method": "self-normalized"}, repeat)
    print(f"estimation grid E2: {cells} cells")
    print(f"  bounds_method paper           {t_paper:8.2f} s")
    print(f"  bounds_method self-normalized {t_sn:8.2f} s   ratio {t_sn / t_paper:.3f}")

    reps = 9 if quick else 45
    print(f"bootstrap, 100 resamples, paper-stable, sigma_w = 1, {reps} repetitions:")
    for N in (10, 100, 450):
        one = {
            **grid,
            "systems": ["paper-stable"],
            "sigma_w": [1.0],
            "N": [N],
            "reps": reps,
        }
        base, cells = run_seconds(one, 1)
        boot, _ = run_seconds({**one, "bounds_method": "bootstrap", "boot_reps": 100}, 1)
        per_cell = (boot - base) / cells
        print(
            f"  N = {N:3d}: {cells} cells, {boot:7.2f} s, bootstrap {1e3 * per_cell:7.2f} ms/cell"
        )


if __name__ == "__main__":
    main(quick="--quick" in sys.argv)
