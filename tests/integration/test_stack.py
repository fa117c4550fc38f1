"""End to end with real processes: uvicorn + celery worker (+ beat) + a real DB.

Each test runs on both stacks (see conftest): the embedded SQLite +
filesystem broker, and PostgreSQL + Redis when the SVROBS_TEST_* URLs are set.
"""

from __future__ import annotations

import json
import subprocess
import sys
import time
from datetime import UTC, datetime, timedelta

import pytest

from svrobs_core import RECORD_FIELDS, parse_spec, plan_units

from .conftest import ROOT, free_port
from .stack import cell_key, fetch_jsonl, in_process_records, same, submit

pytestmark = [pytest.mark.integration, pytest.mark.timeout(300)]

SMALL_SPEC = {
    "systems": ["paper-stable", "paper-unstable"],
    "sigma_w": [0.1, 1.0],
    "N": [10, 20],
    "gamma": [0.01, 0.05],
    "estimators": ["ols", "svr"],
    "reps": 3,
    "stages": ["estimate", "bounds"],
    "seed": 7,
}
TINY_SPEC = {
    "systems": ["paper-stable"],
    "sigma_w": [1.0],
    "N": [10],
    "gamma": [0.05],
    "estimators": ["ols", "svr"],
    "reps": 2,
    "stages": ["estimate", "bounds"],
    "seed": 1,
}


# --------------------------------------------------------------------------- records


def test_rest_job_equals_in_process_run(stack):
    """Same spec and seed over REST (real worker, real DB) and in process: identical
    records, matrices bit for bit."""
    t0 = time.monotonic()
    with stack.client() as c:
        job = submit(c, SMALL_SPEC, name="identity", tags=["it"])
        assert job["progress"]["total"] == len(plan_units(parse_spec(SMALL_SPEC)))
        done = stack.wait_job(c, job["id"], timeout=150)
        assert done["status"] == "succeeded", done
        assert done["progress"]["done"] == done["progress"]["total"]
        got = fetch_jsonl(c, job["id"])
    elapsed = time.monotonic() - t0
    expected = in_process_records(SMALL_SPEC)

    assert len(got) == len(expected) == parse_spec(SMALL_SPEC).n_cells
    by_key = {cell_key(r): r for r in got}
    assert len(by_key) == len(got), "one stored result per cell"
    assert set(by_key) == set(expected)
    problems = []
    for key, exp in expected.items():
        rec = by_key[key]
        for f in RECORD_FIELDS:
            problems += same(rec.get(f), exp[f], f"{key}.{f}")
    assert not problems, "\n".join(problems[:30])
    # the matrices really are there (not both None)
    assert all(isinstance(r["A_hat"], list) and isinstance(r["B_hat"], list) for r in got)
    print(f"\n[{stack.kind}] {len(got)} records over REST in {elapsed:.1f}s, bit-identical")


# --------------------------------------------------------------------------- cancel


WAIT_PUBLISHED = """
import time
import sqlalchemy as sa
from service.config import get_settings
engine = sa.create_engine(get_settings().DATABASE_URL)
n = 0
for _ in range(200):
    with engine.connect() as c:
        n = c.execute(sa.text(
            "SELECT count(*) FROM work_units WHERE job_id = %d AND published_at IS NOT NULL"
        )).scalar()
    if n:
        break
    time.sleep(0.05)
print(n)
"""


def test_cancel_stops_pending_units(stack):
    """Units of a cancelled job never run, even though their messages are delivered."""
    stack.stop("worker1", grace=3)  # idle: nothing reserved, nothing to lose
    try:
        with stack.client() as c:
            job = submit(c, SMALL_SPEC, name="to-cancel")
            # the API publishes after its commit: cancel once a message is out, or the
            # cancel can come first and nothing is ever delivered
            published = stack.python(WAIT_PUBLISHED % job["id"])
            assert int(published) >= 1, "no unit of the job was published in 10 s"
            r = c.post(f"/jobs/{job['id']}/cancel")
            assert r.status_code == 200, r.text
            assert r.json()["status"] == "cancelled"
            time.sleep(0.5)  # let the API's after-commit publish reach the broker
            stack.start_worker()
            # the messages published before the cancel (the fair share publishes at
            # most the pool's size of them) are delivered and skipped
            stack.wait_log("worker1", "'status': 'skipped'")
            marker = submit(c, TINY_SPEC, name="marker")  # the worker still runs new work
            assert stack.wait_job(c, marker["id"])["status"] == "succeeded"
            skipped = (stack.logs / "worker1.log").read_text().count("'status': 'skipped'")
            assert 1 <= skipped <= job["progress"]["total"]
            after = c.get(f"/jobs/{job['id']}").json()
            assert after["status"] == "cancelled"
            assert after["progress"]["done"] == 0
            assert fetch_jsonl(c, job["id"]) == []
            assert c.post(f"/jobs/{job['id']}/cancel").json()["status"] == "cancelled"
    finally:
        if "worker1" not in stack.children:
            stack.start_worker()
    assert "'status': 'done'" in (stack.logs / "worker1.log").read_text()


