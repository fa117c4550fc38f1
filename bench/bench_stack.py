"""A real stack for the benches: the API and worker processes exactly as ``svrobs serve``
starts them, on the embedded back end (SQLite + filesystem broker) or on PostgreSQL +
Redis, with a team and an API key made in it (``bench/service.py``)."""

from __future__ import annotations

import json
import os
import secrets
import socket
import statistics
import subprocess
import sys
import time
from pathlib import Path
from urllib.parse import urlsplit, urlunsplit

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

import httpx  # noqa: E402

from svrobs_cli.processes import Child, stop_all  # noqa: E402
from svrobs_cli.serve import api_command, child_env, worker_command  # noqa: E402

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
