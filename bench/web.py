"""Web UI pages and chart data for a job of 625,050 cells (target: < 300 ms each).

    .venv/bin/python bench/web.py                       # SQLite in a temporary folder
    .venv/bin/python bench/web.py --database-url postgresql+psycopg://postgres@127.0.0.1/bench

The job is the paper's Section 6 grid of E2 (2 systems x sigma_w {0.1, 1, 10} x N
10..450 step 10 x {ols, svr gamma in {0.005, 0.01, 0.05, 0.1}}) with 463 repetitions:
1350 x 463 = 625,050 cells, the size of the paper's full preset (E1-E4). Its result
rows are bulk-inserted with synthetic values, then every unit is completed through
``service.db.units.complete_unit`` (which marks the job succeeded and stores its
summaries), so the pages see a normal finished job. Each page is requested in
process (TestClient, signed in through the login form) 5 times to warm up, then 20
times; the median and the maximum wall time are printed (an upper bound on server
time: the in-process client adds well under a millisecond).
"""

from __future__ import annotations

import argparse
import re
import statistics
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

import numpy as np
from fastapi.testclient import TestClient
from sqlalchemy import select

from service.app import create_app
from service.config import Settings
from service.db import accounts, jobs, units
from service.db.migrate import upgrade
from service.db.models import OLS_GAMMA_KEY, Result, WorkUnit
from service.db.session import session_scope
from svrobs_core.paper import paper_specs

# E2 of the full preset with 463 repetitions instead of 45: 1350 x 463 = 625,050 cells
GRID = {**paper_specs("full")["E2"], "reps": 463}
PAGES = [
    "/jobs",
    "/jobs/{id}",
    "/jobs/{id}/progress",
    "/jobs/{id}/tables",  # Table 2 and findings, loaded by the page
    "/jobs/{id}/chart-data?metric=rmse_A&x=N&metrics=1",  # the page's first load
    "/jobs/{id}/chart-data?metric=rmse_A&x=N",
    "/jobs/{id}/chart-data?metric=H_A&x=sigma_w",
    "/jobs/{id}/chart-data?metric=eps_A&x=gamma",
    "/jobs/{id}/chart-data?preset=fig_rmse/rmse_A",  # the report's figure series
    "/jobs/{id}/chart-data?preset=fig_coverage/coverage_A",
]
METRICS = ("rmse_A", "rmse_B", "H_A", "H_B", "eps_A", "eps_B", "r_A", "r_B")


def store_job(url: str) -> tuple[str, int, int]:
    """The key and id of a finished synthetic job of GRID, and its number of cells."""
    with session_scope(url) as s:
        accounts.create_team(s, "bench")
        accounts.create_user(s, "bench", "bench@lab.example")
        _, key = accounts.create_key(s, "bench@lab.example")
    with session_scope(url) as s:
        team = accounts.get_team(s, "bench")
        job, _ = jobs.create_job(
            s, team_id=team.id, user_id=None, spec=GRID, max_cells=10**7, max_active_jobs=0
        )
        job_id = job.id
        unit_ids = list(s.scalars(select(WorkUnit.id).where(WorkUnit.job_id == job_id)))
    rng = np.random.default_rng(0)
    axis = [("ols", None)] + [("svr", g) for g in GRID["gamma"]]
    n_values = range(GRID["N"]["start"], GRID["N"]["stop"] + 1, GRID["N"]["step"])
    cells = 0
    for system in GRID["systems"]:
        for sigma in GRID["sigma_w"]:
            rows = []
            for n in n_values:
                values = rng.random((GRID["reps"] * len(axis), len(METRICS))) / np.sqrt(n)
                k = 0
                for rep in range(GRID["reps"]):
                    for est, g in axis:
                        row = dict(zip(METRICS, values[k].tolist()))
                        k += 1
                        row.update(
                            job_id=job_id,
                            system=system,
                            sigma_w=sigma,
                            N=n,
                            N0=n - 10,
                            estimator=est,
                            gamma=g,
                            gamma_key=OLS_GAMMA_KEY if g is None else g,
                            rep=rep,
                        )
                        rows.append(row)
            with session_scope(url) as s:
                s.execute(Result.__table__.insert(), rows)
            cells += len(rows)
    for uid in unit_ids:
        with session_scope(url) as s:
            units.start_unit(s, uid, "bench", 60, max_attempts=0)
            units.complete_unit(s, uid, [])
    return key, job_id, cells


def time_pages(client: TestClient, job_id: int) -> list[tuple[str, float, float, int]]:
    out = []
    for page in PAGES:
        path = page.format(id=job_id)
        for _ in range(5):
            assert client.get(path).status_code == 200, path
        times = []
        for _ in range(20):
            t0 = time.perf_counter()
            r = client.get(path)
            times.append(time.perf_counter() - t0)
            assert r.status_code == 200, path
        out.append((path, statistics.median(times), max(times), len(r.content)))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--database-url", help="an empty database (default: SQLite in a temp dir)")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        url = args.database_url or f"sqlite:///{Path(tmp) / 'bench.db'}"
        upgrade(url)
        t0 = time.perf_counter()
        key, job_id, cells = store_job(url)
        print(
            f"stored job {job_id}: {cells:,} cells in {time.perf_counter() - t0:.1f} s ({url.split(':')[0]})"
        )
        settings = Settings(
            DATABASE_URL=url, BROKER_URL="memory://", VAR_DIR=tmp, RATE_LIMIT_PER_MINUTE=10**6
        )
        client = TestClient(create_app(settings))
        login = client.get("/login").text
        token = re.search(r'name="csrf_token" value="([^"]+)"', login).group(1)
        r = client.post("/login", data={"key": key, "csrf_token": token}, follow_redirects=False)
        assert r.status_code == 303, r.text
        print(f"{'page':<58} {'median ms':>10} {'max ms':>8} {'bytes':>9}")
        for path, med, worst, size in time_pages(client, job_id):
            flag = "" if worst < 0.3 else "  over 300 ms"
            print(f"{path:<58} {med * 1000:>10.1f} {worst * 1000:>8.1f} {size:>9,}{flag}")


if __name__ == "__main__":
    main()
