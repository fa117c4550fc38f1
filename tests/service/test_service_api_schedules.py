"""REST: schedules CRUD and validation."""

from __future__ import annotations

from sqlalchemy import func, select

from service.db.models import Schedule
from tests.service.svc_helpers import SMALL_SPEC

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
