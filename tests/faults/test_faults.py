"""Fault tests: real processes on loopback, private PostgreSQL + Redis (see conftest).

1. SIGKILL the worker's pool process mid-unit 20 times during a 48-unit sweep:
   the job completes, one stored result per cell, records equal to an
   undisturbed in-process run of the same spec and seed (exact, after JSON).
2. Restart Redis (no persistence: the queue is lost) mid-sweep: the sweep
   completes, nothing lost or duplicated, same records. A worker whose consumer
   stalls while connected (emulated) is reconnected by its watchdog.
3. Restart PostgreSQL (``pg_ctl stop -m fast``) mid-sweep: while it is down the
   API answers 503 with a JSON error (never a 500, never a traceback), and
   everything recovers by itself; one result per cell, same records.
4. SIGKILL the API during a burst of submissions: every 202 job exists and
   completes; a retry with the same Idempotency-Key never duplicates a job; no
   job row without its work units.
5. Two beats (TickScheduler) at once, due schedules: one job per due time.
6. A unit that kills its worker every time (test-only hook
   SVROBS_TEST_CRASH_UNIT) is failed after K attempts; the job's error names the
   unit's cells and why.

Every loop is bounded in count and time; the measured figures (kills
survived, restarts survived, seconds) are printed at the end of the session.
"""

from __future__ import annotations

import json
import os
import random
import signal
import socket
import subprocess
import sys
import threading
import time
import uuid
from datetime import UTC, datetime
from pathlib import Path

import httpx
import pytest

from svrobs_cli.serve import worker_command
from svrobs_core import RECORD_FIELDS, parse_spec, plan_units
from tests.integration.servers import deathsig
from tests.integration.stack import ROOT, cell_key, fetch_jsonl, same, submit

from .conftest import RESULTS

pytestmark = [pytest.mark.faults, pytest.mark.timeout(240)]

# 48 units of ~0.3 s each (a 500-run Monte Carlo cost): one per (system, sigma_w) with a
# single N, so no planner packing of N values changes the count; 60 cells per unit.
SWEEP = {
    "systems": ["paper-stable", "paper-unstable"],
    "sigma_w": [round(0.1 * 1.15**k, 4) for k in range(24)],
    "N": [60],
    "gamma": [0.01, 0.05],
    "estimators": ["ols", "svr"],
    "reps": 20,
    "stages": ["estimate", "bounds", "gain", "cost"],
    "mc_runs": 500,
    "horizon": 150,
    "seed": 11,
}
TINY = {
    "systems": ["paper-stable"],
    "sigma_w": [1.0],
    "N": [10, 20],
    "gamma": [0.05],
    "estimators": ["ols", "svr"],
    "reps": 2,
    "stages": ["estimate", "bounds"],
    "seed": 3,
}
N_KILLS = 20  # twenty kills of a worker child mid-unit


# --------------------------------------------------------------------------- helpers
REFERENCE_SCRIPT = """
import json, sys, time
from svrobs_core import parse_spec, run_spec
spec = json.loads(sys.argv[1])
t0 = time.perf_counter()
recs = [r for batch in run_spec(parse_spec(spec)) for r in batch]
print(round(time.perf_counter() - t0, 1))
with open(sys.argv[2], "w") as fh:
    json.dump(recs, fh, allow_nan=False)
"""


def _niced_child() -> None:  # pragma: no cover - runs in the child
    os.nice(5)
    deathsig(signal.SIGKILL)()


class Reference:
    """The undisturbed in-process run of SWEEP, computed once in a background
    interpreter (niced) while the first sweep runs; JSON round trip as the API's."""

    def __init__(self, root: Path, env: dict):
        self.path = root / "reference.json"
        self.t0 = time.monotonic()
        self.proc = subprocess.Popen(
            [sys.executable, "-c", REFERENCE_SCRIPT, json.dumps(SWEEP), str(self.path)],
            cwd=str(ROOT),
            env=env,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            start_new_session=True,
            preexec_fn=_niced_child,  # noqa: PLW1509
        )
        self._records: dict | None = None

    def records(self, timeout: float = 120) -> dict[tuple, dict]:
        if self._records is None:
            out, err = self.proc.communicate(timeout=timeout)
            assert self.proc.returncode == 0, err[-3000:]
            with open(self.path) as fh:
                self._records = {cell_key(r): r for r in json.load(fh)}
            RESULTS["reference_in_process_run_s"] = float(out.strip().splitlines()[-1])
        return self._records

    def close(self) -> None:
        if self.proc.poll() is None:
            os.killpg(self.proc.pid, signal.SIGKILL)
            self.proc.wait(10)


