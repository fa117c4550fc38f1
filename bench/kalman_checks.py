"""The steady-state Kalman gain on batches of 4,000 cells, this tree against another.

    .venv/bin/python bench/kalman_checks.py --baseline /tmp/wt_old   # a worktree
    git worktree add /tmp/wt_old 92a203b                             # (made once)

Times ``svrobs_core.kalman.kalman_predictor`` (best of ``--runs`` CPU times, one
thread) on four batches of 3x3 systems (docs/performance.md#the-numbers-at-the-edges-core):
the paper's unstable system with noise and C = I, random non-normal systems with two
random outputs, the same scaled by 1.3, and the paper's system scaled by 1.5 with one
output. Each tree runs in its own child process (``PYTHONPATH`` set to it), the two
alternated ``--rounds`` times; it prints each batch's times and their ratio.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent

CHILD = r"""
import json, sys, time
import numpy as np
from svrobs_core.kalman import kalman_predictor

runs = int(sys.argv[1])
rng = np.random.default_rng(0)
A0 = np.array([[0.9, 0.01, 0], [0.01, 0.9, 0.01], [0, 0.01, 0.9]]) + 0.11 * np.eye(3)
R = 0.9 * np.eye(3) + 0.2 * rng.normal(size=(4000, 3, 3))
batches = {
    "paper-unstable + noise, C = I": (A0 + 0.01 * rng.normal(size=(4000, 3, 3)), np.eye(3)),
    "non-normal, two outputs": (R, rng.normal(size=(2, 3))),
    "the same x 1.3": (1.3 * R, rng.normal(size=(2, 3))),
    "paper-unstable x 1.5, one output": (
        1.5 * (A0 + 0.01 * rng.normal(size=(4000, 3, 3))), np.array([[1.0, 0, 0]])),
}
out = {}
for name, (A, C) in batches.items():
    best = []
    for _ in range(runs):
        t = time.process_time()
        kalman_predictor(A, C, 0.1, 0.1)
        best.append(time.process_time() - t)
    out[name] = min(best)
print(json.dumps(out))
"""


def timed(tree: Path, runs: int) -> dict[str, float]:
    env = {**os.environ, "PYTHONPATH": str(tree), "OPENBLAS_NUM_THREADS": "1"}
    done = subprocess.run(
        [sys.executable, "-c", CHILD, str(runs)],
        env=env,
        cwd=str(tree),
        capture_output=True,
        text=True,
        check=True,
    )
    return json.loads(done.stdout)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--baseline", type=Path, required=True, help="a worktree of the other tree")
    ap.add_argument("--runs", type=int, default=12)
    ap.add_argument("--rounds", type=int, default=2)
    args = ap.parse_args()
    mine: dict[str, list[float]] = {}
    base: dict[str, list[float]] = {}
    for _ in range(args.rounds):
        for store, tree in ((base, args.baseline), (mine, ROOT)):
            for name, t in timed(tree, args.runs).items():
                store.setdefault(name, []).append(t)
    print(f"{'batch (4,000 cells)':36s} {'baseline':>10s} {'this tree':>10s} {'ratio':>6s}")
    for name, times in mine.items():
        b, m = min(base[name]), min(times)
        print(f"{name:36s} {b * 1e3:8.1f} ms {m * 1e3:7.1f} ms {m / b:6.2f}")


if __name__ == "__main__":
    main()
