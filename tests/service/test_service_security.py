"""Security checks not covered elsewhere: the constant-time key
compare behind the prefix lookup, the expiry boundary, mass assignment on every body,
and the queued-jobs cap on the preset route. (Revocation, expiry, per-key rate limit,
body limit, the jobs cap, cross-team 404s and JSON-only Celery are tested in
test_service_auth, test_service_api_jobs and test_service_broker; the fuzzer covers
cross-team access for every id route.)"""

from __future__ import annotations

import hmac
from datetime import timedelta

import pytest
from sqlalchemy import func, select

from service.db import accounts
from service.db.accounts import authenticate, hash_key
from service.db.models import Job, Schedule, utcnow
from tests.service.svc_helpers import SMALL_SPEC

API = "/api/v1"


@pytest.fixture
def compare_spy(monkeypatch):
    calls = []
    real = hmac.compare_digest

    def spy(a, b):
        calls.append((a, b))
        return real(a, b)

    monkeypatch.setattr(accounts.hmac, "compare_digest", spy)
    return calls


def _wrong_secret(key: str) -> str:
    scheme, prefix, secret = key.split("_", 2)
    return f"{scheme}_{prefix}_{'x' if secret[0] != 'x' else 'y'}{secret[1:]}"


def test_right_prefix_wrong_secret_is_rejected_by_constant_time_compare(
    session, make_account, compare_spy
):
    acc = make_account()
    bad = _wrong_secret(acc.key)
    assert accounts.split_key(bad) == acc.key_row.prefix  # the lookup finds the row
    assert authenticate(session, bad) is None
    assert compare_spy == [(acc.key_row.key_hash, hash_key(bad))]
    compare_spy.clear()
    assert authenticate(session, acc.key).id == acc.key_row.id
    assert compare_spy == [(acc.key_row.key_hash, hash_key(acc.key))]


def test_unknown_or_malformed_keys_do_the_same_compare(session, compare_spy):
    # a miss costs one compare too, so timing does not tell a known prefix from an unknown
    for key in ("svr_zzzzzzzz_secret", "not-a-key", ""):
        compare_spy.clear()
        assert authenticate(session, key) is None
        assert len(compare_spy) == 1 and compare_spy[0][0] == accounts._DUMMY_HASH


def test_key_of_one_user_with_secret_of_another_is_401(client, make_account):
    a, b = make_account(), make_account()
    mixed = f"svr_{a.key_row.prefix}_{b.key.split('_', 2)[2]}"
    r = client.get(f"{API}/jobs", headers={"Authorization": f"Bearer {mixed}"})
    assert r.status_code == 401 and r.headers["WWW-Authenticate"] == "Bearer"
    unknown = client.get(f"{API}/jobs", headers={"Authorization": "Bearer svr_zzzzzzzz_x"})
    assert r.json() == unknown.json()  # indistinguishable from an unknown key
    r = client.get(f"{API}/jobs", headers={"Authorization": f"Bearer {_wrong_secret(a.key)}"})
    assert r.status_code == 401


def test_expiry_boundary(session, make_account):
    expires = utcnow() + timedelta(hours=1)
    acc = make_account(expires_at=expires)
    assert authenticate(session, acc.key, now=expires - timedelta(seconds=1)) is not None
    assert authenticate(session, acc.key, now=expires) is None
    assert authenticate(session, acc.key, now=expires + timedelta(days=1)) is None


def _n(session, model, team_id):
    return session.scalar(select(func.count(model.id)).where(model.team_id == team_id))


SERVER_FIELDS = {
    "id": 1,
    "team_id": 1,
    "user_id": 1,
    "owner": "boss@x.org",
    "status": "succeeded",
    "progress": {"done": 8, "total": 8},
    "progress_done": 8,
    "progress_total": 8,
    "n_cells": 1,
    "provenance": {},
    "error": None,
    "created_at": "2020-01-01T00:00:00Z",
    "finished_at": "2020-01-01T00:00:00Z",
    "schedule_id": 1,
    "idempotency_key": "k",
}


@pytest.mark.parametrize("field", sorted(SERVER_FIELDS))
def test_mass_assignment_on_job_submit_is_422(client, session, make_account, publisher, field):
    acc = make_account()
    r = client.post(
        f"{API}/jobs", json={**SMALL_SPEC, field: SERVER_FIELDS[field]}, headers=acc.headers
    )
    assert r.status_code == 422, r.text
    assert r.json()["field"] == field and r.json()["detail"] == "unknown field"
    assert _n(session, Job, acc.team.id) == 0 and publisher.calls == []


@pytest.mark.parametrize(
    "field", ["id", "team_id", "user_id", "owner", "created_at", "updated_at", "next_run_at"]
)
def test_mass_assignment_on_schedules_is_422(client, session, make_account, field):
    acc, other = make_account(), make_account()
    good = {"name": "n", "cron": "0 2 * * *", "spec_template": SMALL_SPEC}
    value = other.team.id if field == "team_id" else SERVER_FIELDS.get(field, "2020-01-01")
    r = client.post(f"{API}/schedules", json={**good, field: value}, headers=acc.headers)
    assert r.status_code == 422 and r.json()["field"] == field, r.text
    assert _n(session, Schedule, acc.team.id) == 0
    sid = client.post(f"{API}/schedules", json=good, headers=acc.headers).json()["id"]
    before = client.get(f"{API}/schedules/{sid}", headers=acc.headers).json()
    r = client.patch(
        f"{API}/schedules/{sid}", json={"enabled": False, field: value}, headers=acc.headers
    )
    assert r.status_code == 422 and r.json()["field"] == field, r.text
    assert client.get(f"{API}/schedules/{sid}", headers=acc.headers).json() == before
    assert _n(session, Schedule, other.team.id) == 0


def test_team_and_owner_always_come_from_the_key(client, session, make_account):
    acc = make_account()
    jid = client.post(f"{API}/jobs", json=SMALL_SPEC, headers=acc.headers).json()["id"]
    job = session.get(Job, jid)
    assert (job.team_id, job.user_id) == (acc.team.id, acc.user.id)
    sid = client.post(
        f"{API}/schedules",
        headers=acc.headers,
        json={"name": "n", "cron": "0 2 * * *", "spec_template": SMALL_SPEC},
    ).json()["id"]
    s = session.get(Schedule, sid)
    assert (s.team_id, s.user_id) == (acc.team.id, acc.user.id)


def test_preset_run_respects_the_queued_jobs_cap_atomically(build_client, session, make_account):
    client, publisher = build_client(MAX_QUEUED_JOBS_PER_TEAM=2)
    acc = make_account()
    r = client.post(
        f"{API}/presets/paper-section-6/run", json={"scale": "reduced"}, headers=acc.headers
    )  # four jobs, over a cap of two
    assert r.status_code == 429 and "SVROBS_MAX_QUEUED_JOBS_PER_TEAM" in r.json()["detail"]
    assert _n(session, Job, acc.team.id) == 0 and publisher.calls == []
    r = client.post(
        f"{API}/presets/paper-section-6/run",
        json={"scale": "reduced", "experiments": ["E1", "E2"]},
        headers=acc.headers,
    )
    assert r.status_code == 202 and len(r.json()) == 2