@pytest.fixture(scope="module")
def reference(fstack, tmp_path_factory):
    ref = Reference(tmp_path_factory.mktemp("reference"), fstack.env)
    try:
        yield ref
    finally:
        ref.close()


def pool_children(pid: int) -> list[int]:
    """Live (non-zombie) children of ``pid``, from /proc."""
    out = []
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        try:
            with open(f"/proc/{entry}/stat") as fh:
                stat = fh.read()
        except OSError:
            continue
        fields = stat.rsplit(")", 1)[-1].split()
        if int(fields[1]) == pid and fields[0] != "Z":
            out.append(int(entry))
    return out


def job_progress(st, job_id: int) -> tuple[str, int, int]:
    row = st.sql("SELECT status, progress_done, progress_total FROM jobs WHERE id = :j", j=job_id)[
        0
    ]
    return row[0], int(row[1]), int(row[2])


def wait_progress(st, job_id: int, done: int, timeout: float) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        status, d, _ = job_progress(st, job_id)
        if d >= done or status not in ("queued", "running"):
            return
        time.sleep(0.1)
    raise AssertionError(
        f"job {job_id}: {done} units not done in {timeout}s\n{diagnose(st, job_id)}"
    )


def wait_job_db(st, job_id: int, timeout: float) -> str:
    """Wait on the DB (not the API: some tests take the API down) for a final status."""
    deadline = time.monotonic() + timeout
    status = None
    while time.monotonic() < deadline:
        status, _, _ = job_progress(st, job_id)
        if status in ("succeeded", "failed", "cancelled"):
            return status
        time.sleep(0.2)
    raise AssertionError(f"job {job_id} still {status} after {timeout}s\n{diagnose(st, job_id)}")


def diagnose(st, job_id: int) -> str:
    """What a stuck job looks like: its units by state (from the DB), the broker's
    queue (Redis), then the logs of the processes this test started, worker first."""
    lines = []
    try:
        rows = st.sql(
            "SELECT status, attempts, count(*), min(published_at), max(published_at), "
            "max(lease_expires_at), max(worker) FROM work_units WHERE job_id = :j "
            "GROUP BY status, attempts ORDER BY status, attempts",
            j=job_id,
        )
        lines += [f"units: {tuple(r)}" for r in rows]
    except Exception as exc:  # noqa: BLE001 - the DB may be the thing that is down
        lines.append(f"units: unreadable ({exc!r})")
    try:
        import redis

        r = redis.Redis.from_url(st.servers.redis.url, socket_timeout=2)
        lines.append(
            f"redis: queue svrobs={r.llen('svrobs')} unacked={r.hlen('unacked')} "
            f"epoch={r.get('svrobs:broker-epoch')!r}"
        )
    except Exception as exc:  # noqa: BLE001 - Redis may be the server that is down
        lines.append(f"redis: unreadable ({exc!r})")
    names = sorted((n for n in st.children if n != "api"), key=lambda n: n == "beat")
    return "\n".join(lines) + "\n" + st.log_tail(*names, "api", n=80)


def assert_one_result_per_cell(st, job_id: int, n_cells: int) -> None:
    dup = st.sql(
        'SELECT system, sigma_w, "N", estimator, gamma_key, rep, count(*) FROM results '
        'WHERE job_id = :j GROUP BY system, sigma_w, "N", estimator, gamma_key, rep '
        "HAVING count(*) > 1",
        j=job_id,
    )
    assert not dup, f"duplicated cells: {dup[:5]}"
    ((rows, cells),) = st.sql(
        'SELECT count(*), count(DISTINCT (system, sigma_w, "N", estimator, gamma_key, rep)) '
        "FROM results WHERE job_id = :j",
        j=job_id,
    )
    assert rows == cells == n_cells, (rows, cells, n_cells)
    units = st.sql(
        "SELECT status, count(*) FROM work_units WHERE job_id = :j GROUP BY status", j=job_id
    )
    assert dict(units) == {"done": len(plan_units(parse_spec(SWEEP)))}, units


