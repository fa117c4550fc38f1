"""Several hosts: the API (with beat) and two workers, each in its
own network namespace with its own hostname, working folder and HOME, against a
PostgreSQL and a Redis this test starts on this machine's ends of the veth pairs.
Nothing is shared but the two servers: no filesystem (each host's folders are
its own), no local clock (leases, publication times and the broker epoch are
the servers'). A sweep completes with records identical to the core run in
this process (what ``svrobs run-local`` writes), both workers ran units, and
the report beat stored in the database is what the API serves. A job on an
uploaded dataset runs too: the workers read its arrays from the database alone,
and its records and validation equal the core's on the same arrays.

Skipped, saying why, without root or ``ip netns``, PostgreSQL's binaries or
redis-server."""

from __future__ import annotations

import json
import os
import time
from pathlib import Path

import httpx
import pytest
from sqlalchemy import select

from svrobs_cli.processes import Child, stop_all
from svrobs_cli.serve import api_command, beat_command, child_env, worker_command
from svrobs_core import parse_spec
from svrobs_core.measured import MeasuredData, run_measured_unit
from svrobs_lab.validation import summarize
from tests.datasets import files
from tests.integration.servers import PG_BINDIR, REDIS_SERVER, PrivatePostgres, PrivateRedis
from tests.integration.stack import cell_key, fetch_jsonl, in_process_records, same
from tests.multihost import netns

API_PORT = 8000
SPEC = {
    "systems": ["paper-stable", "paper-unstable"],
    "sigma_w": [0.25, 0.5, 1.0, 2.0],
    "N": [40, 80, 120],
    "reps": 12,
    "gamma": [0.05, 0.1],
    "estimators": ["ols", "svr"],
    "stages": ["estimate", "bounds"],
    "seed": 13,
}
WAIT = 45.0
DATASET_SPEC = {"N": [4, 8, 12], "holdout": 3, "reps": 400, "gamma": [0.05], "seed": 5}

_why = netns.unavailable()
pytestmark = pytest.mark.skipif(
    _why is not None or PG_BINDIR is None or REDIS_SERVER is None,
    reason=_why or "needs PostgreSQL's initdb/postgres and redis-server",
)


def _wait(pred, timeout: float, what: str, logs=()):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        try:
            if pred():
                return
        except Exception:  # noqa: BLE001 - retried until the deadline
            pass
        time.sleep(0.2)
    tails = "\n".join(f"--- {p} ---\n{p.read_text(errors='replace')[-3000:]}" for p in logs)
    raise AssertionError(f"{what} not reached in {timeout}s\n{tails}")


def _run_job(c: httpx.Client, spec: dict, logs) -> int:
    """Submit ``spec``, wait until the job finished, check it succeeded -> its id."""
    r = c.post("/jobs", json=spec)
    assert r.status_code == 202, r.text
    jid, state = r.json()["id"], {}

    def finished():
        state.update(c.get(f"/jobs/{jid}").json())
        return state["status"] in ("succeeded", "failed", "cancelled")

    _wait(finished, WAIT, f"job {jid} finished", logs)
    assert state["status"] == "succeeded", state
    return jid


def _host_env(folder: Path, gateway: str, pg_port: int, redis_port: int) -> dict:
    base = {k: v for k, v in os.environ.items() if not k.startswith("SVROBS_")}
    env = child_env(None, base)
    for k in [k for k in env if k.startswith("SVROBS_")]:
        del env[k]
    env.update(
        HOME=str(folder / "home"),
        SVROBS_DATABASE_URL=f"postgresql+psycopg://postgres@{gateway}:{pg_port}/postgres",
        SVROBS_BROKER_URL=f"redis://{gateway}:{redis_port}/0",
        SVROBS_VAR_DIR=str(folder / "var"),
        SVROBS_BROKER_DIR=str(folder / "var" / "broker"),
        SVROBS_TICK_SECONDS="1",
        SVROBS_TASK_TIME_LIMIT="300",
        SVROBS_UNIT_LEASE_SECONDS="360",
    )
    for d in ("home", "var"):
        (folder / d).mkdir(parents=True, exist_ok=True)
    return env


