"""Service overhead: the Section 6 estimation grid through the real stacks vs in process.

    .venv/bin/python bench/service.py                      # embedded, and pg if configured
    .venv/bin/python bench/service.py --stacks embedded --quick
    .venv/bin/python bench/service.py --stacks postgres --quick   # pg, postgres, postgresql

The grid (the paper's Section 6: 2 systems x sigma_w {0.1, 1, 10} x N 10..450 step 10
x gamma {0.005, 0.01, 0.05, 0.1} x {ols, svr} x 45 reps, stages estimate +
bounds = 60,750 cells; the work units are counted in the first line printed) is

1. run in this process by the core (``svrobs_core.run_spec``): the baseline;
2. submitted over REST to the embedded stack (SQLite + filesystem broker,
   uvicorn + celery worker processes, exactly as ``svrobs serve`` starts them)
   and timed from POST until the job says succeeded;
3. the same through PostgreSQL + Redis (``SVROBS_BENCH_DATABASE_URL`` /
   ``SVROBS_BENCH_BROKER_URL``, else the ``SVROBS_TEST_*`` ones; a fresh
   schema, dropped afterwards, and the Redis DB of the URL flushed).

It prints each wall time and the ratio service / in-process, against the core in
one process and against the core with ``n_jobs=2`` (the same two cores; the
target is 1.3x of that); the CPU seconds of the stack's processes (API and
worker, from /proc; not the database server's) against the core's in one
process, which a machine loaded by other work does not stretch as it does wall
times; and, from the workers' logs, a unit's mean claim, compute and store
times (what ``worker.tasks.execute_unit`` returns) with claim + store as a share
of compute (target at most 25 %). The worker runs ``svrobs serve``'s default pool (one
process per CPU plus one: 3 here) unless ``--concurrency`` says otherwise.
Then, per stack, it stores a synthetic job of 100,000 cells (bulk-inserted rows,
units completed through ``units.complete_unit``) and times a filtered results page
``GET /jobs/{id}/results?N=..&estimator=svr&gamma=..&limit=100`` (target
< 200 ms; median and p95 over 30 requests after warm-up).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))


from bench.bench_stack import SYNTH, BenchStack
from svrobs_cli.serve import DEFAULT_CONCURRENCY

GRID = {
    "systems": ["paper-stable", "paper-unstable"],
    "sigma_w": [0.1, 1.0, 10.0],
    "N": {"start": 10, "stop": 450, "step": 10},
    "gamma": [0.005, 0.01, 0.05, 0.1],
    "estimators": ["ols", "svr"],
    "reps": 45,
    "stages": ["estimate", "bounds"],
    "seed": 0,
}
QUICK_GRID = {**GRID, "N": {"start": 10, "stop": 450, "step": 70}}
# 2 systems x 5 sigma_w x 20 N x 100 reps x (ols + 4 gammas) = 100,000 cells
BIG = {
    "systems": ["paper-stable", "paper-unstable"],
    "sigma_w": [0.1, 0.5, 1.0, 5.0, 10.0],
    "N": {"start": 10, "stop": 200, "step": 10},
    "gamma": [0.005, 0.01, 0.05, 0.1],
    "estimators": ["ols", "svr"],
    "reps": 100,
    "stages": ["estimate", "bounds"],
}


def unit_breakdown(logs: Path) -> dict:
    """Mean claim / compute / store seconds per unit, from the workers' 'succeeded' lines."""
    import re

    sums: dict[str, list[float]] = {"claim_s": [], "compute_s": [], "store_s": [], "task_s": []}
    for log in logs.glob("worker*.log"):
        for line in log.read_text(errors="replace").splitlines():
            m = re.search(r"succeeded in ([0-9.]+)s: (\{.*'status': 'done'.*\})", line)
            if not m:
                continue
            sums["task_s"].append(float(m.group(1)))
            for k in ("claim_s", "compute_s", "store_s"):
                km = re.search(rf"'{k}': ([0-9.]+)", m.group(2))
                if km:
                    sums[k].append(float(km.group(1)))
    out = {k: sum(v) / len(v) for k, v in sums.items() if v}
    if out:
        out["units"] = len(sums["task_s"])
    return out


