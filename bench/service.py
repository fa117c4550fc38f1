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
import secrets
import shutil
import socket
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from urllib.parse import urlsplit, urlunsplit

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

import httpx

from svrobs_cli.processes import Child, stop_all
from svrobs_cli.serve import DEFAULT_CONCURRENCY, api_command, child_env, worker_command

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

SETUP = """
import json
from service.config import get_settings
from svrobs_cli.serve import prepare_dirs, migrate
from service.db.session import session_scope
from service.db import accounts
s = get_settings(); prepare_dirs(s); migrate(s)
with session_scope(s.DATABASE_URL) as db:
    accounts.create_team(db, 'bench')
    accounts.create_user(db, 'bench', 'bench@lab.example')
    _, key = accounts.create_key(db, 'bench@lab.example')
print(json.dumps({'key': key}))
"""

# A synthetic 100k-cell job: records stored by upsert_results (the write path)
# in batches, then every unit completed through complete_unit (which marks
# the job succeeded and writes its summaries), so the API sees a normal job.
SYNTH = """
import json, sys, time
import numpy as np
from service.db.jobs import create_job
from service.db.results_store import upsert_results
from service.db.units import complete_unit
from service.config import get_settings
from service.db.models import Team, WorkUnit
from service.db.session import session_scope
from sqlalchemy import select
from svrobs_core import parse_spec
from svrobs_core.records import empty_record

url = get_settings().DATABASE_URL
spec_obj = json.loads(sys.argv[1])
spec = parse_spec(spec_obj)
rng = np.random.default_rng(0)
with session_scope(url) as s:
    team = s.scalar(select(Team).where(Team.name == 'bench'))
    job, _ = create_job(s, team_id=team.id, user_id=None, spec=spec_obj, name='synthetic-100k',
                          max_cells=10**7, max_active_jobs=0)
    job_id = job.id
    units = s.execute(select(WorkUnit.id, WorkUnit.payload).where(WorkUnit.job_id == job_id)
                      .order_by(WorkUnit.index)).all()
t0 = time.perf_counter()
axis = [('ols', None)] + [('svr', g) for g in spec.gamma]
rows = []
for uid, p in units:
    system = spec.systems[p['system']]
    for N in p['N']:
        for rep in range(*p['reps']):
            for est, g in axis:
                r = empty_record()
                r.update(system=system.name, sigma_w=spec.sigma_w[p['sigma_w']], N=N, N0=N,
                         estimator=est, gamma=g, rep=rep, seed_key=[p['system'], p['sigma_w'], N, rep],
                         A_hat=rng.standard_normal((system.n, system.n)).tolist(),
                         B_hat=rng.standard_normal((system.n, system.m)).tolist())
                for f in ('rmse_A', 'rmse_B', 'H_A', 'H_B', 'r_A', 'r_B', 'eps_A', 'eps_B',
                          'rho_upper_bound'):
                    r[f] = float(rng.random())
                r['coverage_A'] = r['coverage_B'] = 1.0
                r['thm1_holds_A'] = r['thm1_holds_B'] = True
                r['stable_certified'] = bool(rng.random() < 0.5)
                rows.append(r)
for i in range(0, len(rows), 5000):
    with session_scope(url) as s:
        upsert_results(s, job_id, rows[i:i + 5000])
for uid, _ in units:
    with session_scope(url) as s:
        complete_unit(s, uid, [])
print(json.dumps({'job_id': job_id, 'cells': len(rows), 'store_seconds': time.perf_counter() - t0}))
"""


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class BenchStack:
    def __init__(
        self,
        kind: str,
        root: Path,
        workers: int,
        concurrency: int,
        pg_url: str | None = None,
        redis_url: str | None = None,
    ):
        self.kind, self.root, self.workers, self.concurrency = kind, root, workers, concurrency
        self.pg_url, self.redis_url = pg_url, redis_url
        self.schema = None
        self.children: list[Child] = []
        env = {k: v for k, v in os.environ.items() if not k.startswith("SVROBS_")}
        if kind == "embedded":
            env.update(
                SVROBS_DATABASE_URL=f"sqlite:///{root / 'svrobs.db'}",
                SVROBS_BROKER_URL="filesystem://",
                SVROBS_BROKER_DIR=str(root / "broker"),
            )
        else:
            self.schema = f"bench_{secrets.token_hex(4)}"
            parts = urlsplit(pg_url)
            q = (
                parts.query
                + ("&" if parts.query else "")
                + f"options=-csearch_path%3D{self.schema}"
            )
            env.update(
                SVROBS_DATABASE_URL=urlunsplit(parts._replace(query=q)),
                SVROBS_BROKER_URL=redis_url,
                SVROBS_BROKER_DIR=str(root / "broker"),
            )
        env.update(SVROBS_RATE_LIMIT_PER_MINUTE="100000", SVROBS_MAX_JOB_CELLS="10000000")
        env.update(SVROBS_VAR_DIR=str(root))
        self.env = child_env(None, env)
        self.url = ""
        self.key = ""

    def py(self, code: str, *args: str, timeout: float = 900) -> dict:
        out = subprocess.run(
            [sys.executable, "-c", code, *args],
            cwd=str(ROOT),
            env=self.env,
            capture_output=True,
            text=True,
            timeout=timeout,
            check=False,
        )
        if out.returncode:
            raise RuntimeError(out.stderr[-3000:])
        return json.loads(out.stdout.strip().splitlines()[-1])

    def _pg_reset(self, sql: str) -> None:
        """Run ``sql`` on the PostgreSQL server, then empty the Redis database."""
        import redis
        import sqlalchemy as sa

        eng = sa.create_engine(self.pg_url)
        with eng.begin() as c:
            c.exec_driver_sql(sql)
        eng.dispose()
        redis.Redis.from_url(self.redis_url).flushdb()

    def __enter__(self):
        if self.kind == "pg":
            self._pg_reset(f'CREATE SCHEMA "{self.schema}"')
        self.key = self.py(SETUP)["key"]
        port = free_port()
        logs = self.root / "logs"
        logs.mkdir(parents=True, exist_ok=True)
        self.children.append(
            Child("api", api_command("127.0.0.1", port), self.env, log=logs / "api.log").start()
        )
        for i in range(self.workers):
            name = f"worker{i + 1}"
            self.children.append(
                Child(
                    name, worker_command(name, self.concurrency), self.env, log=logs / f"{name}.log"
                ).start()
            )
        self.url = f"http://127.0.0.1:{port}"
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline:
            try:
                if httpx.get(self.url + "/readyz", timeout=2).status_code == 200:
                    break
            except httpx.HTTPError:
                pass
            time.sleep(0.3)
        else:
            raise RuntimeError("API not ready")
        for i in range(self.workers):  # wait for every worker to be consuming
            log = logs / f"worker{i + 1}.log"
            while "ready." not in (log.read_text() if log.exists() else ""):
                if time.monotonic() > deadline:
                    raise RuntimeError(f"worker{i + 1} not ready")
                time.sleep(0.2)
        return self

    def __exit__(self, *exc):
        stop_all(self.children, grace=10)
        if self.kind == "pg":
            self._pg_reset(f'DROP SCHEMA IF EXISTS "{self.schema}" CASCADE')

    def client(self) -> httpx.Client:
        return httpx.Client(
            base_url=self.url + "/api/v1",
            timeout=60,
            headers={"Authorization": f"Bearer {self.key}"},
        )

    def run_job(self, spec: dict) -> tuple[float, dict]:
        with self.client() as c:
            t0 = time.perf_counter()
            r = c.post("/jobs", json=spec)
            r.raise_for_status()
            job_id = r.json()["id"]
            while True:
                job = c.get(f"/jobs/{job_id}").json()
                if job["status"] in ("succeeded", "failed", "cancelled"):
                    break
                time.sleep(0.2)
            elapsed = time.perf_counter() - t0
        if job["status"] != "succeeded":
            raise RuntimeError(f"job {job_id} {job['status']}: {job.get('error')}")
        return elapsed, job

    def time_results_page(self, job_id: int, n: int = 30) -> dict:
        params = {"N": 100, "estimator": "svr", "gamma": "0.05", "sigma_w": 1.0, "limit": 100}
        times = []
        with self.client() as c:
            for i in range(n + 3):
                t0 = time.perf_counter()
                r = c.get(f"/jobs/{job_id}/results", params={**params, "offset": (i % 2) * 100})
                dt = time.perf_counter() - t0
                r.raise_for_status()
                body = r.json()
                if i >= 3:
                    times.append(dt)
            # the unfiltered first page too
            t0 = time.perf_counter()
            c.get(f"/jobs/{job_id}/results", params={"limit": 100}).raise_for_status()
            unfiltered = time.perf_counter() - t0
        times.sort()
        return {
            "median_ms": 1000 * statistics.median(times),
            "p95_ms": 1000 * times[int(0.95 * (len(times) - 1))],
            "matched": body["total"],
            "items": len(body["items"]),
            "unfiltered_ms": 1000 * unfiltered,
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
