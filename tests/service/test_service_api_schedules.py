"""REST: schedules CRUD and validation."""

from __future__ import annotations

from sqlalchemy import func, select

from service.db.models import Schedule
from tests.service.svc_helpers import SMALL_SPEC, track_sessions

API = "/api/v1"


def _n(session, team_id):
    return session.scalar(select(func.count(Schedule.id)).where(Schedule.team_id == team_id))


def test_schedule_crud(client, session, make_account):
    acc = make_account()
    body = {
        "name": "nightly",
        "cron": "0 2 * * *",
        "timezone": "Europe/Paris",
        "spec_template": SMALL_SPEC,
        "tags": ["sweep"],
    }
    r = client.post(f"{API}/schedules", json=body, headers=acc.headers)
    assert r.status_code == 201, r.text
    s = r.json()
    assert s["enabled"] and s["next_run_at"] and s["timezone"] == "Europe/Paris"
    assert client.post(f"{API}/schedules", json=body, headers=acc.headers).status_code == 409
    lst = client.get(f"{API}/schedules", headers=acc.headers).json()
    assert [x["id"] for x in lst] == [s["id"]]
    r = client.patch(
        f"{API}/schedules/{s['id']}",
        json={"enabled": False, "cron": "*/10 * * * *"},
        headers=acc.headers,
    )
    assert r.status_code == 200 and r.json()["enabled"] is False and r.json()["next_run_at"] is None
    assert client.get(f"{API}/schedules/{s['id']}/runs", headers=acc.headers).json() == []
    assert client.delete(f"{API}/schedules/{s['id']}", headers=acc.headers).status_code == 204
    assert client.get(f"{API}/schedules/{s['id']}", headers=acc.headers).status_code == 404


def test_schedule_validation_422_nothing_written(client, session, make_account):
    acc = make_account()
    good = {"name": "n", "cron": "0 2 * * *", "spec_template": SMALL_SPEC}

    def post(**kw):
        r = client.post(f"{API}/schedules", json={**good, **kw}, headers=acc.headers)
        assert r.status_code == 422, r.text
        return r.json()["field"]

    assert post(cron="61 * * * *") == "cron"
    assert post(cron="every day") == "cron"
    assert post(cron="* * * * * *") == "cron"
    assert post(timezone="Mars/Olympus") == "timezone"
    assert post(timezone="../../etc/passwd") == "timezone"
    assert post(spec_template={**SMALL_SPEC, "N": [0]}) == "spec_template.N[0]"
    assert post(spec_template={**SMALL_SPEC, "colour": 1}) == "spec_template.colour"
    assert post(team_id=3) == "team_id"
    assert post(enabled="perhaps") == "enabled"
    assert _n(session, acc.team.id) == 0
    sid = client.post(f"{API}/schedules", json=good, headers=acc.headers).json()["id"]
    r = client.patch(f"{API}/schedules/{sid}", json={"cron": "bad"}, headers=acc.headers)
    assert r.status_code == 422 and r.json()["field"] == "cron"
    r = client.patch(f"{API}/schedules/{sid}", json={"cron": None}, headers=acc.headers)
    assert r.status_code == 422 and r.json()["field"] == "cron"
    assert client.get(f"{API}/schedules/{sid}", headers=acc.headers).json()["cron"] == "0 2 * * *"


def test_a_template_is_admitted_with_no_transaction_open(
    build_client, session_factory, make_account, monkeypatch
):
    """Admitting a template takes time that grows with its systems (0.2 s of CPU for
    22,000 in a 1 MB body, docs/performance.md#parsing-and-admitting-many-systems):
    creating or changing a schedule, or running it now from its page, does
    it with none of the request's sessions in a transaction, so a writing session on
    SQLite holds no write lock (every other team's writes waited for it) and
    PostgreSQL's quota lock of the team is not taken yet."""
    from service.db import jobs as job_store
    from svrobs_lab import schedules as lab
    from tests.web.helpers import csrf_of, sign_in

    client, _ = build_client(SECRET_KEY="test-secret-0123456789")
    opened = track_sessions(client.app, session_factory)
    in_transaction: list[bool] = []

    def watched(admit):
        def admit_watched(*args, **kwargs):
            in_transaction.append(any(s.in_transaction() for s in opened))
            return admit(*args, **kwargs)

        return admit_watched

    monkeypatch.setattr(lab, "admit_spec", watched(lab.admit_spec))
    monkeypatch.setattr(job_store, "admit", watched(job_store.admit))
    acc = make_account()
    body = {"name": "n", "cron": "0 2 * * *", "spec_template": SMALL_SPEC}
    made = client.post(f"{API}/schedules", json=body, headers=acc.headers)
    assert made.status_code == 201, made.text
    sid = made.json()["id"]
    changed = client.patch(
        f"{API}/schedules/{sid}",
        json={"spec_template": {**SMALL_SPEC, "reps": 2}, "name": "m"},
        headers=acc.headers,
    )
    assert changed.status_code == 200 and changed.json()["name"] == "m", changed.text
    assert changed.json()["spec_template"]["reps"] == 2
    sign_in(client, acc.key)
    token = csrf_of(client.get(f"/schedules/{sid}").text)
    ran = client.post(f"/schedules/{sid}/run", data={"csrf_token": token}, follow_redirects=False)
    assert ran.status_code == 303, ran.text
    assert in_transaction == [False, False, False]
