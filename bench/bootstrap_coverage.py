"""Audit: how often the bootstrap box (docs/uncertainty.md (e)) holds the truth.

Run: PYTHONPATH=. .venv/bin/python bench/bootstrap_coverage.py [--reps R] [--boot-reps B]

Three systems (the paper's two and a 2-state system used nowhere else), final
and all data, N in {8, 300}, T0 = 8, delta = 0.2, OLS and SVR (gamma = 0.05),
the residual sigma_w (boot_sigma_w "estimate", the default). Per group: the
share of repetitions with every entry of A and of B inside the box at once
(coverage_A == coverage_B == 1), its standard error, and the self-normalized
box's share on the same data for comparison.
"""

from __future__ import annotations

import argparse
import math

import numpy as np

from svrobs_core.parsing import parse_spec
from svrobs_core.runner import run_spec

SYSTEMS = [
    "paper-stable",
    "paper-unstable",
    {
        "name": "audit-2x1",
        "A": [[0.6, 0.25], [-0.15, 0.45]],
        "B": [[0.3], [1.0]],
        "sigma_u": 1.0,
        "sigma_v": 0.2,
    },
]
DELTA = 0.2


def coverage(method: str, *, reps: int, boot_reps: int, data: str) -> dict:
    spec = {
        "systems": SYSTEMS,
        "sigma_w": [1.0],
        "N": [8, 300],
        "T0": 8,
        "data": data,
        "reps": reps,
        "estimators": ["ols", "svr"],
        "gamma": [0.05],
        "bounds_method": method,
        "delta": DELTA,
        "stages": ["estimate", "bounds"],
        "seed": 11,
    }
    if method == "bootstrap":
        spec["boot_reps"] = boot_reps
    groups: dict[tuple, list] = {}
    for batch in run_spec(parse_spec(spec)):
        for r in batch:
            key = (r["system"], data, r["N"], r["estimator"])
            inside = r["coverage_A"] == 1 and r["coverage_B"] == 1
            groups.setdefault(key, []).append(inside)
    return {k: float(np.mean(v)) for k, v in groups.items()}


def main(argv=None) -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--reps", type=int, default=300)
    ap.add_argument("--boot-reps", type=int, default=100)
    args = ap.parse_args(argv)
    se = math.sqrt(DELTA * (1 - DELTA) / args.reps)
    print(f"target 1 - delta = {1 - DELTA:.2f}; one standard error {se:.3f} ({args.reps} reps)")
    print("| system | data | N | estimator | bootstrap | self-normalized |")
    print("|---|---|---|---|---|---|")
    below, total, shares = 0, 0, []
    for data in ("final", "all"):
        boot = coverage("bootstrap", reps=args.reps, boot_reps=args.boot_reps, data=data)
        sn = coverage("self-normalized", reps=args.reps, boot_reps=0, data=data)
        for key, c in boot.items():
            system, _, N, estimator = key
            print(f"| {system} | {data} | {N} | {estimator} | {c:.3f} | {sn[key]:.3f} |")
            total += 1
            below += c < 1 - DELTA - 2 * se
            shares.append(c)
    print(
        f"bootstrap: {below} of {total} groups more than 2 SE below {1 - DELTA:.2f};"
        f" range {min(shares):.3f}-{max(shares):.3f}"
    )


if __name__ == "__main__":
    main()
