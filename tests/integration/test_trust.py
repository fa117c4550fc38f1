"""Trust, service side, through real processes (embedded stack, and PostgreSQL +
Redis when the SVROBS_TEST_* URLs are set): fair share between teams, cancel that
stops running work, leases that end the units of a dead worker, permanent failures
failed at once, admission by estimated work.

The measured figures (small-job latency under a heavy neighbour, cancel latency)
are printed; run with ``-s`` to see them. Bounds are stated in each test.
"""

from __future__ import annotations

import re
import statistics
import time
from datetime import UTC, datetime

import pytest
import sqlalchemy as sa

from service.config import default_pool_processes
from svrobs_core import parse_spec
from tests.service.svc_helpers import BIG_MEMORY_SPEC as BIG_MEMORY
from tests.service.svc_helpers import HEAVY_SPEC as HEAVY
from tests.service.svc_helpers import ITEM6_SPEC as ITEM6
from tests.service.svc_helpers import TINY_SPEC as SMALL

from .stack import fetch_jsonl, submit

pytestmark = [pytest.mark.integration, pytest.mark.timeout(420)]

# units of ~0.5-1 s each on an idle machine (Monte Carlo cost), one per sigma_w
LONG_UNIT = {
    "systems": ["paper-stable"],
    "N": [10],
    "reps": 1,
    "estimators": ["ols"],
    "stages": ["estimate", "bounds", "gain", "cost"],
    "mc_reps": 1,
    "mc_runs": 2000,
    "horizon": 2000,
    "seed": 3,
}


def long_job(n_units: int, scale: int = 1) -> dict:
    return {
        **LONG_UNIT,
        "sigma_w": [round(0.1 * (i + 1), 3) for i in range(n_units)],
        "horizon": LONG_UNIT["horizon"] * scale,
    }


def second_team(stack, team: str) -> str:
    """A key of a new team (the stack's own key belongs to team 'lab')."""
    return stack.team_key(team)


def team_client(stack, key: str):
    c = stack.client()
    c.headers["Authorization"] = f"Bearer {key}"
    return c


@pytest.fixture(scope="module")
def db(stack):
    engine = sa.create_engine(stack.env["SVROBS_DATABASE_URL"])
    yield engine
    engine.dispose()


def unit_rows(db, job_id: int) -> list[dict]:
    with db.connect() as c:
        rows = c.execute(
            sa.text(
                "select id, status, attempts, error, n_cells, started_at, finished_at "
                "from work_units where job_id = :j order by id"
            ),
            {"j": job_id},
        )
        return [dict(r._mapping) for r in rows]


def running_units(db, job_id: int, timeout: float, what: str = "running") -> list[int]:
    """The ids of the job's running units, once it has any (``wait_for``)."""
    return wait_for(
        lambda: [u["id"] for u in unit_rows(db, job_id) if u["status"] == "running"],
        timeout,
        what,
    )


def killed_mid_unit(stack, db, c, worker: str, spec: dict, name: str) -> tuple[dict, int]:
    """Submit ``spec``, wait for its unit to run on ``worker``, then SIGKILL the worker
    with its pool -> (the job, the unit left running)."""
    job = submit(c, spec, name=name)
    uid = running_units(db, job["id"], 60)[0]
    stack.children[worker].kill_group()
    stack.children.pop(worker)
    return job, uid


def fresh_units(db, job_id: int, within: float = 1.5) -> list[int]:
    """Units of the job running for less than ``within`` s (far from their end)."""
    now = datetime.now(UTC)
    out = []
    for u in unit_rows(db, job_id):
        started = u["started_at"]
        if isinstance(started, str):  # SQLite
            started = datetime.fromisoformat(started)
        if u["status"] == "running" and started is not None:
            started = started if started.tzinfo else started.replace(tzinfo=UTC)
            if (now - started).total_seconds() < within:
                out.append(u["id"])
    return out


def n_results(db, job_id: int) -> int:
    with db.connect() as c:
        return c.execute(
            sa.text("select count(*) from results where job_id = :j"), {"j": job_id}
        ).scalar()


def wait_for(pred, timeout: float, what: str, poll: float = 0.05):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        got = pred()
        if got:
            return got
        time.sleep(poll)
    raise AssertionError(f"not {what} within {timeout} s")


