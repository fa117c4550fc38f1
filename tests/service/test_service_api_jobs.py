"""REST: submit, list, get, cancel; validation; idempotency; isolation between teams."""

from __future__ import annotations

import json

from sqlalchemy import func, select

from service.config import Settings
from service.db import jobs, outbox
from service.db.models import ApiKey, Job, WorkUnit
from tests.service.svc_fakes import run_job_units
from tests.service.svc_helpers import SMALL_SPEC, SMALL_UNITS

API = "/api/v1"


def _jobs(session, team_id):
    return session.scalar(select(func.count(Job.id)).where(Job.team_id == team_id))


def submit(client, acc, body=None, **kw):
    return client.post(
        f"{API}/jobs",
        json=body if body is not None else SMALL_SPEC,
        headers={**acc.headers, **kw.pop("headers", {})},
        **kw,
    )


def test_submit_publishes_after_commit(client, publisher, session, make_account):
    acc = make_account()
    r = submit(client, acc, {**SMALL_SPEC, "name": "first", "tags": ["nightly", "x"]})
    assert r.status_code == 202, r.text
    job = r.json()
    assert job["status"] == "queued" and job["name"] == "first"
    assert job["tags"] == ["nightly", "x"] and job["owner"] == acc.user.email
    assert job["progress"] == {"done": 0, "total": SMALL_UNITS, "fraction": 0.0}
    assert job["spec"]["seed"] == 7 and job["n_cells"] == 72
    units = jobs.unit_ids_of_job(session, job["id"], pending_only=False)
    cap = Settings().fair_share()[0]  # the team alone: the pool's size
    assert publisher.published == units[:cap]
    assert (
        outbox.units_to_publish(session, retry_seconds=600) == units[cap:]
    )  # the rest: as units finish


def test_submit_while_broker_down_still_202_and_relay_sends(build_client, session, make_account):
    client, publisher = build_client()
    publisher.fail = True
    acc = make_account()
    r = submit(client, acc)
    assert r.status_code == 202
    units = jobs.unit_ids_of_job(session, r.json()["id"])
    assert set(units) <= set(outbox.units_to_publish(session, retry_seconds=600))


def test_idempotency_key_same_job_one_set_of_units(client, publisher, session, make_account):
    acc = make_account()
    h = {"Idempotency-Key": "abc-123"}
    a = submit(client, acc, headers=h)
    b = submit(client, acc, headers=h)
    assert a.status_code == b.status_code == 202
    assert a.json()["id"] == b.json()["id"]
    assert _jobs(session, acc.team.id) == 1
    assert (
        session.scalar(select(func.count(WorkUnit.id)).where(WorkUnit.job_id == a.json()["id"]))
        == SMALL_UNITS
    )
    assert len(publisher.calls) == 1
    c = submit(client, acc, {**SMALL_SPEC, "seed": 99}, headers=h)
    assert c.status_code == 409 and c.json()["field"] == "Idempotency-Key"


# 100,000 cells of an hour or more of CPU (the N axis up to 100,000 samples)
CPU_HEAVY = {
    "systems": ["paper-stable"],
    "sigma_w": [1.0],
    "N": {"start": 1, "stop": 100_000},
    "estimators": ["ols"],
}


def _assert_422(r, field):
    assert r.status_code == 422, r.text
    body = r.json()
    assert body["field"] == field, body
    assert body["detail"]


def test_bad_input_422_names_field_and_writes_nothing(client, publisher, session, make_account):
    acc = make_account()
    _assert_422(submit(client, acc, {**SMALL_SPEC, "gamma": [0.1, -2]}), "gamma[1]")
    _assert_422(
        submit(
            client,
            acc,
            {**SMALL_SPEC, "systems": ["paper-stable", {"name": "x", "A": [[1, 2]], "B": [[1]]}]},
        ),
        "systems[1].A",
    )
    _assert_422(submit(client, acc, {**SMALL_SPEC, "team_id": 5}), "team_id")
    _assert_422(submit(client, acc, {**SMALL_SPEC, "sls": {"T_fir": 5, "bogus": 1}}), "sls.bogus")
    _assert_422(submit(client, acc, {"sigma_w": [1], "N": [5]}), "systems")
    _assert_422(submit(client, acc, {**SMALL_SPEC, "tags": "notalist"}), "tags")
    # 600 million records: refused by the cell cap, from the axis lengths alone
    r = submit(client, acc, {**SMALL_SPEC, "reps": 10**6, "N": list(range(10, 60))})
    _assert_422(r, "spec")
    assert "SVROBS_MAX_JOB_CELLS" in r.json()["detail"]
    _assert_422(
        # under the cell cap, refused by its estimated work, naming the field that weighs most
        submit(client, acc, {**CPU_HEAVY, "reps": 1}),
        "N",
    )
    r = client.post(
        f"{API}/jobs",
        content=b"{not json",
        headers={**acc.headers, "Content-Type": "application/json"},
    )
    assert r.status_code == 422
    r = client.post(f"{API}/jobs", json=[1, 2], headers=acc.headers)
    assert r.status_code == 422
    assert _jobs(session, acc.team.id) == 0 and publisher.calls == []


