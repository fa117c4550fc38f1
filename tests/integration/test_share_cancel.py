"""Fair share and cancel at the default configuration, through real processes on the
embedded stack (SQLite + filesystem broker; one worker with ``svrobs serve``'s
default pool, the API's default fair share): a small job of team B under team A's
long jobs is never queued behind A's next unit; a cancelled solver (sls) unit stops
without running to its end, and so do the running units of a job cancelled then
deleted; the worker keeps serving (docs/architecture.md#one-job).

The measured figures (cancel latency of the solver stage, the small job's wait) are
printed; run with ``-s`` to see them.
"""

from __future__ import annotations

import time
from datetime import datetime

import pytest
import sqlalchemy as sa

from svrobs_cli.serve import DEFAULT_CONCURRENCY
from tests.service.svc_helpers import TINY_SPEC

from .stack import Stack, submit
from .test_trust import (
    long_job,
    n_results,
    running_units,
    second_team,
    team_client,
    unit_rows,
    wait_for,
)
from .test_trust import stop_line as trust_stop_line

pytestmark = [pytest.mark.integration, pytest.mark.timeout(420)]

# one unit of 40 repetitions, each an SLS synthesis (cvxpy + Clarabel): ~1 min
SLS_UNIT = {
    "systems": ["paper-stable"],
    "sigma_w": [1.0],
    "N": [20],
    "gamma": [0.05],
    "estimators": ["ols"],
    "reps": 40,
    "stages": ["estimate", "bounds", "sls"],
    "sls": {"T_fir": 600},
    "seed": 1,
}


@pytest.fixture(scope="module")
def stack(tmp_path_factory):
    """The embedded stack as ``svrobs serve`` starts it: one worker, default pool."""
    st = Stack("embedded", tmp_path_factory.mktemp("share-cancel"))
    try:
        st.setup()
        st.start_api_and_worker(concurrency=DEFAULT_CONCURRENCY)
        yield st
    finally:
        st.teardown()


@pytest.fixture(scope="module")
def db(stack):
    engine = sa.create_engine(stack.env["SVROBS_DATABASE_URL"])
    yield engine
    engine.dispose()


def _at(value) -> datetime | None:
    return datetime.fromisoformat(value) if isinstance(value, str) else value


def worker_log(stack) -> str:
    return (stack.logs / "worker1.log").read_text(errors="replace")


def stop_line(stack, uid: int) -> str | None:
    return trust_stop_line(stack, "worker1", uid)


def ran_to_its_end(line: str) -> bool:
    """A result with records: the computation finished (and the store refused it)."""
    return "'records':" in line


def test_small_job_is_not_queued_behind_a_neighbours_next_unit(stack, db):
    """Team A's four one-unit long jobs fill the pool (A alone: the pool's size); team
    B's one-unit job then starts before any of A's units not yet started, and
    finishes while A still has jobs running or queued."""
    key_b = second_team(stack, "team-b")
    with stack.client() as a, team_client(stack, key_b) as b:
        heavy = [submit(a, long_job(1, scale=2), name=f"heavy {i}")["id"] for i in range(4)]
        wait_for(
            lambda: (
                sum(u["status"] == "running" for j in heavy for u in unit_rows(db, j))
                >= min(DEFAULT_CONCURRENCY, 4)
            ),
            120,
            "A's units running",
        )
        waiting = [u["id"] for j in heavy for u in unit_rows(db, j) if u["started_at"] is None]
        t0 = time.monotonic()
        small = submit(b, TINY_SPEC, name="small")
        done = stack.wait_job(b, small["id"], timeout=240)
        wait_s = time.monotonic() - t0
        assert done["status"] == "succeeded", done
        a_jobs = [a.get(f"/jobs/{j}").json()["status"] for j in heavy]
        (b_unit,) = unit_rows(db, small["id"])
        a_units = {u["id"]: u for j in heavy for u in unit_rows(db, j)}
        for j in heavy:
            a.post(f"/jobs/{j}/cancel")
    ran = sorted(
        (_at(u["finished_at"]) - _at(u["started_at"])).total_seconds()
        for u in a_units.values()
        if u["status"] == "done"
    )
    print(
        f"\n[{stack.kind}] small job of team B under team A's 4 long one-unit jobs "
        f"({DEFAULT_CONCURRENCY} pool processes): done in {wait_s:.2f} s (A's units ran "
        f"{', '.join(f'{t:.1f}' for t in ran)} s); A's jobs then {a_jobs}; "
        f"A's units not started at B's submit: {len(waiting)}"
    )
    assert any(s in ("queued", "running") for s in a_jobs), a_jobs
    b_start = _at(b_unit["started_at"])
    for uid in waiting:  # B's unit never waited for one of them to run
        # When A's running units end together, B's unit and A's next one start on two
        # freed pool processes at once, in either order (20 ms apart seen): B was not
        # behind it unless that unit had finished before B's started.
        started = _at(a_units[uid]["started_at"])
        finished = _at(a_units[uid]["finished_at"])
        assert started is None or started >= b_start or finished is None or finished > b_start, (
            uid,
            started,
            finished,
            b_start,
        )