def test_api_and_two_workers_on_separate_hosts(tmp_path):
    hosts = netns.Hosts()
    children: list[Child] = []
    pg = redis = None
    try:
        api_host, w1, w2 = (hosts.add(label) for label in ("api", "w1", "w2"))
        gateways = tuple(h.gateway for h in hosts.hosts)
        pg = PrivatePostgres(listen=gateways)
        pg.init()
        with open(pg.data / "pg_hba.conf", "a") as f:  # the namespaces' addresses
            f.write(f"host all all {netns.SUBNET}0/24 trust\n")
        pg.start()
        redis = PrivateRedis(tmp_path / "redis", bind=gateways)
        redis.start()

        from service.db import accounts
        from service.db.migrate import upgrade
        from service.db.models import WorkUnit
        from service.db.session import dispose_all, session_scope

        upgrade(pg.url)
        with session_scope(pg.url) as s:
            accounts.create_team(s, "lab")
            accounts.create_user(s, "lab", "mh@lab.example")
            _, key = accounts.create_key(s, "mh@lab.example")
        dispose_all()

        def start(host, name: str, argv: list[str]) -> Path:
            folder = tmp_path / host.name
            env = _host_env(folder, host.gateway, pg.port, redis.port)
            log = folder / f"{name}.log"
            children.append(Child(name, host.wrap(argv), env, log=log, cwd=folder).start())
            return log

        api_log = start(api_host, "api", api_command(api_host.address, API_PORT))
        beat_log = start(api_host, "beat", beat_command(tmp_path / api_host.name / "beat-sched"))
        worker_logs = [
            start(h, f"worker{i}", worker_command(f"worker{i}", 1))
            for i, h in enumerate((w1, w2), start=1)
        ]
        logs = [api_log, beat_log, *worker_logs]
        base = f"http://{api_host.address}:{API_PORT}"
        _wait(lambda: httpx.get(f"{base}/readyz", timeout=2).status_code == 200, WAIT, "API", logs)
        for log in worker_logs:
            _wait(lambda p=log: "ready." in p.read_text(errors="replace"), WAIT, "worker", logs)

        headers = {"Authorization": f"Bearer {key}"}
        with httpx.Client(base_url=base + "/api/v1", headers=headers, timeout=30) as c:
            jid = _run_job(c, {**SPEC, "name": "multihost"}, logs)
            got = fetch_jsonl(c, jid)

        want = in_process_records(SPEC)
        assert len(got) == len(want)
        diffs = [m for r in got for m in same(r, want[cell_key(r)], str(cell_key(r)))]
        assert not diffs, diffs[:5]
        with session_scope(pg.url) as s:
            workers = set(s.scalars(select(WorkUnit.worker).where(WorkUnit.job_id == jid)))
        dispose_all()
        assert workers == {f"worker1@{w1.name}", f"worker2@{w2.name}"}, workers

        # beat stores the finished job's report in the database; the API serves it
        from service.db.models import JobReport

        def stored():
            with session_scope(pg.url) as s:
                return s.get(JobReport, jid) is not None

        _wait(stored, WAIT, "the report stored by beat", logs)
        with session_scope(pg.url) as s:
            html = s.get(JobReport, jid).html
        dispose_all()
        r = httpx.get(f"{base}/api/v1/jobs/{jid}/report", headers=headers, timeout=30)
        assert r.status_code == 200 and r.text == html

        # a job on a dataset: the workers read its arrays from the database alone
        X, U = files.rollouts(seed=31, lengths=(15,) * 16, n=2, m=1)
        with httpx.Client(base_url=base + "/api/v1", headers=headers, timeout=30) as c:
            r = c.post(
                "/datasets", files={"file": ("d.csv", files.csv_bytes(X, U))}, data={"name": "d"}
            )
            assert r.status_code == 201, r.text
            spec = {**DATASET_SPEC, "dataset": r.json()["id"]}
            did = _run_job(c, spec, logs)
            got = fetch_jsonl(c, did)
            validation = c.get(f"/jobs/{did}/validation")
        parsed = parse_spec(spec)
        unit = {"system": 0, "sigma_w": 0, "N": list(parsed.N), "reps": [0, parsed.reps]}
        data = MeasuredData(X=X, U=U)
        want = {
            cell_key(r): json.loads(json.dumps(r, allow_nan=False))
            for r in run_measured_unit(parsed, unit, data).records()
        }
        assert len(got) == len(want) == parsed.n_cells
        diffs = [m for r in got for m in same(r, want[cell_key(r)], str(cell_key(r)))]
        assert not diffs, diffs[:5]
        assert validation.status_code == 200, validation.text
        expected = json.loads(json.dumps(summarize(spec, data), allow_nan=False))
        assert {k: v for k, v in validation.json().items() if k not in ("job_id", "dataset")} == (
            expected
        )
    finally:
        stop_all(children, grace=5)
        hosts.close()
        if redis is not None:
            redis.stop()
        if pg is not None:
            pg.close()
