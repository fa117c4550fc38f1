"""Benchmark: the Monte Carlo J of one E3 unit's grid against its draws.

    OPENBLAS_NUM_THREADS=1 .venv/bin/python bench/mc_grid.py [--rows 10] [--cells 4]
                                                             [--runs 1000] [--repeat 6]

``svrobs_core.cost_mc.mc_cost_shared`` on the paper's stable system (horizon 200)
for ``--rows`` repetitions of ``--cells`` perturbed cells each, as an E3 unit calls
it, side by side with the same normal draws alone (one ``standard_normal`` per
block of steps and row, its floor), alternated ``--repeat`` times in one process.
Prints the median CPU seconds of each and their ratio
(docs/performance.md#reproduce).
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))

from svrobs_core.cost_mc import mc_cost_shared
from svrobs_core.systems import resolve_system


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rows", type=int, default=10)
    ap.add_argument("--cells", type=int, default=4)
    ap.add_argument("--runs", type=int, default=1000)
    ap.add_argument("--repeat", type=int, default=6)
    args = ap.parse_args(argv)
    sy = resolve_system("paper-stable")
    n, m, p = sy.n, sy.m, sy.C.shape[0]
    R, E, T, runs = args.rows, args.cells, 200, args.runs
    rng = np.random.default_rng(0)
    At = sy.A + 0.01 * rng.standard_normal((R, E, n, n))
    Bt = sy.B + 0.01 * rng.standard_normal((R, E, n, m))
    L = 0.3 * np.eye(n, p) * np.ones((R, E, n, p))

    def grid() -> None:
        mc_cost_shared(
            sy.A,
            sy.B,
            At,
            Bt,
            L=L,
            C=sy.C,
            sigma_u=sy.sigma_u,
            sigma_w=1.0,
            sigma_v=sy.sigma_v,
            horizon=T,
            rngs=[np.random.default_rng(r) for r in range(R)],
            runs=runs,
        )

    def draws() -> None:
        for r in range(R):
            np.random.default_rng(r).standard_normal((T, runs, m + n + p))

    times: dict[str, list[float]] = {"grid": [], "draws": []}
    grid()
    for _ in range(args.repeat):
        for name, fn in (("grid", grid), ("draws", draws)):
            t = time.process_time()
            fn()
            times[name].append(time.process_time() - t)
    g, d = (statistics.median(times[k]) for k in ("grid", "draws"))
    print(
        f"Monte Carlo J, {R} rows x {E} cells x {runs} runs x {T} steps "
        f"({R * T * runs * (m + n + p):,} normals), median of {args.repeat}:"
    )
    print(f"  mc_cost_shared {g * 1e3:8.1f} ms CPU")
    print(f"  draws alone    {d * 1e3:8.1f} ms CPU")
    print(f"  ratio          {g / d:8.2f}x")
    return 0


if __name__ == "__main__":
    sys.exit(main())