def in_process(spec: dict, n_jobs: int = 1) -> tuple[float, int, float]:
    """(wall seconds, records, CPU seconds of this process and its children)."""
    import resource

    from svrobs_core import parse_spec, run_spec

    def cpu() -> float:  # this process, its children reaped, and those still alive
        r = resource.getrusage(resource.RUSAGE_CHILDREN)
        return time.process_time() + r.ru_utime + r.ru_stime + descendants_cpu()

    c0 = cpu()
    t0 = time.perf_counter()
    n = sum(len(batch) for batch in run_spec(parse_spec(spec), n_jobs=n_jobs))
    wall = time.perf_counter() - t0
    return wall, n, cpu() - c0


def descendants_cpu(root: int | None = None) -> float:
    """CPU seconds (user + system) used so far by the live descendants of ``root``
    (default: this process), from /proc: the stack's API and worker processes. A
    machine shared with other work stretches wall times; CPU seconds compare."""
    root = os.getpid() if root is None else root
    tick = os.sysconf("SC_CLK_TCK")
    parent: dict[int, int] = {}
    cpu: dict[int, float] = {}
    for d in os.listdir("/proc"):
        if not d.isdigit():
            continue
        try:
            stat = Path(f"/proc/{d}/stat").read_text()
        except OSError:
            continue
        fields = stat[stat.rindex(")") + 2 :].split()  # after "pid (comm) "
        parent[int(d)] = int(fields[1])
        cpu[int(d)] = (int(fields[11]) + int(fields[12])) / tick
    total, todo = 0.0, [root]
    while todo:
        p = todo.pop()
        for child, pp in parent.items():
            if pp == p:
                total += cpu[child]
                todo.append(child)
    return total


# the names --stacks takes, and the stack each means
STACK_NAMES = {
    "embedded": "embedded",
    "sqlite": "embedded",
    "pg": "pg",
    "postgres": "pg",
    "postgresql": "pg",
}