def stop_line(stack, worker: str, uid: int) -> str | None:
    """How the unit's run ended, from the worker's log: its task's result, or the
    watch ending its pool process (a computation that did not stop at the interrupt)."""
    text = (stack.logs / f"{worker}.log").read_text(errors="replace")
    m = re.search(rf"succeeded in [0-9.]+s: (\{{'unit': {uid}, [^\n]*)", text)
    if m:
        return m.group(1)
    m = re.search(rf"unit {uid}: still computing [^\n]*ending pool process", text)
    return m.group(0) if m else None


def unit_seconds(stack, worker: str) -> list[float]:
    """Run times of the units the worker finished, from Celery's 'succeeded in' lines."""
    text = (stack.logs / f"{worker}.log").read_text(errors="replace")
    return [
        float(m.group(1))
        for m in re.finditer(r"succeeded in ([0-9.]+)s: \{'unit': \d+, 'status': 'done'", text)
    ]


@pytest.fixture(scope="module")
def pool(stack):
    """One worker with two pool processes (the embedded default on 2 cores)."""
    stack.stop("worker1", grace=5)
    stack.start_worker("pool", concurrency=2)
    yield "pool"
    stack.stop("pool", grace=5)
    stack.start_worker()


# --------------------------------------------------------------------------- fair share


def test_small_job_of_another_team_is_not_queued_behind_a_long_job(stack, pool, db):
    """Team B's 40-unit job is running on both pool processes; team A's one-unit job
    finishes within 3 x B's median unit time + 3 s (without the per-team cap of units
    in flight it would wait for B's remaining units: ~20 unit times)."""
    key_b = second_team(stack, "team-b")
    with team_client(stack, key_b) as b, stack.client() as a:
        big = submit(b, long_job(40), name="heavy neighbour")
        wait_for(lambda: b.get(f"/jobs/{big['id']}").json()["progress"]["done"] >= 4, 120, "4 done")
        t0 = time.monotonic()
        small = submit(a, SMALL, name="small")
        done = wait_for(
            lambda: (j := a.get(f"/jobs/{small['id']}").json())["status"] == "succeeded" and j,
            120,
            "small job done",
        )
        latency = time.monotonic() - t0
        big_now = b.get(f"/jobs/{big['id']}").json()
        in_flight = sum(u["status"] == "running" for u in unit_rows(db, big["id"]))
        assert done["cells_done"] == parse_spec(SMALL).n_cells
        b.post(f"/jobs/{big['id']}/cancel")
    times = unit_seconds(stack, pool)
    unit = statistics.median(times)
    bound = 3 * unit + 3.0
    print(
        f"\n[{stack.kind}] small job of team A under team B's 40-unit job: {latency:.2f} s "
        f"(bound {bound:.2f} s = 3 x median unit {unit:.2f} s + 3 s; B had "
        f"{big_now['progress']['done']}/{big_now['progress']['total']} units done, "
        f"{in_flight} running)"
    )
    # B's job was still far from done: the small job did not wait for it
    assert big_now["progress"]["done"] < big_now["progress"]["total"] - 10
    assert latency < bound


def test_fair_share_keeps_k_units_in_flight_per_team(stack, pool, db):
    """At no time does a team alone have more units published and unfinished than its
    fair share (default: SVROBS_WORKER_POOL_PROCESSES); its job still completes."""
    cap = default_pool_processes()  # the stack runs its API with the default settings
    with stack.client() as c:
        job = submit(c, long_job(12, scale=1), name="capped")
        peak = 0
        deadline = time.monotonic() + 180
        while time.monotonic() < deadline:
            with db.connect() as conn:
                n = conn.execute(
                    sa.text(
                        "select count(*) from work_units where job_id = :j and "
                        "(status = 'running' or (status = 'pending' and published_at is not null))"
                    ),
                    {"j": job["id"]},
                ).scalar()
            peak = max(peak, n)
            if c.get(f"/jobs/{job['id']}").json()["status"] == "succeeded":
                break
            time.sleep(0.1)
        assert c.get(f"/jobs/{job['id']}").json()["status"] == "succeeded"
        assert len(fetch_jsonl(c, job["id"])) == parse_spec(long_job(12)).n_cells
    print(f"\n[{stack.kind}] peak units in flight for one team: {peak} (cap {cap})")
    assert 1 <= peak <= cap