def test_cancel_stops_a_solver_unit(stack, db):
    """A running sls unit (one unit of ~1 min) is cancelled: it stops without running
    to its end, stores nothing, and the worker serves the next job."""
    with stack.client() as c:
        job = submit(c, SLS_UNIT, name="sls to cancel")
        (uid,) = [u["id"] for u in unit_rows(db, job["id"])]
        wait_for(lambda: unit_rows(db, job["id"])[0]["status"] == "running", 120, "running")
        time.sleep(2.0)  # well inside the solver stage
        t0 = time.monotonic()
        r = c.post(f"/jobs/{job['id']}/cancel")
        assert r.status_code == 200 and r.json()["status"] == "cancelled"
        line = wait_for(lambda: stop_line(stack, uid), 60, "the sls unit stopped", poll=0.02)
        latency = time.monotonic() - t0
        assert not ran_to_its_end(line), line
        assert unit_rows(db, job["id"])[0]["status"] == "cancelled"
        assert n_results(db, job["id"]) == 0
        marker = submit(c, TINY_SPEC, name="after the sls cancel")
        assert stack.wait_job(c, marker["id"], timeout=120)["status"] == "succeeded"
        assert c.get(f"/jobs/{job['id']}").json()["status"] == "cancelled"
    if "ending pool process" in line:  # the lost worker's message came back: skipped
        wait_for(lambda: f"{{'unit': {uid}, 'status': 'skipped'}}" in worker_log(stack), 60, "skip")
    print(
        f"\n[{stack.kind}] cancel latency of a running sls unit (T_fir 600): {latency:.2f} s "
        f"(check every 1 s); stopped by {'ending its process' if 'pool' in line else 'the interrupt'}"
    )


def test_cancel_then_delete_stops_the_running_units(stack, db):
    """A job is cancelled and at once deleted while its units run: the units (whose
    rows are gone) stop without running to their end, and the worker serves on."""
    with stack.client() as c:
        job = submit(c, long_job(3, scale=16), name="cancel then delete")
        running = running_units(db, job["id"], 120, "a unit running")
        time.sleep(1.5)
        assert c.post(f"/jobs/{job['id']}/cancel").status_code == 200
        assert c.delete(f"/jobs/{job['id']}").status_code == 204
        assert unit_rows(db, job["id"]) == []
        for uid in running:
            line = wait_for(lambda uid=uid: stop_line(stack, uid), 60, f"unit {uid} stopped")
            assert not ran_to_its_end(line), line
        marker = submit(c, TINY_SPEC, name="after the delete")
        assert stack.wait_job(c, marker["id"], timeout=120)["status"] == "succeeded"