def test_job_size_limit_from_settings(build_client, make_account, session):
    client, _ = build_client(MAX_JOB_CELLS=50)
    acc = make_account()
    r = submit(client, acc)
    _assert_422(r, "spec")
    assert "72 cells" in r.json()["detail"]
    assert _jobs(session, acc.team.id) == 0


def test_body_over_limit_413(build_client, make_account, session):
    client, _ = build_client(MAX_BODY_BYTES=2000)
    acc = make_account()
    big = {**SMALL_SPEC, "name": "x" * 150, "tags": ["t" * 90] * 40}
    r = submit(client, acc, big)
    assert r.status_code == 413 and "detail" in r.json()
    # a chunked body without Content-Length is counted too
    data = json.dumps(big).encode()

    def chunks():
        for i in range(0, len(data), 500):
            yield data[i : i + 500]

    r = client.post(
        f"{API}/jobs", content=chunks(), headers={**acc.headers, "Content-Type": "application/json"}
    )
    assert r.status_code == 413
    assert _jobs(session, acc.team.id) == 0


def test_queued_jobs_cap_429(build_client, make_account):
    client, _ = build_client(MAX_QUEUED_JOBS_PER_TEAM=2)
    acc = make_account()
    assert submit(client, acc).status_code == 202
    assert submit(client, acc).status_code == 202
    r = submit(client, acc)
    assert r.status_code == 429 and "SVROBS_MAX_QUEUED_JOBS_PER_TEAM" in r.json()["detail"]


def test_rate_limit_429(build_client, make_account):
    client, _ = build_client(RATE_LIMIT_PER_MINUTE=5)
    acc = make_account()
    codes = [client.get(f"{API}/jobs", headers=acc.headers).status_code for _ in range(8)]
    assert codes[:5] == [200] * 5 and 429 in codes[5:]
    r = client.get(f"{API}/jobs", headers=acc.headers)
    assert r.status_code == 429 and int(r.headers["Retry-After"]) >= 1
    other = make_account()  # per key
    assert client.get(f"{API}/jobs", headers=other.headers).status_code == 200


def test_list_filters_and_pagination(client, session, make_account):
    acc = make_account()
    ids = [
        submit(client, acc, {**SMALL_SPEC, "tags": ["even" if i % 2 == 0 else "odd"]}).json()["id"]
        for i in range(5)
    ]
    second_user = make_account()  # another team never shows up
    submit(client, second_user)
    r = client.get(f"{API}/jobs", params={"limit": 2}, headers=acc.headers).json()
    assert r["total"] == 5 and [j["id"] for j in r["items"]] == ids[::-1][:2]
    r = client.get(f"{API}/jobs", params={"limit": 2, "offset": 4}, headers=acc.headers).json()
    assert [j["id"] for j in r["items"]] == [ids[0]]
    r = client.get(f"{API}/jobs", params={"tag": "even"}, headers=acc.headers).json()
    assert sorted(j["id"] for j in r["items"]) == [ids[0], ids[2], ids[4]]
    client.post(f"{API}/jobs/{ids[1]}/cancel", headers=acc.headers)
    r = client.get(f"{API}/jobs", params={"status": "cancelled"}, headers=acc.headers).json()
    assert [j["id"] for j in r["items"]] == [ids[1]]
    r = client.get(f"{API}/jobs", params={"owner": "me"}, headers=acc.headers).json()
    assert r["total"] == 5
    r = client.get(f"{API}/jobs", params={"owner": "nobody@x.org"}, headers=acc.headers).json()
    assert r["total"] == 0
    assert (
        client.get(f"{API}/jobs", params={"status": "weird"}, headers=acc.headers).json()["field"]
        == "status"
    )