# --------------------------------------------------------------------------- cancel


def test_cancel_stops_running_units(stack, pool, db):
    """Cancel units (~12x the long unit, a few seconds on a fast CPU) that started less
    than 1.5 s before: they stop within 5 s, their state is final (`cancelled`), no row
    of them is stored, the job says how many cells were done, and the pool takes new
    work at once."""
    with stack.client() as c:
        job = submit(c, long_job(8, scale=12), name="to cancel")
        wait_for(lambda: c.get(f"/jobs/{job['id']}").json()["progress"]["done"] >= 1, 180, "1 done")
        running = wait_for(lambda: fresh_units(db, job["id"]), 120, "a unit just started")
        log = stack.logs / f"{pool}.log"
        t0 = time.monotonic()
        r = c.post(f"/jobs/{job['id']}/cancel")
        assert r.status_code == 200 and r.json()["status"] == "cancelled"
        try:
            lines = wait_for(
                lambda: (ls := [stop_line(stack, pool, u) for u in running]) and all(ls) and ls,
                30,
                "the running units stopped",
            )
            assert not any("'records':" in line for line in lines), lines  # not run to the end
        except AssertionError as exc:  # say what the units and the worker did
            tail = "\n".join(log.read_text(errors="replace").splitlines()[-40:])
            raise AssertionError(
                f"{exc}; units {running} were fresh; rows {unit_rows(db, job['id'])}; "
                f"{pool}.log ends:\n{tail}"
            ) from None
        latency = time.monotonic() - t0
        rows = unit_rows(db, job["id"])
        assert {u["status"] for u in rows} <= {"done", "cancelled"}
        assert all(u["status"] == "cancelled" for u in rows if u["id"] in running)
        done_cells = sum(u["n_cells"] for u in rows if u["status"] == "done")
        after = c.get(f"/jobs/{job['id']}").json()
        assert after["status"] == "cancelled"
        assert after["cells_done"] == done_cells == n_results(db, job["id"]) > 0
        assert after["cells_done"] < after["n_cells"]
        t1 = time.monotonic()
        marker = submit(c, SMALL, name="after cancel")
        assert stack.wait_job(c, marker["id"], timeout=60)["status"] == "succeeded"
        free = time.monotonic() - t1
    print(
        f"\n[{stack.kind}] cancel latency: {len(running)} running units stopped "
        f"{latency:.2f} s after the cancel (check every 1 s); a new small job then took "
        f"{free:.2f} s; cells done {after['cells_done']} of {after['n_cells']}"
    )
    assert latency < 5.0


@pytest.mark.faults  # kills a worker: `make test-faults`
def test_a_worker_restarted_takes_back_the_unit_it_was_killed_in(stack, pool, db):
    """A worker SIGKILLed (with its pool) mid-unit, then started again under the same
    node name (as `svrobs serve` restarts it), with the lease still hours long and no
    beat: the new process ends the unit's lease before it takes a message and
    re-publishes it, so the unit runs again at once (a second attempt) and the job
    finishes."""
    stack.stop("pool", grace=5)
    env = {"SVROBS_UNIT_LEASE_SECONDS": "7200"}
    stack.start_worker("restarted", concurrency=1, env=env)
    try:
        with stack.client() as c:
            job, uid = killed_mid_unit(stack, db, c, "restarted", long_job(1, scale=4), "cut short")
            t0 = time.monotonic()
            stack.start_worker("restarted", concurrency=1, env=env)
            stack.wait_log("restarted", "this node left running", timeout=30)
            done = stack.wait_job(c, job["id"], timeout=120)
            left = time.monotonic() - t0
        assert done["status"] == "succeeded", done
        unit = next(u for u in unit_rows(db, job["id"]) if u["id"] == uid)
        assert unit["status"] == "done" and unit["attempts"] == 2
        print(f"\n[{stack.kind}] the killed worker's job finished {left:.1f} s after its restart")
    finally:
        stack.stop("restarted")
        stack.start_worker("pool", concurrency=2)


