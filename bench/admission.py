"""Admission latency and the bytes of a results page (docs/deploy.md#admission).

    .venv/bin/python bench/admission.py [--repeat 5]

Part 1: the CPU milliseconds (``time.process_time``, the median of ``--repeat``
runs) of parsing (json.loads and parse_spec) and of admitting bodies under the body size limit, at the default job
limits (svrobs_core.admission.admit, as ``POST /jobs`` calls it): refused ones
(by the cell cap, the stored bytes, the CPU cost) and the largest admitted
ones; the wall time too (the shared machine's load inflates it). Part 2: the
JSON bytes of one results page of a 50x50 system's records at the default
page cap (SVROBS_MAX_PAGE_MATRIX_ENTRIES), encoded as the API encodes them,
against the rows ``limit=4000`` asked for. About 10 s.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import time

sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))

import numpy as np  # noqa: E402

from service.config import Settings  # noqa: E402
from svrobs_core import parse_spec  # noqa: E402
from svrobs_core.admission import admit  # noqa: E402
from svrobs_core.workload import WorkloadError  # noqa: E402


def _system(n: int) -> dict:
    A = (0.5 * np.eye(n) + 0.02 * np.eye(n, k=1)).tolist()
    return {"name": f"s{n}", "A": A, "B": np.ones((n, 1)).tolist()}


SIGMAS = [0.01 * (i + 1) for i in range(10)]
BODIES = {
    "the 194-byte body (1M cells, ~85,000 s)": {
        "systems": ["paper-stable"],
        "sigma_w": SIGMAS,
        "N": {"start": 1, "stop": 100000},
        "reps": 1,
        "estimators": ["ols"],
        "stages": ["estimate"],
    },
    "10^11 cells (cell cap)": {
        "systems": ["paper-stable"],
        "sigma_w": [1.0],
        "N": {"start": 1, "stop": 100000},
        "reps": 1000000,
    },
    "N list of 100,000 values (~700 KB)": {
        "systems": ["paper-stable"],
        "sigma_w": [1.0],
        "N": list(range(1, 100001)),
        "estimators": ["ols"],
        "stages": ["estimate"],
    },
    "50x50, every stage (stored bytes)": {
        "systems": [_system(50)],
        "sigma_w": SIGMAS,
        "N": [100, 200],
        "reps": 10000,
        "stages": ["estimate", "bounds", "gain"],
    },
    "admitted: 200,000 cells, 10 sigma_w": {
        "systems": ["paper-stable"],
        "sigma_w": SIGMAS,
        "N": list(range(10, 30)),
        "reps": 1000,
        "estimators": ["ols"],
        "stages": ["estimate"],
    },
    "admitted: the paper's grid, every stage": {
        "systems": ["paper-stable", "paper-unstable"],
        "sigma_w": [0.1, 0.5, 1.0],
        "N": [10, 20, 50, 100, 200],
        "reps": 20,
        "gamma": [0.01, 0.05, 0.1],
        "estimators": ["ols", "svr"],
        "stages": ["estimate", "bounds", "gain", "cost", "cost_bound"],
        "mc_runs": 100,
    },
}


def _limits(s: Settings) -> dict:
    return {
        "max_cells": s.MAX_JOB_CELLS,
        "max_stored_bytes": s.MAX_JOB_STORED_MB * 2**20,
        "max_cpu_seconds": s.MAX_JOB_CPU_SECONDS,
        "max_unit_bytes": s.MAX_UNIT_MEMORY_MB * 2**20,
        "max_unit_seconds": s.MAX_UNIT_CPU_SECONDS,
    }


def _admit_once(text: str, limits: dict) -> tuple[float, float, float, str]:
    """(parse CPU s, admit CPU s, both wall s, outcome) of one body."""
    w, t = time.perf_counter(), time.process_time()
    spec = parse_spec(json.loads(text))
    t1 = time.process_time()
    try:
        units, _ = admit(spec, **limits)
        out = f"admitted, {len(units)} units"
    except WorkloadError as exc:
        out = f"422 {exc.kind}: {exc.field}"
    return t1 - t, time.process_time() - t1, time.perf_counter() - w, out


def page_bytes(settings: Settings) -> None:
    """The JSON bytes of a page of 50x50 records, at the cap and at limit=4000."""
    from pydantic_core import to_json

    n = 50
    rng = np.random.default_rng(0)
    rec = {
        "A_hat": rng.standard_normal((n, n)).tolist(),
        "B_hat": rng.standard_normal((n, 1)).tolist(),
        "radii_A": rng.standard_normal((n, n)).tolist(),
        "radii_B": rng.standard_normal((n, 1)).tolist(),
        "L": rng.standard_normal((n, n)).tolist(),
        "K": rng.standard_normal((n, n)).tolist(),
    }
    entries = 4 * n * n + 2 * n
    one = len(to_json(rec, inf_nan_mode="null"))
    rows = max(1, settings.MAX_PAGE_MATRIX_ENTRIES // entries)
    print(f"\n50x50 records, every stage: {entries} matrix entries, {one / 2**10:.0f} KiB each")
    print(f"  limit=4000 uncapped: {4000 * one / 2**20:8.1f} MiB")
    print(
        f"  capped page ({settings.MAX_PAGE_MATRIX_ENTRIES:,} entries): {rows} rows,"
        f" {rows * one / 2**20:.1f} MiB"
    )


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=5)
    args = ap.parse_args(argv)
    settings = Settings()
    limits = _limits(settings)
    print(
        f"{'body':42s} {'bytes':>7s} {'parse':>6s} {'admit':>6s} {'wall':>6s}  outcome"
        "  (CPU ms; wall ms of both)"
    )
    worst = 0.0
    for name, body in BODIES.items():
        text = json.dumps(body)
        runs = [_admit_once(text, limits) for _ in range(args.repeat)]
        parse, cpu, wall = (statistics.median(r[i] for r in runs) * 1e3 for i in range(3))
        worst = max(worst, cpu)
        print(
            f"{name:42s} {len(text):7d} {parse:6.1f} {cpu:6.1f} {wall:6.1f}  {runs[0][3]}",
            flush=True,
        )
    print(f"slowest admission: {worst:.1f} CPU ms (target: well under 50)")
    page_bytes(settings)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