def parse_stacks(text: str) -> list[str]:
    """``--stacks`` as stack kinds (``embedded``, ``pg``), in order, each once."""
    kinds: list[str] = []
    for name in (n.strip().lower() for n in text.split(",")):
        if not name:
            continue
        if name not in STACK_NAMES:
            raise argparse.ArgumentTypeError(
                f"unknown stack {name!r}: use {', '.join(STACK_NAMES)} (comma-separated)"
            )
        if STACK_NAMES[name] not in kinds:
            kinds.append(STACK_NAMES[name])
    return kinds


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument(
        "--stacks",
        type=parse_stacks,
        default="embedded,pg",
        help="embedded (sqlite) and/or pg (postgres, postgresql), comma-separated",
    )
    p.add_argument("--quick", action="store_true", help="a 7-N grid instead of 45 (smoke run)")
    p.add_argument("--embedded-workers", type=int, default=1)
    p.add_argument("--pg-workers", type=int, default=2)
    p.add_argument(
        "--concurrency",
        type=int,
        default=DEFAULT_CONCURRENCY,
        help="pool processes per worker (default: svrobs serve's, one per CPU plus one)",
    )
    p.add_argument("--no-page", action="store_true", help="skip the 100k-cell results page")
    p.add_argument("--keep", action="store_true", help="keep the stacks' folders (logs)")
    args = p.parse_args()
    grid = QUICK_GRID if args.quick else GRID
    pg_url = os.environ.get("SVROBS_BENCH_DATABASE_URL") or os.environ.get(
        "SVROBS_TEST_DATABASE_URL"
    )
    redis_url = os.environ.get("SVROBS_BENCH_BROKER_URL") or os.environ.get(
        "SVROBS_TEST_BROKER_URL"
    )
    stacks = args.stacks

    from svrobs_core import parse_spec, plan_units

    spec = parse_spec(grid)
    print(
        f"grid: {spec.n_cells} cells in {len(plan_units(spec))} work units; {os.cpu_count()} CPUs"
    )
    base, n, base_cpu = in_process(grid)
    print(
        f"{'in process (run_spec, 1 process):':54s}{base:8.1f} s  ({n} records, "
        f"{base_cpu:.1f} CPU s)",
        flush=True,
    )
    base2, _, base2_cpu = in_process(grid, n_jobs=2)
    print(
        f"{'in process (run_spec, n_jobs=2):':54s}{base2:8.1f} s  ({base2_cpu:.1f} CPU s; "
        "ratios below: against 1 process, against n_jobs=2)",
        flush=True,
    )
    print(f"load average at the start: {os.getloadavg()[0]:.1f}", flush=True)

    rows = []
    for kind in stacks:
        if kind == "pg" and not (pg_url and redis_url):
            print("pg: skipped (set SVROBS_BENCH_DATABASE_URL/_BROKER_URL or SVROBS_TEST_*)")
            continue
        workers = args.embedded_workers if kind == "embedded" else args.pg_workers
        root = Path(tempfile.mkdtemp(prefix=f"svrobs-bench-{kind}-"))
        try:
            with BenchStack(kind, root, workers, args.concurrency, pg_url, redis_url) as st:
                cpu0 = descendants_cpu()
                elapsed, job = st.run_job(grid)
                stack_cpu = descendants_cpu() - cpu0
                label = (
                    "embedded (SQLite + filesystem)" if kind == "embedded" else "PostgreSQL + Redis"
                )
                procs = f"{workers}x{args.concurrency} worker process(es)"
                print(
                    f"{label + ', ' + procs + ':':54s}{elapsed:8.1f} s  "
                    f"ratio {elapsed / base:5.2f}x, {elapsed / base2:5.2f}x  "
                    f"(units {job['progress']['total']}, "
                    f"job run {job['timings'].get('run_seconds', float('nan')):.1f} s)",
                    flush=True,
                )
                print(
                    f"  CPU of the stack's processes (API + worker, not the database server): "
                    f"{stack_cpu:.1f} s, {stack_cpu / base_cpu:.2f}x the core's in one process "
                    f"(load average {os.getloadavg()[0]:.1f})",
                    flush=True,
                )
                row = {
                    "stack": kind,
                    "workers": workers,
                    "concurrency": args.concurrency,
                    "seconds": elapsed,
                    "ratio": elapsed / base,
                    "ratio_2_processes": elapsed / base2,
                    "stack_cpu_seconds": stack_cpu,
                    "cpu_ratio": stack_cpu / base_cpu,
                }
                if not args.no_page:
                    synth = st.py(SYNTH, json.dumps(BIG))
                    page = st.time_results_page(synth["job_id"])
                    print(
                        f"  {synth['cells']:,} stored cells (stored in {synth['store_seconds']:.1f} s): "
                        f"filtered page median {page['median_ms']:.1f} ms, "
                        f"p95 {page['p95_ms']:.1f} ms ({page['items']} of {page['matched']} "
                        f"matches); unfiltered first page {page['unfiltered_ms']:.1f} ms",
                        flush=True,
                    )
                    row["page"] = page
                rows.append(row)
                breakdown = unit_breakdown(root / "logs")
                if breakdown:
                    print(
                        f"  per unit (mean of {breakdown['units']} units, worker log): "
                        + ", ".join(
                            f"{label} {breakdown[k] * 1000:.0f} ms"
                            for label, k in (
                                ("claim", "claim_s"),
                                ("compute", "compute_s"),
                                ("store", "store_s"),
                                ("whole task", "task_s"),
                            )
                            if k in breakdown
                        ),
                        flush=True,
                    )
                    if breakdown.get("compute_s"):
                        share = (breakdown["claim_s"] + breakdown["store_s"]) / breakdown[
                            "compute_s"
                        ]
                        print(
                            f"  claim + store = {100 * share:.0f} % of compute (target 25 %)",
                            flush=True,
                        )
                        row["claim_store_share"] = share
                    row["per_unit_ms"] = {
                        k: round(v * 1000, 1) for k, v in breakdown.items() if k != "units"
                    }
                else:
                    print("  per unit: no 'succeeded' lines in the worker log", flush=True)
        finally:
            if args.keep:
                print(f"  logs kept in {root}/logs")
            else:
                shutil.rmtree(root, ignore_errors=True)
    print(
        json.dumps(
            {
                "in_process_seconds": base,
                "in_process_2_seconds": base2,
                "in_process_cpu_seconds": base_cpu,
                "cells": n,
                "stacks": rows,
            },
            indent=1,
        )
    )


if __name__ == "__main__":
    main()