def assert_records_equal_reference(st, job_id: int, reference: Reference) -> int:
    with st.client() as c:
        got = fetch_jsonl(c, job_id)
    expected = reference.records()
    by_key = {cell_key(r): r for r in got}
    assert len(by_key) == len(got) == len(expected), (len(by_key), len(got), len(expected))
    assert set(by_key) == set(expected)
    problems = []
    for key, exp in expected.items():
        for f in RECORD_FIELDS:
            problems += same(by_key[key].get(f), exp[f], f"{key}.{f}")
    assert not problems, "\n".join(problems[:30])
    return len(got)


def submit_sweep(st, name: str) -> dict:
    with st.client() as c:
        return submit(c, SWEEP, name=name, tags=["faults"])


def log_count(st, name: str, text: str) -> int:
    return sum(p.read_text(errors="replace").count(text) for p in st.logs.glob(f"{name}*.log"))


# --------------------------------------------------------------------------- 1. kills


def start_workers(st, names: list[str], concurrency: int = 1, env: dict | None = None) -> dict:
    """Start several workers at once (their imports overlap), then wait for each."""
    for name in names:
        st.start(name, worker_command(name, concurrency), env)
    for name in names:
        st.wait_log(name, "ready.")
    return {name: st.children[name] for name in names}


KILL_WORKERS = 4  # single-process workers: the kills' detection latency overlaps
# kills of one unit at most: below the attempt limit (MAX_UNIT_ATTEMPTS, 5), which a
# unit killed on every claim reaches (that is test 6); a redelivered unit claimed by a
# worker whose turn it is to kill could otherwise be killed on all five claims
KILLS_PER_UNIT = 3
MAX_KILL_JOBS = 3  # copies of the sweep the kills may need (a unit can end before its kill)