# --------------------------------------------------------------------------- relay


def test_relay_publishes_what_the_api_could_not(stack, tmp_path):
    """The API cannot reach the broker: POST /jobs still answers 202 (the job and its
    units are committed), nothing runs; beat's tick relays the units and the job
    completes."""
    if stack.kind == "pg":
        dead = {"SVROBS_BROKER_URL": f"redis://127.0.0.1:{free_port()}/0"}
    else:
        blocker = tmp_path / "not-a-dir"
        blocker.write_text("a file where the broker folder should be")
        dead = {"SVROBS_BROKER_DIR": str(blocker / "broker")}
    url = stack.start_api("api-nobroker", env=dead, wait="/healthz")
    try:
        with stack.client(url) as c:
            job = submit(c, TINY_SPEC, name="relayed")  # 202 within the client's timeout
            time.sleep(3)  # the worker is up: it would have run a published unit by now
            assert c.get(f"/jobs/{job['id']}").json()["status"] == "queued"
        stack.start_beat("beat", tick_seconds=1)
        with stack.client() as c:
            done = stack.wait_job(c, job["id"], timeout=90)
            assert done["status"] == "succeeded", done
            assert len(fetch_jsonl(c, job["id"])) == parse_spec(TINY_SPEC).n_cells
    finally:
        stack.stop("beat")
        stack.stop("api-nobroker")
    assert "relayed" in (stack.logs / "beat.log").read_text()


# --------------------------------------------------------------------------- schedules

TICK = """
import json, sys, time
from datetime import datetime
from worker.tick import run_tick
out = []
for start, now in json.loads(sys.argv[1]):
    time.sleep(max(0.0, start - time.time()))
    out.append(run_tick(now=datetime.fromisoformat(now), reports=False))
print(json.dumps(out))
"""


def concurrent_ticks(stack, nows: list[datetime], n: int = 2) -> list[list[dict]]:
    """Run the tick in ``n`` processes at once, one round per ``now``: in every round
    the processes are released at the same instant. -> results[round][process]."""
    t0 = time.time() + 4.0  # after every interpreter has imported everything
    plan = json.dumps([(t0 + 1.5 * i, now.isoformat()) for i, now in enumerate(nows)])
    procs = [
        subprocess.Popen(
            [sys.executable, "-c", TICK, plan],
            cwd=str(ROOT),
            env=stack.env,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        for _ in range(n)
    ]
    outs = []
    for p in procs:
        out, err = p.communicate(timeout=90)
        assert p.returncode == 0, err[-3000:]
        outs.append(json.loads(out.strip().splitlines()[-1]))
    return [list(r) for r in zip(*outs)]


def test_schedule_due_once_even_with_two_ticks(stack):
    """Two ticks at once (as with two beats) give exactly one job per due time; the
    tick also publishes the new jobs' units and the jobs run."""
    with stack.client() as c:
        r = c.post(
            "/schedules",
            json={
                "name": f"nightly-{stack.kind}",
                "cron": "* * * * *",
                "timezone": "UTC",
                "spec_template": TINY_SPEC,
                "tags": ["sweep"],
                "enabled": True,
            },
        )
        assert r.status_code in (200, 201), r.text
        sched = r.json()
        created = datetime.fromisoformat(sched["created_at"].replace("Z", "+00:00"))
        if created.tzinfo is None:
            created = created.replace(tzinfo=UTC)
        due1 = (created + timedelta(minutes=1)).replace(second=0, microsecond=0)
        due2 = due1 + timedelta(minutes=1)
        rounds = concurrent_ticks(
            stack,
            [
                due1 + timedelta(seconds=5),  # due1 falls due: one job
                due2 + timedelta(seconds=1),  # due2 falls due: one job
                due2 + timedelta(seconds=30),  # due2 again (a late or restarted beat): none
            ],
        )
        for outs in rounds:
            assert not any(o["errors"] for o in outs), outs
        made = [[j for o in outs for j in o["created"]] for outs in rounds]
        assert [len(m) for m in made] == [1, 1, 0], rounds
        jobs = made[0] + made[1]

        listed = c.get("/jobs", params={"tag": f"schedule:nightly-{stack.kind}"}).json()
        assert sorted(j["id"] for j in listed["items"]) == sorted(jobs)
        assert all(j["schedule_id"] == sched["id"] for j in listed["items"])
        # the first job's unit is relayed by a tick; the second's by a tick or by the
        # worker, which publishes its team's next units when the first one finishes
        assert sum(o["relayed"] for outs in rounds for o in outs) >= 1
        for job_id in jobs:  # the tick's relay published them: they run
            assert stack.wait_job(c, job_id)["status"] == "succeeded"