def test_get_and_cancel(client, session, make_account):
    acc = make_account()
    jid = submit(client, acc).json()["id"]
    r = client.get(f"{API}/jobs/{jid}", headers=acc.headers)
    assert r.status_code == 200 and r.json()["id"] == jid
    r = client.post(f"{API}/jobs/{jid}/cancel", headers=acc.headers)
    assert r.status_code == 200 and r.json()["status"] == "cancelled"
    assert outbox.units_to_publish(session, retry_seconds=600) == [] or all(
        session.get(WorkUnit, u).job_id != jid
        for u in outbox.units_to_publish(session, retry_seconds=600)
    )
    assert client.post(f"{API}/jobs/{jid}/cancel", headers=acc.headers).status_code == 200
    jid2 = submit(client, acc).json()["id"]
    run_job_units(session, jid2)
    r = client.get(f"{API}/jobs/{jid2}", headers=acc.headers).json()
    assert r["status"] == "succeeded" and r["progress"]["fraction"] == 1.0
    assert client.post(f"{API}/jobs/{jid2}/cancel", headers=acc.headers).status_code == 409


def test_other_team_gets_404_on_every_id_route(client, session, make_account):
    a, b = make_account(), make_account()
    jid = submit(client, a).json()["id"]
    run_job_units(session, jid)
    routes = [
        ("get", f"{API}/jobs/{jid}"),
        ("post", f"{API}/jobs/{jid}/cancel"),
        ("get", f"{API}/jobs/{jid}/results"),
        ("get", f"{API}/jobs/{jid}/results?format=csv"),
        ("get", f"{API}/jobs/{jid}/results?format=jsonl"),
        ("get", f"{API}/jobs/{jid}/summary"),
        ("get", f"{API}/compare?jobs={jid}&metric=rmse_A"),
    ]
    for method, url in routes:
        ok = (409,) if url.endswith("/cancel") else (200,)  # the job already succeeded
        assert getattr(client, method)(url, headers=a.headers).status_code in ok, url
        r = getattr(client, method)(url, headers=b.headers)
        assert r.status_code == 404, (url, r.status_code)
        assert str(jid) in r.json()["detail"]
    listed = client.get(f"{API}/jobs", headers=b.headers).json()
    assert listed["total"] == 0
    r = client.get(f"{API}/jobs/999999", headers=a.headers)
    assert r.status_code == 404
    # schedules too
    sid = client.post(
        f"{API}/schedules",
        headers=a.headers,
        json={"name": "n", "cron": "0 2 * * *", "spec_template": SMALL_SPEC},
    ).json()["id"]
    for method, url, kw in [
        ("get", f"{API}/schedules/{sid}", {}),
        ("patch", f"{API}/schedules/{sid}", {"json": {"enabled": False}}),
        ("get", f"{API}/schedules/{sid}/runs", {}),
        ("delete", f"{API}/schedules/{sid}", {}),
    ]:
        assert getattr(client, method)(url, headers=b.headers, **kw).status_code == 404, url
    assert client.get(f"{API}/schedules/{sid}", headers=a.headers).status_code == 200
    assert client.get(f"{API}/jobs/{jid}", headers=a.headers).json()["status"] == "succeeded"


def test_auth_required_and_keys_hashed(client, session, make_account):
    acc = make_account()
    assert client.get(f"{API}/jobs").status_code == 401
    assert client.get(f"{API}/jobs", headers={"Authorization": "Bearer nope"}).status_code == 401
    assert (
        client.get(f"{API}/jobs", headers={"Authorization": f"Bearer {acc.key}x"}).status_code
        == 401
    )
    assert (
        client.get(f"{API}/jobs", headers={"Authorization": f"Basic {acc.key}"}).status_code == 401
    )
    row = session.get(ApiKey, acc.key_row.id)
    assert acc.key not in (row.key_hash, row.prefix) and len(row.key_hash) == 64
    secret = acc.key.split("_", 2)[2]
    for r in session.execute(select(ApiKey.__table__)).all():
        assert all(secret not in str(v) for v in r)
