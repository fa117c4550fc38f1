"""Parsing and admitting a spec of many systems: CPU per system, this tree against another.

    .venv/bin/python bench/many_systems.py [--repeat 5] [--against DIR]

Each body is parsed (``parse_spec`` of the decoded JSON; ``json.loads`` is timed
apart) and admitted at the default job limits (``svrobs_core.admission.admit``, as
``POST /jobs`` and a schedule's template call them), in a child process per tree;
the figures are CPU milliseconds (``time.process_time``), the median of
``--repeat`` runs. ``--against DIR`` runs the same bodies on the code in DIR (a
checkout of another revision, e.g. ``git archive REV svrobs_core service |
tar -x -C DIR``) and prints both side by side with the ratio; the outcome of each
body (the units and the cost, or the error) must be the same in both. About a minute.
"""

from __future__ import annotations

import argparse
import gc
import itertools
import json
import os
import statistics
import subprocess
import sys
import time
from collections.abc import Callable
from functools import partial

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))


def _random_systems(k: int, seed: int = 0) -> list[dict]:
    """n = 3, m = 1, p = 1: A scaled to rho 0.5 (even) or 1.5 (odd); every tenth with
    sigma_v = 0 and a square C (its cond(C) is checked)."""
    rng = np.random.default_rng(seed)
    out = []
    for i in range(k):
        A = rng.standard_normal((3, 3))
        A *= (1.5 if i % 2 else 0.5) / np.max(np.abs(np.linalg.eigvals(A)))
        s = {"name": f"s{i}", "A": A.tolist(), "B": rng.standard_normal((3, 1)).tolist()}
        if i % 10 == 0:
            s.update(C=rng.standard_normal((3, 3)).tolist(), sigma_v=0)
        else:
            s["C"] = rng.standard_normal((1, 3)).tolist()
        out.append(s)
    return out


def _many_shapes(limit: int = 2**20) -> list[dict]:
    """Systems of distinct (n, m, p), the smallest first, as many as a body of
    ``limit`` bytes (SVROBS_MAX_BODY_BYTES) holds: each is a kind of its own."""
    shapes = sorted(itertools.product(range(1, 51), repeat=3), key=lambda s: s[0] * sum(s))
    out, size = [], 100
    for i, (n, m, p) in enumerate(shapes):
        s = {"name": f"s{i}", "A": [[0] * n] * n, "B": [[0] * m] * n, "C": [[0] * n] * p}
        size += len(json.dumps(s)) + 2
        if size > limit:
            return out
        out.append(s)
    return out


def bodies() -> dict[str, Callable[[], dict]]:
    """The bodies, each made when asked (one at a time in memory)."""
    small = {"sigma_w": [1.0], "N": [10], "reps": 1, "estimators": ["ols"], "stages": ["estimate"]}
    return {
        "5,000 random 3x1x1 (1 in 10 sigma_v = 0)": lambda: {
            "systems": _random_systems(5000),
            **small,
        },
        "22,000 one-state, defaults (1 MB)": lambda: {
            "systems": [{"name": f"s{i}", "A": [[0.5]], "B": [[1.0]]} for i in range(22_000)],
            "sigma_w": [1.0],
            "N": [10],
        },
        "one system of each (n, m, p), 1 MB": lambda: {"systems": _many_shapes(), **small},
        "5,000 random 3x1x1, refused (CPU)": lambda: {
            "systems": _random_systems(5000, seed=1),
            "sigma_w": [1.0],
            "N": [100_000],
            "reps": 40,
        },
    }


def _outcome(admitted: Callable[[], tuple], refusal: type[Exception]) -> str:
    """The units and the cost the spec is admitted with, or the error refusing it."""
    try:
        units, cost = admitted()
    except refusal as exc:
        return str(exc)
    return f"{len(units)} units, {cost.cpu_seconds!r} s, {cost.peak_unit_bytes} B"


def child(repeat: int) -> None:
    """Time every body on the code of the tree on PYTHONPATH; one JSON line per body."""
    sys.path[:] = [p for p in sys.path if os.path.abspath(p or ".") != HERE]  # bench/service.py
    from service.config import Settings
    from svrobs_core import parse_spec
    from svrobs_core.admission import admit
    from svrobs_core.errors import SpecError

    s = Settings()
    limits = {
        "max_cells": s.MAX_JOB_CELLS,
        "max_stored_bytes": s.MAX_JOB_STORED_MB * 2**20,
        "max_cpu_seconds": s.MAX_JOB_CPU_SECONDS,
        "max_unit_bytes": s.MAX_UNIT_MEMORY_MB * 2**20,
        "max_unit_seconds": s.MAX_UNIT_CPU_SECONDS,
    }
    for name, make in bodies().items():
        body = make()
        text, k = json.dumps(body), len(body["systems"])
        del body
        gc.collect()
        runs = []
        for _ in range(repeat):
            gc.collect()  # the previous run's objects gone: each run starts alike
            t0 = time.process_time()
            obj = json.loads(text)
            t1 = time.process_time()
            spec = parse_spec(obj)
            t2 = time.process_time()
            outcome = _outcome(partial(admit, spec, **limits), SpecError)
            runs.append((t1 - t0, t2 - t1, time.process_time() - t2))
            del obj, spec
        loads, parse, adm = (statistics.median(r[i] for r in runs) * 1e3 for i in range(3))
        line = {"name": name, "systems": k, "bytes": len(text)}
        line.update(loads=loads, parse=parse, admit=adm, outcome=outcome)
        print(json.dumps(line), flush=True)


def _run(tree: str, repeat: int) -> list[dict]:
    env = {**os.environ, "PYTHONPATH": tree}
    cmd = [sys.executable, os.path.abspath(__file__), "--child", "--repeat", str(repeat)]
    out = subprocess.run(cmd, env=env, cwd=tree, capture_output=True, text=True)
    if out.returncode:
        raise SystemExit(f"{tree}: {out.stderr}")
    return [json.loads(line) for line in out.stdout.splitlines() if line.startswith("{")]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--against", metavar="DIR", help="a tree of another revision")
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.child:
        child(args.repeat)
        return 0
    here = _run(os.path.dirname(HERE), args.repeat)
    there = _run(os.path.abspath(args.against), args.repeat) if args.against else None
    print("CPU ms (median); per system: (parse + admit) / systems")
    for i, row in enumerate(here):
        k = row["systems"]
        now = row["parse"] + row["admit"]
        print(f"\n{row['name']}  ({row['bytes']:,} bytes; json.loads {row['loads']:.0f} ms)")
        if there is not None:
            old = there[i]["parse"] + there[i]["admit"]
            print(f"  {'':8s} {'parse':>8s} {'admit':>8s} {'us/system':>10s}")
            print(
                f"  {'against':8s} {there[i]['parse']:8.1f} {there[i]['admit']:8.1f}"
                f" {old / k * 1e3:10.1f}"
            )
        print(f"  {'this':8s} {row['parse']:8.1f} {row['admit']:8.1f} {now / k * 1e3:10.1f}")
        if there is not None:
            print(f"  ratio {old / now:.1f}x")
            if there[i]["outcome"] != row["outcome"]:
                print(f"  OUTCOMES DIFFER: {there[i]['outcome']!r} != {row['outcome']!r}")
                return 1
        print(f"  outcome: {row['outcome']}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
