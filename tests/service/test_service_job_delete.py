"""DELETE /jobs/{id} and service.db.job_delete: one transaction removes the job, its
units, results, summaries and tags; 409 while queued/running; team-scoped."""

from __future__ import annotations

from sqlalchemy import func, select

from service.db.models import Job, JobTag, Result, Summary, WorkUnit
from tests.service.svc_fakes import run_job_units
from tests.service.svc_helpers import SMALL_SPEC

API = "/api/v1"


def _count(session, model, job_id) -> int:
    col = model.id if model is Job else model.job_id
    return session.scalar(select(func.count()).select_from(model).where(col == job_id))


def _submit(client, acc) -> int:
    r = client.post(f"{API}/jobs", json={**SMALL_SPEC, "tags": ["t1"]}, headers=acc.headers)
    assert r.status_code == 202, r.text
    return r.json()["id"]


def test_delete_finished_job_removes_every_row_and_leaves_others(client, session, make_account):
    acc = make_account()
    jid, other = _submit(client, acc), _submit(client, acc)
    run_job_units(session, jid)
    run_job_units(session, other)
    before = {m: _count(session, m, jid) for m in (Job, WorkUnit, Result, Summary, JobTag)}
    assert all(before.values()), before  # there is something of every kind to delete
    kept = {m: _count(session, m, other) for m in (Job, WorkUnit, Result, Summary, JobTag)}
    r = client.delete(f"{API}/jobs/{jid}", headers=acc.headers)
    assert r.status_code == 204 and r.content == b""
    session.expire_all()
    assert {m: _count(session, m, jid) for m in before} == dict.fromkeys(before, 0)
    assert {m: _count(session, m, other) for m in kept} == kept
    assert client.get(f"{API}/jobs/{jid}", headers=acc.headers).status_code == 404
    assert client.delete(f"{API}/jobs/{jid}", headers=acc.headers).status_code == 404


def test_delete_refused_while_queued_then_allowed_once_cancelled(client, session, make_account):
    acc = make_account()
    jid = _submit(client, acc)
    r = client.delete(f"{API}/jobs/{jid}", headers=acc.headers)
    assert r.status_code == 409 and "cancel it" in r.json()["detail"]
    assert _count(session, WorkUnit, jid) > 0
    assert client.post(f"{API}/jobs/{jid}/cancel", headers=acc.headers).status_code == 200
    assert client.delete(f"{API}/jobs/{jid}", headers=acc.headers).status_code == 204
    session.expire_all()
    assert _count(session, WorkUnit, jid) == 0 and _count(session, Job, jid) == 0


def test_another_teams_job_cannot_be_deleted(client, session, make_account):
    a, b = make_account(), make_account()
    jid = _submit(client, a)
    run_job_units(session, jid)
    assert client.delete(f"{API}/jobs/{jid}", headers=b.headers).status_code == 404
    session.expire_all()
    assert _count(session, Job, jid) == 1 and _count(session, Result, jid) > 0
