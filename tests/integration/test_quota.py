"""A team's quotas hold under concurrent requests, through real processes (embedded
stack, and PostgreSQL + Redis when the SVROBS_TEST_* URLs are set): 50 submits at
once against a cap of 5 queued jobs, 20 schedule creates at once against a cap
of 3 schedules, 12 dataset uploads at once against a cap of 3 datasets and 20 share
links of one job at once against a cap of 3 live links are accepted exactly up to
the cap; the rest are refused naming the setting (docs/architecture.md#one-job,
docs/datasets.md#limits, docs/security.md)."""

from __future__ import annotations

import threading
from concurrent.futures import ThreadPoolExecutor

import httpx
import pytest

from tests.datasets import files
from tests.service.svc_helpers import TINY_SPEC

from .stack import API
from .test_trust import second_team

pytestmark = [pytest.mark.integration, pytest.mark.timeout(300)]

JOB_CAP, SCHEDULE_CAP, DATASET_CAP, SHARE_CAP = 5, 3, 3, 3


@pytest.fixture(scope="module")
def capped(stack):
    """A second API process with the caps lowered (and no rate limit in the way)."""
    env = {
        "SVROBS_MAX_QUEUED_JOBS_PER_TEAM": str(JOB_CAP),
        "SVROBS_MAX_SCHEDULES_PER_TEAM": str(SCHEDULE_CAP),
        "SVROBS_MAX_DATASETS_PER_TEAM": str(DATASET_CAP),
        "SVROBS_MAX_SHARES_PER_JOB": str(SHARE_CAP),
        "SVROBS_UPLOADS_PER_TEAM": "100",
        "SVROBS_UPLOADS_AT_ONCE": "100",
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


def made_up_to_the_cap(rs, cap: int, setting: str, url: str, key: str, listing: str):
    """Exactly ``cap`` of ``rs`` made (201), the rest 422 naming ``setting``, and the
    team's ``listing`` holds exactly the ones made."""
    made = [r for r in rs if r.status_code == 201]
    assert len(made) == cap, [(r.status_code, r.text[:80]) for r in rs]
    for r in rs:
        if r.status_code != 201:
            assert r.status_code == 422 and setting in r.json()["detail"], r.text
    with httpx.Client(
        base_url=url + API, timeout=30, headers={"Authorization": f"Bearer {key}"}
    ) as c:
        listed = c.get(listing).json()
        items = listed["items"] if isinstance(listed, dict) else listed
        assert sorted(s["id"] for s in items) == sorted(r.json()["id"] for r in made)
    return made


def test_parallel_schedule_creates_stop_at_the_schedules_cap(stack, capped):
    key = second_team(stack, "quota-schedules")

    def create(c, i):
        body = {"name": f"nightly-{i}", "cron": "0 2 * * *", "spec_template": TINY_SPEC}
        return c.post("/schedules", json=body)

    rs = at_once(20, capped, key, create)
    setting = "SVROBS_MAX_SCHEDULES_PER_TEAM"
    made = made_up_to_the_cap(rs, SCHEDULE_CAP, setting, capped, key, "/schedules")
    print(f"\n[{stack.kind}] 20 parallel schedule creates, cap {SCHEDULE_CAP}: {len(made)} made")


def test_parallel_uploads_stop_at_the_datasets_cap(stack, capped):
    key = second_team(stack, "quota-datasets")
    data = files.csv_bytes(*files.rollouts(lengths=(200, 300)))

    def send(c, i):
        return c.post("/datasets", files={"file": ("r.csv", data)}, data={"name": f"r{i}"})

    rs = at_once(12, capped, key, send)
    setting = "SVROBS_MAX_DATASETS_PER_TEAM"
    made = made_up_to_the_cap(rs, DATASET_CAP, setting, capped, key, "/datasets?limit=100")
    print(f"\n[{stack.kind}] 12 parallel uploads, cap {DATASET_CAP}: {len(made)} stored")


def test_parallel_share_creates_stop_at_the_shares_cap(stack, capped):
    key = second_team(stack, "quota-shares")
    with httpx.Client(
        base_url=capped + API, timeout=30, headers={"Authorization": f"Bearer {key}"}
    ) as c:
        job_id = c.post("/jobs", json=TINY_SPEC).json()["id"]

    rs = at_once(20, capped, key, lambda c, i: c.post(f"/jobs/{job_id}/shares", json={}))
    setting = "SVROBS_MAX_SHARES_PER_JOB"
    made = made_up_to_the_cap(rs, SHARE_CAP, setting, capped, key, f"/jobs/{job_id}/shares")
    print(f"\n[{stack.kind}] 20 parallel share creates, cap {SHARE_CAP}: {len(made)} made")
