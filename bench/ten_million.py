"""Ten million cells in PostgreSQL: size per cell and the read paths' latencies.

    python bench/ten_million.py                    # 10^7 cells (about 6 GB; minutes)
    python bench/ten_million.py --cells 1000000    # a quick check

Into a private database it creates and drops (on the server of
``SVROBS_BENCH_DATABASE_URL``, else ``SVROBS_TEST_DATABASE_URL``; never the
database of that URL itself), migrated to head, it loads a realistic mix of
jobs: 50 jobs of log-normally spread sizes over the paper's systems,
sigma_w {0.1, 1, 10}, N on 10..450, ols and svr at one to four gammas, stages
estimate + bounds or the whole observer pipeline (matrices L and K, the cost
fields, the Monte Carlo J for rep < 10 and its note). Result rows are written
with COPY in the stored format (random values; real rows of the same shape),
each job's summaries likewise, then ``VACUUM ANALYZE``. It prints

* the database size per cell and the ``results`` table's (heap / indexes);
* a filtered results page through the API (the app in process, a TestClient with
  an API key: ``GET /jobs/{id}/results?N=..&estimator=svr&gamma=..&limit=100`` of
  the biggest job; target < 100 ms);
* compare across five jobs (``GET /compare?jobs=..&metric=rmse_A``; < 300 ms), and
  the same ``by=N,N0`` (not a summary grouping: aggregated over the cell rows);
* a dashboard chart's data (what the dashboard's ``GET /jobs/{id}/chart-data``
  computes, from the stored summaries: rmse_A against N of the biggest job;
  < 300 ms);

each the median and p95 of 5-20 calls after a warm-up call.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

import numpy as np
from fastapi.testclient import TestClient
from sqlalchemy import create_engine, text
from sqlalchemy.orm import Session

from bench.pg_private import bench_pg_url, private_database
from service.app import create_app
from service.config import Settings
from service.db import accounts
from service.db.jobs import create_job
from service.db.migrate import upgrade
from service.db.models import OLS_GAMMA_KEY
from service.db.results_store import note_ids
from service.db.session import get_engine
from service.web import charts
from svrobs_core.parsing import parse_spec
from svrobs_core.records import SUMMARY_FIELDS

SYSTEMS = ["paper-stable", "paper-unstable"]
GAMMAS = [0.005, 0.01, 0.05, 0.1]
FULL = ["estimate", "bounds", "gain", "cost"]
NOTE_MC = "stages not run: cost_bound, sls; J_mc: only computed for rep < mc_reps = 10"
NOTE_EB = "stages not run: gain, cost, cost_bound, sls"
BOUND_FLOATS = ["rmse_A", "rmse_B", "H_A", "H_B", "r_A", "r_B", "eps_A", "eps_B"]
BOUND_FLOATS += ["coverage_A", "coverage_B", "rho_upper_bound"]
GAIN_FLOATS = ["g_L", "rho_true", "J_exact", "J_stationary", "J_star", "cost_ratio"]
MC = ["J_mc", "J_mc_se"]
BOOLS = ["thm1_holds_A", "thm1_holds_B", "stable_certified", "certified"]
PAYLOAD = BOUND_FLOATS + GAIN_FLOATS + MC + BOOLS + ["seed_key", "A_hat", "B_hat", "L", "K"]
PAYLOAD += ["bounds_method", "radii_A", "radii_B"]
KEYS = ["job_id", "system", "sigma_w", "N", "estimator", "gamma_key", "rep", "gamma", "N0"]
COPY_COLUMNS = KEYS + ["notes_id"] + PAYLOAD
POOL = 4096
NULL = "\\N"  # COPY text format


def job_mix(total: int, n_jobs: int, rng) -> list[dict]:
    """``n_jobs`` specs whose cells sum to about ``total`` (sizes log-normal)."""
    weights = rng.lognormal(0.0, 1.0, n_jobs)
    specs = []
    for j, w in enumerate(weights / weights.sum()):
        kind = j % 3
        est = ["ols", "svr"] if kind < 2 else ["svr"]
        gam = GAMMAS[:1] if kind == 0 else GAMMAS
        spec = {
            "systems": SYSTEMS if j % 4 else SYSTEMS[:1],
            "sigma_w": [0.1, 1.0, 10.0] if kind < 2 else [1.0],
            "N": {"start": 10, "stop": 450, "step": 10 if j % 2 else 40},
            "gamma": gam,
            "estimators": est,
            "stages": FULL if kind != 1 else ["estimate", "bounds"],
            "mc_reps": 10,
            "seed": j,
        }
        per_rep = parse_spec({**spec, "reps": 1}).n_cells
        spec["reps"] = max(1, round(w * total / per_rep))
        specs.append(spec)
    return specs


def _f(x: float) -> str:
    return repr(float(x))


def _hex(a: np.ndarray) -> str:
    return "\\\\x" + a.astype("<f8").tobytes().hex()


def payload_pool(full: bool, rng) -> list[str]:
    """POOL pre-rendered COPY tails (payload columns) of one stage set."""
    out = []
    for _ in range(POOL):
        vals = [_f(rng.random()) for _ in BOUND_FLOATS[:8]]
        vals += ["1.0", "1.0", _f(1 + rng.random())]
        if full:
            vals += [_f(rng.random()) for _ in GAIN_FLOATS] + ["%s", "%s"]
        else:
            vals += ["\\N"] * (len(GAIN_FLOATS) + 2)
        vals += ["t", "t", "f", ("f" if full else "\\N")]
        vals += ["\\N", _hex(rng.standard_normal(9)), _hex(rng.standard_normal(3))]
        if full:  # L, and K as stored: once per (system, sigma_w) in result_constants
            vals += [_hex(rng.standard_normal(9)), "\\\\x"]
        else:
            vals += ["\\N", "\\N"]
        # the paper's bounds: each radius matrix is its row's r_A / r_B, stored as
        # zero bytes (migration 0007)
        vals += ["paper", "\\\\x", "\\\\x"]
        out.append("\t".join(vals))
    return out


def summary_json(rng, reps: int) -> str:
    stats = {
        f: {"mean": float(rng.random()), "std": float(rng.random()), "count": reps}
        for f in SUMMARY_FIELDS
    }
    return json.dumps(stats).replace("\\", "\\\\")


def load_job(conn, job_id: int, spec: dict, pools: dict, notes: dict, rng) -> int:
    """COPY one job's result rows and summaries; returns its cells."""
    s = parse_spec(spec)
    full = "gain" in s.stages
    pool = pools[full]
    axis = [(e, None) for e in s.estimators if e == "ols"]
    axis += [(e, g) for e in s.estimators if e != "ols" for g in s.gamma]
    cur = conn.connection.driver_connection.cursor()
    n = 0
    cols = ", ".join(f'"{c}"' for c in COPY_COLUMNS)
    with cur.copy(f"COPY results ({cols}) FROM STDIN") as cp:
        for system in s.systems:
            for sigma in s.sigma_w:
                for N in s.N:
                    for est, g in axis:
                        gk = OLS_GAMMA_KEY if g is None else g
                        head = f"{job_id}\t{system.name}\t{_f(sigma)}\t{N}\t{est}\t{_f(gk)}\t"
                        gs = NULL if g is None else _f(g)
                        mid = f"\t{gs}\t{(s.T0 - 1) * N}\t"
                        start = int(rng.integers(POOL))
                        lines = []
                        for rep in range(s.reps):
                            tail = pool[(start + rep) % POOL]
                            if full:
                                mc = rep < 10
                                note = notes[NOTE_MC] if not mc else "\\N"
                                tail = tail % ((_f(0.05), _f(0.001)) if mc else ("\\N", "\\N"))
                            else:
                                note = notes[NOTE_EB]
                            lines.append(f"{head}{rep}{mid}{note}\t{tail}\n")
                        cp.write("".join(lines))
                        n += s.reps
    if full:
        with cur.copy(
            "COPY result_constants (job_id, system, sigma_w, field, value) FROM STDIN"
        ) as cp:
            for system in s.systems:
                for sigma in s.sigma_w:
                    k = _hex(rng.standard_normal(9))
                    cp.write(f"{job_id}\t{system.name}\t{_f(sigma)}\tK\t{k}\n")
    with cur.copy(
        'COPY summaries (job_id, system, sigma_w, "N", estimator, gamma, gamma_key, count, '
        "stats) FROM STDIN"
    ) as cp:
        for system in s.systems:
            for sigma in s.sigma_w:
                for N in s.N:
                    for est, g in axis:
                        gk = OLS_GAMMA_KEY if g is None else g
                        gs = "\\N" if g is None else _f(g)
                        cp.write(
                            f"{job_id}\t{system.name}\t{_f(sigma)}\t{N}\t{est}\t{gs}\t{_f(gk)}"
                            f"\t{s.reps}\t{summary_json(rng, s.reps)}\n"
                        )
    return n


