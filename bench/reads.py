"""Bounded reads: report and compare of a 625,050-cell job.

    .venv/bin/python bench/reads.py                       # SQLite and PostgreSQL
    .venv/bin/python bench/reads.py --stacks sqlite --cells 100000

For each database it stores one synthetic job of ``--cells`` result rows (the
paper's full preset has 625,050) through the real write path
(``bench/load.py``'s ``prepare``: ``units.start_unit`` + ``units.complete_unit``,
as a worker does; records with every field, random values), starts ``uvicorn service.app:app`` (one
process, loopback), then measures

* the first ``GET /jobs/{id}/report`` (it builds the report from the rows read
  as columns and stores it): target < 2 s;
* four concurrent report requests (served as stored): target each < 2 s;
* twenty stored report requests one after the other: target median < 50 ms;
* four concurrent ``GET /compare`` by every summary field (from the stored
  summaries) and four by ``...,rep`` (aggregated over the rows in the
  database, one page of 1,000 groups): target each < 2 s;
* ``GET /jobs`` (spec summaries) body size;

and the API process's resident memory from ``/proc/<pid>/status`` (VmRSS, the
current value, and VmHWM, its peak): target < 500 MB. PostgreSQL: a database
``svrobs_bench_reads`` on ``--pg`` (dropped at the end).
"""

from __future__ import annotations

import argparse
import asyncio
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

import httpx  # noqa: E402

from bench.api_server import (  # noqa: E402
    API,
    HOST,
    free_port,
    start_server,
    stop_server,
    wait_ready,
)
from bench.load import prepare  # noqa: E402

PAPER_CELLS = 625_050
TARGET_FIRST_S = 2.0  # the first report of a job, built from its rows
TARGET_S = 2.0
TARGET_STORED_S = 0.050  # one stored report, requested alone
TARGET_MB = 500.0
PG_DB = "svrobs_bench_reads"


def bench_spec(cells: int) -> dict:
    """2 systems x 3 sigma_w x 45 N x (ols + svr at 4 gammas) x reps; 463 reps = 625,050."""
    reps = max(1, round(cells / (2 * 3 * 45 * 5)))
    return {
        "systems": ["paper-stable", "paper-unstable"],
        "sigma_w": [0.1, 1.0, 10.0],
        "N": {"start": 10, "stop": 450, "step": 10},
        "reps": reps,
        "gamma": [0.005, 0.01, 0.05, 0.1],
        "estimators": ["ols", "svr"],
        "stages": ["estimate", "bounds"],
        "seed": 2,
    }


def load_job(db_url: str, spec_dict: dict) -> tuple[str, int, int, float]:
    """Migrate, make a team and key, store the job -> (key, job id, rows, seconds)."""
    t0 = time.perf_counter()
    key, job_id, rows = prepare(db_url, spec_dict, team_name="reads", max_cells=10**8)
    return key, job_id, rows, time.perf_counter() - t0


def rss_mb(pid: int) -> tuple[float, float]:
    """(VmRSS, VmHWM) of a process in MB."""
    out = {}
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        k, _, v = line.partition(":")
        if k in ("VmRSS", "VmHWM"):
            out[k] = int(v.split()[0]) / 1024
    return out["VmRSS"], out["VmHWM"]


async def timed_get(client: httpx.AsyncClient, url: str, params=None) -> tuple[float, int, int]:
    t0 = time.perf_counter()
    r = await client.get(url, params=params)
    return time.perf_counter() - t0, r.status_code, len(r.content)


async def concurrent(base: str, key: str, url: str, params=None, n: int = 4):
    headers = {"Authorization": f"Bearer {key}"}
    async with httpx.AsyncClient(base_url=base, headers=headers, timeout=600) as c:
        return await asyncio.gather(*(timed_get(c, url, params) for _ in range(n)))


def show(label: str, results, pid: int) -> bool:
    times = [t for t, _, _ in results]
    codes = {c for _, c, _ in results}
    size = max(b for _, _, b in results)
    now, peak = rss_mb(pid)
    ok = codes == {200} and max(times) < TARGET_S and peak < TARGET_MB
    print(
        f"  {label:<34} {len(times)} x: max {max(times):7.3f} s  codes {sorted(codes)}  "
        f"{size / 1e3:9.1f} kB  API RSS {now:6.1f} MB (peak {peak:6.1f})  "
        f"{'ok' if ok else 'MISSES target'}"
    )
    return ok