def test_sigkill_worker_child_mid_unit_20_times(stack_up, reference):
    """SIGKILL a pool process while it runs a unit, 20 times. Each worker has one pool
    process, so a unit the DB shows ``running`` under a worker's name, claimed last
    by that worker, is the unit its pool process executes right now. Each worker
    alternates: its next claim is killed, the one after runs to the end. A kill that
    would land after its unit finished is skipped, so the kills may need a second or
    third copy of the sweep; every job must still end with the reference's records."""
    st = stack_up
    t0 = time.monotonic()
    n_units = len(plan_units(parse_spec(SWEEP)))
    n_cells = parse_spec(SWEEP).n_cells
    assert 40 <= n_units <= 60, f"SWEEP now plans {n_units} units: resize it for 20 kills"
    names = [f"killw{i + 1}" for i in range(KILL_WORKERS)]
    workers = start_workers(st, names)
    hostnames = {f"{n}@{socket.gethostname()}": n for n in names}
    # a unit that finishes before its kill lands is not killed; when a job ends short of
    # N_KILLS kills, a copy of the sweep is submitted and the killing goes on there
    job_ids = [submit_sweep(st, "kill-20")["id"]]

    rng = random.Random(20)
    kills: list[dict] = []
    seen: dict[str, object] = {}  # worker -> started_at of its last claim seen
    kill_next = dict.fromkeys(names, True)
    planned: list[tuple[float, str, int, int]] = []  # (when, worker, unit, attempts)
    deadline = time.monotonic() + 300
    polls = 0
    while len(kills) < N_KILLS and time.monotonic() < deadline and polls < 200_000:
        polls += 1
        job_id = job_ids[-1]
        status, done, _ = job_progress(st, job_id)
        if status not in ("queued", "running"):
            if len(job_ids) == MAX_KILL_JOBS:
                break
            job_ids.append(submit_sweep(st, f"kill-20-{len(job_ids) + 1}")["id"])
            continue
        # every worker's latest claim in this job
        latest = st.sql(
            "SELECT DISTINCT ON (worker) worker, id, attempts, status, started_at "
            "FROM work_units WHERE job_id = :j AND worker IS NOT NULL "
            "ORDER BY worker, started_at DESC",
            j=job_id,
        )
        by_worker = {}
        for host, uid, att, ustatus, started in latest:
            name = hostnames.get(host)
            if name is None:
                continue
            by_worker[name] = (uid, att, ustatus)
            if ustatus != "running" or (name in seen and started <= seen[name]):
                continue
            seen[name] = started  # a new claim by this worker
            if kill_next[name] and att <= KILLS_PER_UNIT:
                planned.append((time.monotonic() + rng.uniform(0.02, 0.15), name, uid, att))
                kill_next[name] = False
            elif not kill_next[name]:
                kill_next[name] = True
            # else: a unit killed KILLS_PER_UNIT times runs; the worker's next claim is killed
        now = time.monotonic()
        for item in [p for p in planned if p[0] <= now]:
            planned.remove(item)
            _, name, uid, att = item
            # still that worker's latest claim, still running: its pool process is mid-unit
            if by_worker.get(name) != (uid, att, "running"):
                kill_next[name] = True  # finished before the kill: kill the next claim
                continue
            kids = pool_children(workers[name].pid)
            if len(kids) != 1:
                kill_next[name] = True
                continue
            os.kill(kids[0], signal.SIGKILL)
            kills.append(
                {
                    "worker": name,
                    "job": job_id,
                    "unit": uid,
                    "attempt": att,
                    "pid": kids[0],
                    "units_done": done,
                }
            )
            if len(kills) == N_KILLS:
                break
        time.sleep(0.01)
    assert len(kills) == N_KILLS, (
        f"only {len(kills)} kills before {len(job_ids)} jobs ended\n{st.log_tail()}"
    )
    t_kills = time.monotonic() - t0

    records = 0
    for job_id in job_ids:
        assert wait_job_db(st, job_id, timeout=120) == "succeeded", st.log_tail(*names)
        with st.client() as c:
            final = c.get(f"/jobs/{job_id}").json()
        assert final["status"] == "succeeded"
        assert final["progress"]["done"] == final["progress"]["total"] == n_units, final
        assert_one_result_per_cell(st, job_id, n_cells)
        records += assert_records_equal_reference(st, job_id, reference)

    attempts = st.sql(
        "SELECT sum(attempts), max(attempts) FROM work_units WHERE job_id = ANY(:j)",
        j=job_ids,
    )[0]
    lost = sum(log_count(st, w, "exited with 'signal 9 (SIGKILL)'") for w in names)
    assert lost == N_KILLS, f"the workers logged {lost} lost pool processes"
    assert all(w.poll() is None for w in workers.values()), "a worker's main process died"
    # every kill hit a claimed, unfinished unit: it cost exactly one extra claim
    assert int(attempts[0]) == n_units * len(job_ids) + N_KILLS, (attempts, kills)
    RESULTS["1_sigkill_worker_child"] = {
        "kills_survived": len(kills),
        "distinct_units_killed": len({k["unit"] for k in kills}),
        "workers": KILL_WORKERS,
        "units": n_units,
        "cells": n_cells,
        "jobs": len(job_ids),
        "records_identical_to_in_process_run": records,
        "claims": int(attempts[0]),
        "max_claims_of_a_unit": int(attempts[1]),
        "kill_phase_s": round(t_kills, 1),
        "seconds": round(time.monotonic() - t0, 1),
    }


# --------------------------------------------------------------------------- 2. redis