def timed(fn, runs: int = 20, warm: int = 3) -> tuple[float, float]:
    for _ in range(warm):
        fn()
    t = []
    for _ in range(runs):
        t0 = time.perf_counter()
        fn()
        t.append(time.perf_counter() - t0)
    t.sort()
    return statistics.median(t) * 1000, t[int(0.95 * (len(t) - 1))] * 1000


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--cells", type=int, default=10_000_000)
    ap.add_argument("--jobs", type=int, default=50)
    ap.add_argument("--keep", action="store_true", help="do not drop the database")
    args = ap.parse_args()
    base = bench_pg_url()
    if not base:
        sys.exit("set SVROBS_BENCH_DATABASE_URL (or SVROBS_TEST_DATABASE_URL) to a PostgreSQL URL")
    with private_database(base, "svrobs_tenm", keep=args.keep) as url:
        run(url, args)


def run(url: str, args) -> None:
    rng = np.random.default_rng(0)
    upgrade(url)
    engine = get_engine(url)
    specs = job_mix(args.cells, args.jobs, rng)
    pools = {True: payload_pool(True, rng), False: payload_pool(False, rng)}
    t0 = time.perf_counter()
    with Session(engine) as s, s.begin():
        team = accounts.create_team(s, "bench")
        user = accounts.create_user(s, team.id, "bench@lab.example")
        _, key = accounts.create_key(s, user.id)
        ids = []
        for spec in specs:
            job, _ = create_job(
                s, team_id=team.id, user_id=None, spec=spec, max_cells=10**8, max_active_jobs=0
            )
            ids.append(job.id)
        s.flush()
        s.execute(text("UPDATE jobs SET status = 'succeeded', n_cells = n_cells"))
        s.execute(text("UPDATE work_units SET status = 'done'"))
        notes = {t: str(i) for t, i in note_ids(s, [NOTE_MC, NOTE_EB]).items() if t}
    cells = 0
    for job_id, spec in zip(ids, specs):
        with engine.begin() as conn:
            cells += load_job(conn, job_id, spec, pools, notes, rng)
    print(f"loaded {cells:,} cells in {len(ids)} jobs by COPY in {time.perf_counter() - t0:.0f} s")
    with create_engine(url, isolation_level="AUTOCOMMIT").connect() as c:
        t1 = time.perf_counter()
        c.exec_driver_sql("VACUUM ANALYZE")
        print(f"VACUUM ANALYZE {time.perf_counter() - t1:.0f} s")
        db = c.scalar(text("SELECT pg_database_size(current_database())"))
        heap = c.scalar(text("SELECT pg_table_size('results')"))
        idx = c.scalar(text("SELECT pg_indexes_size('results')"))
        summ = c.scalar(text("SELECT pg_total_relation_size('summaries')"))
        heap += c.scalar(text("SELECT pg_total_relation_size('result_constants')"))
    print(
        f"database {db / 2**30:.2f} GiB = {db / cells:.0f} B/cell; results: heap "
        f"{heap / cells:.0f} + indexes {idx / cells:.0f} B/cell; summaries {summ / cells:.1f} B/cell"
    )
    sizes = [parse_spec(sp).n_cells for sp in specs]
    biggest = int(np.argmax(sizes))
    big, big_spec = ids[biggest], specs[biggest]
    app = create_app(
        Settings(DATABASE_URL=url, BROKER_URL="memory://", RATE_LIMIT_PER_MINUTE=10**7)
    )
    app.state.broker_check = lambda: None
    client = TestClient(app)
    headers = {"Authorization": f"Bearer {key}"}

    def get(path, **params):
        r = client.get(f"/api/v1{path}", params=params, headers=headers)
        assert r.status_code == 200, (path, r.status_code, r.text[:300])
        return r

    n_page = big_spec["N"]["start"] + 4 * big_spec["N"]["step"]
    gamma = str(big_spec["gamma"][-1])

    def page():
        return get(f"/jobs/{big}/results", N=n_page, estimator="svr", gamma=gamma, limit=100)

    # five jobs of one grid kind (the same estimators/gammas), the biggest ones
    kind = [i for i in range(len(specs)) if i % 3 == biggest % 3]
    five = [ids[i] for i in sorted(kind, key=lambda i: -sizes[i])[:5]]
    five_cells = sum(sizes[ids.index(j)] for j in five)

    def compare():
        return get("/compare", jobs=",".join(map(str, five)), metric="rmse_A")

    def compare_cells():  # finer than the summaries: aggregated over the cell rows
        return get("/compare", jobs=",".join(map(str, five)), metric="rmse_A", by="N,N0", limit=100)

    def chart():  # the body of the dashboard's GET /jobs/{id}/chart-data (service.web)
        with Session(engine) as s:
            groups = charts.stored_groups(s, big, "rmse_A")
            data = charts.chart_data(groups, metric="rmse_A", x="N")
            data.update(groups=len(groups), metrics=charts.stored_metrics(s, big))
            return json.dumps(data)

    items = len(page().json()["items"])
    print(f"results page of job {big} ({max(sizes):,} cells): {items} items")
    for label, fn, target, runs in (
        ("filtered results page", page, 100, 20),
        (f"compare across 5 jobs ({five_cells:,} cells)", compare, 300, 5),
        ("  the same by N, N0 (from the cell rows, in the database)", compare_cells, 300, 3),
        ("dashboard chart data (rmse_A vs N of the biggest job)", chart, 300, 10),
    ):
        med, p95 = timed(fn, runs=runs, warm=1)
        print(f"{label:<60} median {med:8.1f} ms  p95 {p95:8.1f} ms  (target < {target} ms)")


if __name__ == "__main__":
    main()
