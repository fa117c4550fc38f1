"""A team's quotas hold under concurrent requests, through real processes (embedded
stack, and PostgreSQL + Redis when the SVROBS_TEST_* URLs are set): 50 submits at
once against a cap of 5 queued jobs and 20 schedule creates at once against a cap
of 3 schedules are accepted exactly up to the cap; the rest are refused naming the
setting (docs/architecture.md#one-job)."""

from __future__ import annotations

import threading
from concurrent.futures import ThreadPoolExecutor

import httpx
import pytest

from tests.service.svc_helpers import TINY_SPEC

from .stack import API
from .test_trust import second_team

pytestmark = [pytest.mark.integration, pytest.mark.timeout(300)]

JOB_CAP, SCHEDULE_CAP = 5, 3


@pytest.fixture(scope="module")
def capped(stack):
    """A second API process with the caps lowered (and no rate limit in the way)."""
    env = {
        "SVROBS_MAX_QUEUED_JOBS_PER_TEAM": str(JOB_CAP),
        "SVROBS_MAX_SCHEDULES_PER_TEAM": str(SCHEDULE_CAP),
        "SVROBS_RATE_LIMIT_PER_MINUTE": "100000",
    }
    url = stack.start_api("api-capped", env=env)
    yield url
    stack.stop("api-capped")


def at_once(n: int, url: str, key: str, send) -> list[httpx.Response]:
    """``send(client, i)`` for i < n from n threads released together, each with its
    own connection."""
    barrier = threading.Barrier(n)

    def one(i):
        with httpx.Client(
            base_url=url + API, timeout=120, headers={"Authorization": f"Bearer {key}"}
        ) as c:
            c.get("/jobs", params={"limit": 1})  # connected and authenticated first
            barrier.wait()
            return send(c, i)

    with ThreadPoolExecutor(n) as pool:
        return list(pool.map(one, range(n)))


def test_parallel_submits_stop_at_the_queued_jobs_cap(stack, capped):
    key = second_team(stack, "quota-jobs")
    stack.stop("worker1", grace=5)  # no job finishes (and frees a slot) meanwhile
    try:
        rs = at_once(50, capped, key, lambda c, i: c.post("/jobs", json={**TINY_SPEC, "seed": i}))
        accepted = [r.json()["id"] for r in rs if r.status_code == 202]
        refused = [r for r in rs if r.status_code != 202]
        assert len(accepted) == JOB_CAP, [r.status_code for r in rs]
        for r in refused:
            assert r.status_code == 429, r.text
            assert "SVROBS_MAX_QUEUED_JOBS_PER_TEAM" in r.json()["detail"], r.text
        with httpx.Client(
            base_url=capped + API, timeout=30, headers={"Authorization": f"Bearer {key}"}
        ) as c:
            listed = c.get("/jobs", params={"limit": 100}).json()
            assert sorted(j["id"] for j in listed["items"]) == sorted(accepted)
            assert listed["total"] == JOB_CAP
            for job_id in accepted:
                assert c.post(f"/jobs/{job_id}/cancel").status_code == 200
    finally:
        stack.start_worker()
    print(f"\n[{stack.kind}] 50 parallel submits, cap {JOB_CAP}: {len(accepted)} accepted")


def test_parallel_schedule_creates_stop_at_the_schedules_cap(stack, capped):
    key = second_team(stack, "quota-schedules")

    def create(c, i):
        body = {"name": f"nightly-{i}", "cron": "0 2 * * *", "spec_template": TINY_SPEC}
        return c.post("/schedules", json=body)

    rs = at_once(20, capped, key, create)
    made = [r for r in rs if r.status_code == 201]
    refused = [r for r in rs if r.status_code != 201]
    assert len(made) == SCHEDULE_CAP, [(r.status_code, r.text[:80]) for r in rs]
    for r in refused:
        assert r.status_code == 422, r.text
        assert "SVROBS_MAX_SCHEDULES_PER_TEAM" in r.json()["detail"], r.text
    with httpx.Client(
        base_url=capped + API, timeout=30, headers={"Authorization": f"Bearer {key}"}
    ) as c:
        listed = c.get("/schedules").json()
        items = listed["items"] if isinstance(listed, dict) else listed
        assert sorted(s["id"] for s in items) == sorted(r.json()["id"] for r in made)
    print(f"\n[{stack.kind}] 20 parallel schedule creates, cap {SCHEDULE_CAP}: {len(made)} made")