def show_one_by_one(label: str, base: str, key: str, url: str, n: int = 20) -> bool:
    """``n`` requests one after the other on one connection: median and slowest
    against the stored report's target (TARGET_STORED_S)."""
    headers = {"Authorization": f"Bearer {key}"}
    times = []
    with httpx.Client(base_url=base, headers=headers, timeout=60) as c:
        for _ in range(n):
            t0 = time.perf_counter()
            r = c.get(url)
            times.append(time.perf_counter() - t0)
            if r.status_code != 200:
                print(f"  {label:<34} code {r.status_code}  MISSES target")
                return False
    times.sort()
    med = times[n // 2]
    ok = med < TARGET_STORED_S
    print(
        f"  {label:<34} {n} x: median {med * 1e3:6.1f} ms, max {times[-1] * 1e3:6.1f} ms  "
        f"{len(r.content) / 1e3:9.1f} kB  {'ok' if ok else 'MISSES target'} "
        f"(median < {TARGET_STORED_S * 1e3:.0f} ms)"
    )
    return ok


def run_stack(name: str, db_url: str, cells: int, tmp: Path) -> bool:
    spec = bench_spec(cells)
    key, job_id, rows, load_s = load_job(db_url, spec)
    print(f"{name}: job {job_id} with {rows:,} rows stored through complete_unit in {load_s:.1f} s")
    port = free_port()
    base = f"http://{HOST}:{port}"
    proc = start_server(tmp, db_url, port)
    ok = True
    try:
        wait_ready(base, proc)
        pid = proc.pid
        print(f"  API process {pid}: RSS at start {rss_mb(pid)[0]:.1f} MB")
        report = f"{API}/jobs/{job_id}/report"
        first = asyncio.run(concurrent(base, key, report, n=1))
        now, peak = rss_mb(pid)
        fast = first[0][0] < TARGET_FIRST_S
        print(
            f"  {'first report (build + store)':<34} 1 x: {first[0][0]:7.3f} s  codes "
            f"[{first[0][1]}]  {first[0][2] / 1e3:9.1f} kB  API RSS {now:6.1f} MB "
            f"(peak {peak:6.1f}){'' if peak < TARGET_MB else '  MISSES the memory target'}"
            f"  {'ok' if fast else 'MISSES target'} (< {TARGET_FIRST_S:.0f} s)"
        )
        ok &= first[0][1] == 200 and peak < TARGET_MB and fast
        ok &= show("report (stored)", asyncio.run(concurrent(base, key, report)), pid)
        ok &= show_one_by_one("report (stored), one at a time", base, key, report)
        by_group = {"jobs": job_id, "metric": "rmse_A", "by": "system,sigma_w,N,estimator,gamma"}
        ok &= show(
            "compare by group (summaries)",
            asyncio.run(concurrent(base, key, f"{API}/compare", by_group)),
            pid,
        )
        by_rep = {**by_group, "by": by_group["by"] + ",rep", "limit": 1000}
        ok &= show(
            "compare by rep (rows, page 1,000)",
            asyncio.run(concurrent(base, key, f"{API}/compare", by_rep)),
            pid,
        )
        listed = asyncio.run(concurrent(base, key, f"{API}/jobs", {"limit": 500}, n=1))
        print(f"  GET /jobs: {listed[0][2]:,} bytes for 1 job ({listed[0][0] * 1e3:.1f} ms)")
    finally:
        stop_server(proc)
    return ok


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--stacks", default="sqlite,pg", help="sqlite, pg or both")
    ap.add_argument("--cells", type=int, default=PAPER_CELLS)
    ap.add_argument("--pg", default="postgresql+psycopg://postgres@127.0.0.1:5432/postgres")
    args = ap.parse_args(argv)
    ok = True
    for stack in args.stacks.split(","):
        with tempfile.TemporaryDirectory(prefix="svrobs-reads-") as d:
            tmp = Path(d)
            if stack == "sqlite":
                ok &= run_stack("SQLite", f"sqlite:///{tmp / 'svrobs.db'}", args.cells, tmp)
            elif stack == "pg":
                from sqlalchemy import create_engine, text
                from sqlalchemy.engine import make_url

                admin = create_engine(args.pg, isolation_level="AUTOCOMMIT")
                with admin.connect() as c:
                    c.execute(text(f'DROP DATABASE IF EXISTS "{PG_DB}" WITH (FORCE)'))
                    c.execute(text(f'CREATE DATABASE "{PG_DB}"'))
                url = make_url(args.pg).set(database=PG_DB).render_as_string(hide_password=False)
                try:
                    ok &= run_stack("PostgreSQL", url, args.cells, tmp)
                finally:
                    from service.db.session import dispose_all

                    dispose_all()
                    with admin.connect() as c:
                        c.execute(text(f'DROP DATABASE IF EXISTS "{PG_DB}" WITH (FORCE)'))
                    admin.dispose()
            else:
                ap.error(f"unknown stack {stack!r}")
    print("all targets met" if ok else "some targets missed")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
