"""What fuzzing the API found (tests/fuzz): input that must be a clear error, not a 500.

* N/rep result filters beyond 32 bits overflow the driver (SQLite and PostgreSQL).
* NUL characters in query parameters and bodies: PostgreSQL text cannot hold them.
* Lone surrogates (valid JSON escapes, not UTF-8) inside the free-form spec, once
  stored, would make every response carrying the spec fail to serialise: the job or
  schedule a permanent 500 for the team's listings.
* A body that is not UTF-8 is a 422, as malformed JSON is (not an undocumented 400).
* An error echoing an unencodable key must still render.
"""

from __future__ import annotations

import json

import pytest
from sqlalchemy import func, select

from service.db.models import Job, Schedule
from tests.service.svc_fakes import run_job_units
from tests.service.svc_helpers import SMALL_SPEC

API = "/api/v1"
SURROGATE = "\ud800"


def _count(session, model, team_id):
    return session.scalar(select(func.count(model.id)).where(model.team_id == team_id))


def _post_raw(client, url, body, acc):
    """A JSON body as text, so lone surrogates travel as \\ud800 escapes."""
    return client.post(
        url, content=json.dumps(body), headers={**acc.headers, "Content-Type": "application/json"}
    )


def _assert_422(r, field):
    assert r.status_code == 422, r.text
    assert r.json()["field"] == field, r.text
    assert r.json()["detail"]


@pytest.mark.parametrize("param", ["N", "rep"])
@pytest.mark.parametrize("value", [2**31, -(2**31) - 1, 2**63, 10**30])
def test_integer_filters_out_of_range_are_422(client, session, make_account, param, value):
    acc = make_account()
    jid = client.post(f"{API}/jobs", json=SMALL_SPEC, headers=acc.headers).json()["id"]
    for fmt in ("json", "csv"):
        r = client.get(
            f"{API}/jobs/{jid}/results", params={param: value, "format": fmt}, headers=acc.headers
        )
        _assert_422(r, f"{param}[0]")
    ok = client.get(f"{API}/jobs/{jid}/results", params={param: 2**31 - 1}, headers=acc.headers)
    assert ok.status_code == 200 and ok.json()["total"] == 0


def test_nul_in_query_parameters_is_422(client, session, make_account):
    acc = make_account()
    jid = client.post(f"{API}/jobs", json=SMALL_SPEC, headers=acc.headers).json()["id"]
    run_job_units(session, jid)
    for url, params, field in [
        (f"{API}/jobs", {"tag": "a\x00b"}, "tag"),
        (f"{API}/jobs", {"owner": "\x00"}, "owner"),
        (f"{API}/jobs/{jid}/results", {"system": "paper-stable\x00"}, "system"),
        (f"{API}/jobs/{jid}/results", {"estimator": "ols\x00", "format": "csv"}, "estimator"),
        (f"{API}/compare", {"jobs": str(jid), "metric": "rmse_A\x00"}, "metric"),
    ]:
        _assert_422(client.get(url, params=params, headers=acc.headers), field)
    r = client.get(
        f"{API}/jobs/{jid}/results", params={"system": "paper-stable"}, headers=acc.headers
    )
    assert r.status_code == 200 and r.json()["total"] > 0


def test_nul_and_surrogates_in_job_bodies_are_422_and_nothing_written(
    client, session, make_account, publisher
):
    acc = make_account()
    custom = {"name": "x", "A": [[0.5]], "B": [[1.0]]}
    for body, field in [
        ({**SMALL_SPEC, "name": "a\x00b"}, "name"),
        ({**SMALL_SPEC, "tags": ["ok", "t\x00"]}, "tags[1]"),
        ({**SMALL_SPEC, "name": SURROGATE}, "name"),
        ({**SMALL_SPEC, "systems": [{**custom, "name": "x" + SURROGATE}]}, "systems[0].name"),
        ({**SMALL_SPEC, "systems": [{**custom, "name": "x\x00"}]}, "systems[0].name"),
        ({**SMALL_SPEC, "sls": {"T_fir": 5, SURROGATE: 1}}, "sls"),
        # names are printable: no terminal escape, line break or C1 control
        ({**SMALL_SPEC, "name": "run \x1b[2J"}, "name"),
        ({**SMALL_SPEC, "tags": ["ok", "a\nb"]}, "tags[1]"),
        ({**SMALL_SPEC, "systems": [{**custom, "name": "x\x9b"}]}, "systems[0].name"),
    ]:
        _assert_422(_post_raw(client, f"{API}/jobs", body, acc), field)
    r = client.post(
        f"{API}/jobs", json=SMALL_SPEC, headers={**acc.headers, "Idempotency-Key": "k\x00"}
    )
    _assert_422(r, "Idempotency-Key")
    assert _count(session, Job, acc.team.id) == 0 and publisher.calls == []
    assert client.get(f"{API}/jobs", headers=acc.headers).status_code == 200