def test_redis_restart_mid_sweep(stack_up, reference):
    st = stack_up
    t0 = time.monotonic()
    n_units = len(plan_units(parse_spec(SWEEP)))
    st.start_worker("redisw", concurrency=2)
    # default PUBLISH_RETRY_SECONDS (600): the restarted Redis has lost the queue, and
    # the relay must notice that at once (service.broker.broker_epoch)
    st.start_beat("beat", tick_seconds=1)
    job_id = submit_sweep(st, "redis-restart")["id"]
    wait_progress(st, job_id, n_units // 4, timeout=90)
    done_before = job_progress(st, job_id)[1]
    down = st.servers.redis.restart(down=3.0)
    t_back = time.monotonic()
    status = wait_job_db(st, job_id, timeout=150)
    assert status == "succeeded", st.log_tail("redisw", "beat")
    t_done = time.monotonic()
    assert_one_result_per_cell(st, job_id, parse_spec(SWEEP).n_cells)
    n = assert_records_equal_reference(st, job_id, reference)
    assert st.children["redisw"].poll() is None and st.children["beat"].poll() is None
    relayed = [
        int(x.split("relayed ")[1].split()[0])
        for x in (st.logs / "beat.log").read_text().splitlines()
        if "tick: relayed" in x
    ]
    assert relayed, "the relay re-published nothing: the lost queue was not noticed"
    RESULTS["2_redis_restart"] = {
        "restarts_survived": 1,
        "redis_down_s": round(down, 1),
        "units_done_before_restart": done_before,
        "units": n_units,
        "units_republished_by_relay": sum(relayed),
        "completion_after_restart_s": round(t_done - t_back, 1),
        "records_identical": n,
        "seconds": round(time.monotonic() - t0, 1),
    }


def test_stalled_consumer_reconnects(stack_up, reference):
    """A worker connected to Redis but no longer consuming (the failure of
    celery#8091/kombu#2007 after a broker restart; emulated by the test-only hook
    SVROBS_TEST_STALL_CONSUMER, a basic_cancel after the first message) is noticed by
    its watchdog, which reconnects; the sweep completes, once per cell."""
    st = stack_up
    t0 = time.monotonic()
    st.start_worker(
        "stallw",
        concurrency=2,
        env={"SVROBS_TEST_STALL_CONSUMER": "1", "SVROBS_WORKER_WATCHDOG_SECONDS": "0.5"},
    )
    job_id = submit_sweep(st, "stalled-consumer")["id"]
    status = wait_job_db(st, job_id, timeout=120)
    assert status == "succeeded", st.log_tail("stallw")
    log = (st.logs / "stallw.log").read_text(errors="replace")
    assert "TEST: consumer cancelled" in log, st.log_tail("stallw")
    # the watchdog saw messages waiting, a free process and nothing received, 3 times
    stalls = [x for x in log.splitlines() if "watchdog:" in x and "reconnecting" in x]
    assert stalls, st.log_tail("stallw")
    assert_one_result_per_cell(st, job_id, parse_spec(SWEEP).n_cells)
    n = assert_records_equal_reference(st, job_id, reference)
    assert st.children["stallw"].poll() is None
    RESULTS["2b_stalled_consumer"] = {
        "stalls_detected": len(stalls),
        "detail": stalls[0].split("watchdog: ")[1],
        "records_identical": n,
        "seconds": round(time.monotonic() - t0, 1),
    }


# --------------------------------------------------------------------------- 3. postgres


def _probe_api(base_url: str, key: str, job_id: int) -> list[tuple[str, int, str]]:
    """One request to each kind of route -> [(route, status, body)]."""
    out = []
    h = {"Authorization": f"Bearer {key}"}
    calls = [
        ("GET /jobs/{id}", "GET", f"/api/v1/jobs/{job_id}", None),
        ("GET /jobs", "GET", "/api/v1/jobs", None),
        ("GET /jobs/{id}/results", "GET", f"/api/v1/jobs/{job_id}/results", None),
        ("POST /jobs", "POST", "/api/v1/jobs", TINY),
        ("GET /readyz", "GET", "/readyz", None),
    ]
    with httpx.Client(base_url=base_url, timeout=20, headers=h) as c:
        for label, method, path, body in calls:
            r = c.request(method, path, json=body)
            out.append((label, r.status_code, r.text))
    return out


def test_postgres_restart_mid_sweep(stack_up, reference):
    st = stack_up
    t0 = time.monotonic()
    n_units = len(plan_units(parse_spec(SWEEP)))
    st.start_worker("pgw", concurrency=2)
    st.start_beat("beat", tick_seconds=1)
    job_id = submit_sweep(st, "pg-restart")["id"]
    wait_progress(st, job_id, n_units // 4, timeout=90)
    done_before = job_progress(st, job_id)[1]
    st.dispose()

    pg = st.servers.pg
    t_stop = time.monotonic()
    pg.stop("fast")
    probes: list[tuple[str, int, str]] = []
    try:
        deadline = time.monotonic() + 6.0  # down for ~6 s; probe the API meanwhile
        rounds = 0
        while time.monotonic() < deadline and rounds < 50:
            rounds += 1
            probes += _probe_api(st.base_url, st.key, job_id)
            time.sleep(0.3)
    finally:
        pg.start()
    t_up = time.monotonic()
    assert probes, "no request made while PostgreSQL was down"
    for label, status, body in probes:
        assert status == 503, (label, status, body[:500])
        assert "Traceback" not in body and 'File "' not in body, body[:500]
        data = json.loads(body)  # a JSON error
        assert isinstance(data, dict) and data.get("detail"), data

    # recovers by itself: the same API process answers again, the sweep completes
    deadline = time.monotonic() + 60
    recovered = None
    while time.monotonic() < deadline:
        try:
            if all(
                s == 200
                for lbl, s, _ in _probe_api(st.base_url, st.key, job_id)
                if lbl != "POST /jobs"
            ):
                recovered = time.monotonic() - t_up
                break
        except httpx.HTTPError:
            pass
        time.sleep(0.25)
    assert recovered is not None, f"the API did not recover\n{st.log_tail('api')}"
    status = wait_job_db(st, job_id, timeout=150)
    assert status == "succeeded", st.log_tail("pgw", "beat")
    assert_one_result_per_cell(st, job_id, parse_spec(SWEEP).n_cells)
    n = assert_records_equal_reference(st, job_id, reference)
    for name in ("api", "pgw", "beat"):
        assert st.children[name].poll() is None, f"{name} died with the database"
    api_log = (st.logs / "api.log").read_text(errors="replace")
    assert "Traceback" not in api_log, api_log[-3000:]
    # the POSTs answered 503 while the DB was down wrote nothing; their jobs (if the
    # database had committed them) would have to run too
    RESULTS["3_postgres_restart"] = {
        "restarts_survived": 1,
        "pg_down_s": round(t_up - t_stop, 1),
        "requests_while_down": len(probes),
        "statuses_while_down": sorted({s for _, s, _ in probes}),
        "api_recovered_after_s": round(recovered, 2),
        "units_done_before_restart": done_before,
        "units": n_units,
        "sweep_done_after_restart_s": round(time.monotonic() - t_up, 1),
        "records_identical": n,
        "seconds": round(time.monotonic() - t0, 1),
    }


# --------------------------------------------------------------------------- 4. API kill


def test_api_killed_during_submission_burst(stack_up):
    st = stack_up
    t0 = time.monotonic()
    st.start_worker("apiw", concurrency=2)
    st.start_beat("beat", tick_seconds=1)  # the relay publishes what the dead API did not
    base = st.base_url
    outcomes: dict[str, dict] = {}  # Idempotency-Key -> {"status", "job"}
    lock = threading.Lock()
    stop = threading.Event()
    accepted = threading.Semaphore(0)

    def client(i: int) -> None:
        with httpx.Client(
            base_url=base + "/api/v1", timeout=10, headers={"Authorization": f"Bearer {st.key}"}
        ) as c:
            for n in range(200):  # bounded
                if stop.is_set():
                    return
                key = f"burst-{i}-{n}-{uuid.uuid4().hex[:8]}"
                try:
                    r = c.post(
                        "/jobs", json={**TINY, "name": key}, headers={"Idempotency-Key": key}
                    )
                    res = {
                        "status": r.status_code,
                        "job": r.json().get("id") if r.status_code == 202 else None,
                    }
                except httpx.HTTPError as exc:
                    res = {"status": None, "error": type(exc).__name__}
                with lock:
                    outcomes[key] = res
                if res["status"] == 202:
                    accepted.release()
                elif res["status"] is None:
                    return  # the API is gone
                else:
                    raise AssertionError(res)

    threads = [threading.Thread(target=client, args=(i,), daemon=True) for i in range(6)]
    for t in threads:
        t.start()
    for _ in range(15):  # let some submissions through, then kill the API mid-burst
        assert accepted.acquire(timeout=30), "the burst does not get through"
    st.children["api"].kill_group()
    killed_at = time.monotonic()
    stop.set()
    for t in threads:
        t.join(timeout=30)
    assert not any(t.is_alive() for t in threads)
    st.stop("api", grace=1)

    restarted_at = datetime.now(UTC)
    st.start_api()  # a new API process (new port); the clients retry what got no answer
    lost = [k for k, v in outcomes.items() if v["status"] is None]
    with st.client() as c:
        for key in lost:
            r = c.post("/jobs", json={**TINY, "name": key}, headers={"Idempotency-Key": key})
            assert r.status_code == 202, r.text
            outcomes[key] = {"status": 202, "job": r.json()["id"], "retried": True}
        jobs = {k: v["job"] for k, v in outcomes.items()}
        assert all(v["status"] == 202 for v in outcomes.values())
        for job_id in jobs.values():
            assert st.wait_job(c, job_id, timeout=90)["status"] == "succeeded"

    # the DB holds exactly these jobs: none lost, none doubled by a retry
    rows = st.sql("SELECT id, idempotency_key FROM jobs WHERE name LIKE 'burst-%'")
    assert sorted(r[0] for r in rows) == sorted(set(jobs.values()))
    assert {r[1]: r[0] for r in rows} == jobs
    # no half-written job: every job row has all its work units
    half = st.sql(
        "SELECT j.id, j.progress_total, count(u.id) FROM jobs j LEFT JOIN work_units u "
        "ON u.job_id = j.id GROUP BY j.id, j.progress_total "
        "HAVING count(u.id) = 0 OR count(u.id) <> j.progress_total"
    )
    assert not half, half
    per_job = len(plan_units(parse_spec(TINY)))
    # requests cut by the kill whose job had been committed: the retry returned that job
    committed_unanswered = st.sql(
        "SELECT count(*) FROM jobs WHERE idempotency_key = ANY(:keys) AND created_at < :t",
        keys=lost or [""],
        t=restarted_at,
    )[0][0]
    unpublished = st.sql(
        "SELECT count(*) FROM work_units WHERE job_id = ANY(:ids) AND status <> 'done'",
        ids=list(jobs.values()),
    )[0][0]
    assert unpublished == 0
    RESULTS["4_api_killed_during_burst"] = {
        "api_kills_survived": 1,
        "jobs_accepted": len(jobs),
        "accepted_before_kill": sum(1 for v in outcomes.values() if not v.get("retried")),
        "requests_cut_by_kill_then_retried": len(lost),
        "of_which_committed_before_the_kill": committed_unanswered,
        "units": len(jobs) * per_job,
        "lost": 0,
        "duplicated": 0,
        "seconds": round(time.monotonic() - t0, 1),
        "recovery_to_all_done_s": round(time.monotonic() - killed_at, 1),
    }


# --------------------------------------------------------------------------- 5. two beats


def test_two_beats_one_job_per_due_time(stack_up):
    st = stack_up
    t0 = time.monotonic()
    names = [f"twobeats-{i}-{uuid.uuid4().hex[:6]}" for i in range(3)]
    with st.client() as c:
        ids = []
        for name in names:
            r = c.post(
                "/schedules",
                json={"name": name, "cron": "* * * * *", "timezone": "UTC", "spec_template": TINY},
            )
            assert r.status_code in (200, 201), r.text
            ids.append(r.json()["id"])
    # created an hour ago: the current minute is due at once, every minute after it too
    st.sql(
        "UPDATE schedules SET created_at = created_at - interval '1 hour' WHERE id = ANY(:ids)",
        ids=ids,
    )
    st.start_worker("beatw", concurrency=2)
    for b in ("beat-a", "beat-b"):  # two schedulers at once, ticking twice a second
        st.start_beat(b, tick_seconds=0.5)
    # the first due time (the minute running when the beats first ticked) ...
    deadline = time.monotonic() + 60
    first = []
    while time.monotonic() < deadline and len(first) < len(ids):
        first = st.sql(
            "SELECT schedule_id, min(due_at) FROM schedule_runs "
            "WHERE schedule_id = ANY(:ids) GROUP BY schedule_id",
            ids=ids,
        )
        time.sleep(0.2)
    assert len(first) == len(ids), f"the beats created no run\n{st.log_tail('beat-a')}"
    first_due = max(r[1] for r in first)
    # ... and the next one: keep both beats ticking until 6 s past it (at most ~70 s)
    end = first_due.timestamp() + 60 + 6.0
    deadline = time.monotonic() + 75
    while time.time() < end and time.monotonic() < deadline:
        for b in ("beat-a", "beat-b"):
            assert st.children[b].poll() is None, st.log_tail(b)
        time.sleep(0.5)
    st.stop("beat-a", grace=5)
    st.stop("beat-b", grace=5)

    runs = st.sql(
        "SELECT schedule_id, due_at, job_id FROM schedule_runs "
        "WHERE schedule_id = ANY(:ids) ORDER BY schedule_id, due_at",
        ids=ids,
    )
    jobs = st.sql("SELECT schedule_id, id, name FROM jobs WHERE schedule_id = ANY(:ids)", ids=ids)
    per_sched = {i: [r for r in runs if r[0] == i] for i in ids}
    for i, rs in per_sched.items():
        dues = [r[1].timestamp() for r in rs]
        # consecutive minutes, one run each, from the minute running at the first tick
        # through the next one
        assert dues == [dues[0] + 60 * k for k in range(len(dues))], (i, dues)
        assert {first_due.timestamp(), first_due.timestamp() + 60} <= set(dues), (i, dues)
        assert all(r[2] is not None for r in rs), rs
    assert len(jobs) == len(runs) >= 2 * len(ids), (jobs, runs)
    assert len({j[2] for j in jobs}) == len(jobs), "two jobs for one due time"
    with st.client() as c:
        for _, job_id, _ in jobs:
            assert st.wait_job(c, job_id, timeout=60)["status"] == "succeeded"
    for b in ("beat-a", "beat-b"):
        assert log_count(st, b, "beat: Starting") == 1
    RESULTS["5_two_beats"] = {
        "beats": 2,
        "schedules": len(ids),
        "due_times": len(runs) // len(ids),
        "jobs": len(jobs),
        "runs": len(runs),
        "seconds": round(time.monotonic() - t0, 1),
    }


# --------------------------------------------------------------------------- 6. poison unit


def test_unit_that_kills_its_worker_fails_after_k_attempts(stack_up):
    st = stack_up
    t0 = time.monotonic()
    k = 3
    spec = {**TINY, "sigma_w": [0.5, 1.0, 2.0, 4.0], "N": [30]}  # 4 units, one per sigma_w
    assert len(plan_units(parse_spec(spec))) == 4
    with st.client() as c:
        job = submit(c, spec, name="poison")  # no worker yet: nothing runs
    job_id = job["id"]
    ((unit_id,),) = st.sql("SELECT id FROM work_units WHERE job_id = :j AND index = 2", j=job_id)
    st.start_worker(
        "poisonw",
        concurrency=1,
        env={"SVROBS_TEST_CRASH_UNIT": str(unit_id), "SVROBS_MAX_UNIT_ATTEMPTS": str(k)},
    )
    assert wait_job_db(st, job_id, timeout=90) == "failed", st.log_tail("poisonw")
    with st.client() as c:
        final = c.get(f"/jobs/{job_id}").json()
    err = final["error"] or ""
    # which cells: unit 2 is (paper-stable, sigma_w=2.0, N=30, reps 0..1); and why
    assert "unit 2" in err and "system=paper-stable" in err and "sigma_w=2.0" in err, err
    assert "N=[30]" in err and "reps 0..1" in err, err
    assert f"gave up after {k} attempts" in err and "worker died" in err, err
    # what killed it, recorded by the worker's main process (worker.tasks.UnitRequest)
    assert "WorkerLostError: Worker exited prematurely: exitcode 1" in err, err
    units = dict(st.sql("SELECT index, status FROM work_units WHERE job_id = :j", j=job_id))
    assert units[2] == "failed", units
    assert set(units.values()) <= {"done", "failed", "cancelled"}, units
    ((attempts,),) = st.sql("SELECT attempts FROM work_units WHERE id = :u", u=unit_id)
    assert attempts == k
    crashes = log_count(st, "poisonw", "exited with 'exitcode 1'")
    assert crashes == k, crashes
    assert st.children["poisonw"].poll() is None  # the worker itself lives on
    # the failed unit stored nothing; the others stored all their cells
    n_done = sum(1 for s in units.values() if s == "done")
    ((stored,),) = st.sql("SELECT count(*) FROM results WHERE job_id = :j", j=job_id)
    per_unit = parse_spec(spec).n_cells // len(units)
    assert stored == n_done * per_unit
    RESULTS["6_poison_unit"] = {
        "k": k,
        "worker_deaths": crashes,
        "attempts_recorded": attempts,
        "job_error": err,
        "seconds": round(time.monotonic() - t0, 1),
    }