@pytest.mark.faults  # kills a worker: `make test-faults`
def test_lease_ends_the_units_of_a_killed_worker(stack, pool, db):
    """A worker with a 3 s lease is SIGKILLed (with its pool) mid-unit: beat's relay
    takes the unit out of `running` once the lease has run out."""
    stack.stop("pool", grace=5)
    stack.start_worker("short-lease", concurrency=1, env={"SVROBS_UNIT_LEASE_SECONDS": "3"})
    try:
        with stack.client() as c:
            job, uid = killed_mid_unit(stack, db, c, "short-lease", long_job(1, scale=8), "orphan")
            t0 = time.monotonic()
            stack.start_beat("beat", tick_seconds=1)
            wait_for(
                lambda: (
                    next(u for u in unit_rows(db, job["id"]) if u["id"] == uid)["status"]
                    != "running"
                ),
                30,
                "out of running",
                poll=0.2,
            )
            left = time.monotonic() - t0
            c.post(f"/jobs/{job['id']}/cancel")
        print(f"\n[{stack.kind}] a killed worker's unit left `running` {left:.1f} s after the kill")
    finally:
        stack.stop("beat")
        stack.start_worker("pool", concurrency=2)


# --------------------------------------------------------------------------- retries, admission


@pytest.mark.faults  # kills a worker: `make test-faults`
def test_permanent_failure_fails_at_once(stack, pool, db):
    """A unit that runs out of memory (a worker under a 2 GB address-space limit, a
    spec admitted by an API with no work limits) fails on its first attempt with the
    reason; it is never retried."""
    url = stack.start_api(
        "api-nolimits",
        env={"SVROBS_MAX_UNIT_MEMORY_MB": "100000000", "SVROBS_MAX_JOB_CPU_SECONDS": "1e12"},
    )
    stack.stop("pool", grace=5)
    from svrobs_cli.serve import worker_command

    stack.start("oom", ["prlimit", "--as=2000000000", "--", *worker_command("oom", 1)])
    stack.wait_log("oom", "ready.")
    spec = BIG_MEMORY  # ~2.9 GB for one repetition
    try:
        with stack.client(url) as c:
            job = submit(c, spec, name="oom")
            done = stack.wait_job(c, job["id"], timeout=120)
        (unit,) = unit_rows(db, job["id"])
        assert done["status"] == "failed", done
        assert "MemoryError" in done["error"] and "MemoryError" in unit["error"]
        assert unit["status"] == "failed" and unit["attempts"] == 1
        assert "retry" not in (stack.logs / "oom.log").read_text(errors="replace").lower()
        # the default API refuses it before it runs: the estimate names the memory cap
        with stack.client() as c:
            r = c.post("/jobs", json=spec)
        assert r.status_code == 422 and r.json()["field"] in ("N", "T0", "systems")
        assert "SVROBS_MAX_UNIT_MEMORY_MB" in r.json()["detail"]
    finally:
        stack.stop("oom", grace=5)
        stack.stop("api-nolimits")
        stack.start_worker("pool", concurrency=2)


def test_heavy_spec_is_refused_by_its_estimated_work(stack):
    """A spec within the core's hard caps but ~2.6 h of CPU is a 422 naming the field
    that weighs most, the estimate and the limit, on POST /jobs and as a schedule's
    template; a cell of ~11 h (`mc_runs` = 10^6, `horizon` = 10^5) is over a hard cap (`mc_runs`); nothing is queued."""
    with stack.client() as c:
        before = c.get("/jobs").json()["total"]
        r = c.post("/jobs", json=HEAVY)
        assert r.status_code == 422, r.text
        body = r.json()
        assert body["field"] in ("horizon", "mc_runs", "reps", "mc_reps")
        assert re.search(r"estimated [0-9]+ CPU seconds", body["detail"])
        assert "SVROBS_MAX_JOB_CPU_SECONDS" in body["detail"] and "3600" in body["detail"]
        r = c.post(
            "/schedules",
            json={"name": "too big", "cron": "0 3 * * *", "spec_template": HEAVY},
        )
        assert r.status_code == 422 and r.json()["field"].startswith("spec_template.")
        r = c.post("/jobs", json=ITEM6)
        assert r.status_code == 422 and r.json()["field"] == "mc_runs"
        assert c.get("/jobs").json()["total"] == before
    print(f"\n[{stack.kind}] heavy spec: {body['field']}: {body['detail']}")