def test_nul_and_surrogates_in_schedule_bodies_are_422(client, session, make_account):
    acc = make_account()
    good = {"name": "n", "cron": "0 2 * * *", "spec_template": SMALL_SPEC}
    custom = {"name": "x" + SURROGATE, "A": [[0.5]], "B": [[1.0]]}
    for body, field in [
        ({**good, "name": "n\x00"}, "name"),
        ({**good, "name": "n\u2028x"}, "name"),
        ({**good, "tags": ["\x00"]}, "tags[0]"),
        ({**good, "timezone": "UTC\x00"}, "timezone"),
        (
            {**good, "spec_template": {**SMALL_SPEC, "systems": [custom]}},
            "spec_template.systems[0].name",
        ),
        ({**good, "spec_template": {**SMALL_SPEC, "k\x00": 1}}, "spec_template"),
    ]:
        _assert_422(_post_raw(client, f"{API}/schedules", body, acc), field)
    assert _count(session, Schedule, acc.team.id) == 0
    sid = client.post(f"{API}/schedules", json=good, headers=acc.headers).json()["id"]
    r = client.patch(
        f"{API}/schedules/{sid}",
        content=json.dumps({"spec_template": {**SMALL_SPEC, "systems": [custom]}}),
        headers={**acc.headers, "Content-Type": "application/json"},
    )
    _assert_422(r, "spec_template.systems[0].name")
    assert client.get(f"{API}/schedules", headers=acc.headers).status_code == 200


def test_body_that_is_not_utf8_is_422(client, make_account):
    acc = make_account()
    for url in (f"{API}/jobs", f"{API}/schedules", f"{API}/presets/paper-section-6/run"):
        r = client.post(
            url,
            content=b'{"name": "\xff\xfe"}',
            headers={**acc.headers, "Content-Type": "application/json"},
        )
        _assert_422(r, "body")


def test_error_echoing_an_unencodable_key_still_renders(client, make_account):
    acc = make_account()
    r = _post_raw(client, f"{API}/presets/paper-section-6/run", {SURROGATE: 1}, acc)
    assert r.status_code == 422
    assert r.json()["detail"]


def test_openapi_documents_error_media_types_and_413(client):
    spec = client.get("/openapi.json").json()
    report = spec["paths"]["/api/v1/jobs/{job_id}/report"]["get"]["responses"]
    assert list(report["200"]["content"]) == ["text/html"]
    for code in ("401", "404", "422"):
        assert list(report[code]["content"]) == ["application/json"]
    for path, method in [
        ("/api/v1/jobs", "post"),
        ("/api/v1/schedules", "post"),
        ("/api/v1/schedules/{schedule_id}", "patch"),
        ("/api/v1/presets/paper-section-6/run", "post"),
    ]:
        assert "413" in spec["paths"][path][method]["responses"], (path, method)
    assert "409" in spec["paths"]["/api/v1/jobs"]["post"]["responses"]


def test_preset_run_idempotency_key_reused_with_another_scale_is_409(client, session, make_account):
    # found by the PostgreSQL fuzz pass: errors.IdempotencyConflict escaped as a 500
    acc = make_account()
    h = {**acc.headers, "Idempotency-Key": "paper"}
    url = f"{API}/presets/paper-section-6/run"
    first = client.post(url, json={"scale": "reduced", "experiments": ["E1"]}, headers=h)
    assert first.status_code == 202
    again = client.post(url, json={"scale": "reduced", "experiments": ["E1"]}, headers=h)
    assert again.status_code == 202 and again.json()[0]["id"] == first.json()[0]["id"]
    r = client.post(url, json={"scale": "full", "experiments": ["E2", "E1"]}, headers=h)
    assert r.status_code == 409 and r.json()["field"] == "Idempotency-Key", r.text
    assert _count(session, Job, acc.team.id) == 1  # E2 of the failed request rolled back


@pytest.mark.parametrize("field", ["reps", "T0", "seed", "mc_runs", "mc_reps", "horizon"])
@pytest.mark.parametrize("value", [2**63, 10**30])
def test_huge_integers_in_a_spec_are_422_naming_the_field(
    client, session, make_account, field, value
):
    """Every integer field is bounded before it reaches numpy (a C long) or the database."""
    acc = make_account()
    spec = {**SMALL_SPEC, "stages": ["estimate", "bounds", "gain", "cost"], field: value}
    r = client.post(f"{API}/jobs", json=spec, headers=acc.headers)
    _assert_422(r, field)
    assert "must be <=" in r.json()["detail"]


def test_a_negative_gamma_filter_is_422_not_the_ols_rows(client, session, make_account):
    """OLS is stored under gamma -1: a typed -1 must not select it."""
    acc = make_account()
    jid = client.post(f"{API}/jobs", json=SMALL_SPEC, headers=acc.headers).json()["id"]
    run_job_units(session, jid)
    url = f"{API}/jobs/{jid}/results"
    ols = client.get(url, params={"gamma": "ols"}, headers=acc.headers).json()
    assert ols["total"] > 0 and {r["estimator"] for r in ols["items"]} == {"ols"}
    for value in ("-1", "-1.0", "-0.5"):
        r = client.get(url, params={"gamma": value}, headers=acc.headers)
        _assert_422(r, "gamma")
        assert "'null' for OLS" in r.json()["detail"]
