"""REST: unknown query parameters, results sort and range filters
(against an independent sort/filter of the JSONL export), the bearer scheme and the
offline docs, plain-words union errors, and the schedules' seed policy."""

from __future__ import annotations

import json
import re
from datetime import UTC, datetime, timedelta

import pytest
from sqlalchemy import select

from service.config import get_settings
from service.db import schedules
from service.db.models import Schedule
from svrobs_lab import schedules as lab_schedules
from tests.service import test_service_api_results as results_tests
from tests.service.svc_helpers import SMALL_SPEC

API = "/api/v1"


# a finished job of SMALL_SPEC: (account, job id, its records as stored)
done_job = results_tests.done_job


def _export(client, acc, jid) -> list[dict]:
    """The job's JSONL export: the oracle the sorted and filtered pages are checked on."""
    export = client.get(f"{API}/jobs/{jid}/results?format=jsonl", headers=acc.headers)
    assert export.status_code == 200
    return [json.loads(line) for line in export.text.splitlines()]


def _all(client, acc, jid, params):
    """Every record of a sorted/filtered selection, through JSON pages of 7."""
    out, offset = [], 0
    while True:
        page = client.get(
            f"{API}/jobs/{jid}/results",
            params={**params, "limit": 7, "offset": offset},
            headers=acc.headers,
        )
        assert page.status_code == 200, page.text
        body = page.json()
        out += body["items"]
        offset += 7
        if offset >= body["total"]:
            return out, body["total"]


def test_unknown_query_parameters_are_422_naming_them(client, done_job):
    acc, jid, _ = done_job
    for url, name in (
        (f"{API}/jobs?sort=-rmse_A", "sort"),
        (f"{API}/jobs/{jid}?verbose=1", "verbose"),
        (f"{API}/jobs/{jid}/summary?metric=rmse_A", "metric"),
        (f"{API}/jobs/{jid}/results?rmse_A_below=0.1", "rmse_A_below"),
        (f"{API}/jobs/{jid}/results?notes_lt=1", "notes_lt"),  # not a numeric field
        (f"{API}/jobs/{jid}/results?certified_lt=1", "certified_lt"),  # a boolean
        (f"{API}/compare?jobs={jid}&metric=rmse_A&group=N", "group"),
        (f"{API}/schedules?page=2", "page"),
        (f"{API}/presets?x=1", "x"),
        ("/healthz?probe=1", "probe"),
    ):
        r = client.get(url, headers=acc.headers)
        assert r.status_code == 422, (url, r.text)
        assert r.json()["field"] == name and repr(name) in r.json()["detail"], r.text
    # declared parameters and range filters on numeric fields pass
    ok = client.get(f"{API}/jobs/{jid}/results?N=20&rmse_A_lt=10&sort=N", headers=acc.headers)
    assert ok.status_code == 200, ok.text


@pytest.mark.parametrize("field", ["rmse_A", "H_B", "N"])
@pytest.mark.parametrize("desc", [False, True])
def test_sort_matches_an_independent_sort_of_the_export(client, done_job, field, desc):
    acc, jid, _ = done_job
    export = _export(client, acc, jid)
    got, total = _all(client, acc, jid, {"sort": ("-" if desc else "") + field})
    assert total == len(export) == len(got)
    values = [r[field] for r in got]
    present = [v for v in values if v is not None]
    assert present == sorted((r[field] for r in export if r[field] is not None), reverse=desc)
    assert values[len(present) :] == [None] * (len(values) - len(present))  # nulls last
    assert sorted(map(json.dumps, got)) == sorted(map(json.dumps, export))  # same records


def test_range_filters_match_a_filter_of_the_export(client, done_job):
    acc, jid, _ = done_job
    export = _export(client, acc, jid)
    vals = sorted(r["rmse_A"] for r in export if r["rmse_A"] is not None)
    lo, hi = vals[len(vals) // 4], vals[3 * len(vals) // 4]
    got, total = _all(
        client, acc, jid, {"rmse_A_gte": lo, "rmse_A_lt": hi, "N_gt": 20, "sort": "-rmse_A"}
    )
    want = [r for r in export if r["rmse_A"] is not None and lo <= r["rmse_A"] < hi and r["N"] > 20]
    assert 0 < total == len(want)
    assert [r["rmse_A"] for r in got] == sorted((r["rmse_A"] for r in want), reverse=True)
    csv_body = client.get(
        f"{API}/jobs/{jid}/results",
        params={"format": "csv", "rmse_A_gte": lo, "rmse_A_lt": hi, "N_gt": 20},
        headers=acc.headers,
    ).text
    assert len(csv_body.strip().splitlines()) == 1 + len(want)
    for bad, msg in (("abc", "must be a number"), ("nan", "must be finite")):
        r = client.get(f"{API}/jobs/{jid}/results?rmse_A_lt={bad}", headers=acc.headers)
        assert r.status_code == 422 and r.json() == {"detail": msg, "field": "rmse_A_lt"}
    r = client.get(f"{API}/jobs/{jid}/results?sort=-notes", headers=acc.headers)
    assert r.status_code == 422 and r.json()["field"] == "sort"


def test_openapi_declares_bearer_and_docs_load_locally(client, make_account):
    spec = client.get("/openapi.json").json()
    assert spec["components"]["securitySchemes"]["HTTPBearer"] == {
        "type": "http",
        "scheme": "bearer",
        "description": spec["components"]["securitySchemes"]["HTTPBearer"]["description"],
    }
    assert {"HTTPBearer": []} in spec["paths"]["/api/v1/jobs"]["get"]["security"]
    for page in ("/docs", "/redoc"):
        html = client.get(page).text
        urls = re.findall(r"""(?:src|href|url)\s*[:=]\s*["']([^"']+)""", html)
        assert urls and all(u.startswith(("/", "data:")) for u in urls), urls
        for u in urls:
            if not u.startswith("data:"):
                asset = client.get(u)
                assert asset.status_code == 200, u
                assert "cdn." not in asset.text and "fonts.googleapis" not in asset.text, u
    # the 401 bodies are unchanged by the declared scheme
    r = client.get(f"{API}/jobs", headers={"Authorization": "Basic abc"})
    assert r.status_code == 401 and "missing API key" in r.json()["detail"]
    r = client.get(f"{API}/jobs", headers={"Authorization": "Bearer nope"})
    assert r.status_code == 401 and r.json()["detail"] == "invalid, revoked or expired API key"


def test_N_as_a_string_is_a_plain_words_error(client, make_account):
    acc = make_account()
    r = client.post(f"{API}/jobs", json={**SMALL_SPEC, "N": "100"}, headers=acc.headers)
    assert r.status_code == 422
    body = r.json()
    assert body["field"] == "N" and body["detail"] == "must be a list or an object"
    assert "list[" not in r.text and "dict[" not in r.text


def test_seed_policy_due_time_derives_the_seed_from_the_due_time(client, session, make_account):
    acc = make_account()
    ids = {}
    for policy in ("fixed", "due-time"):
        body = {
            "name": f"nightly-{policy}",
            "cron": "0 2 * * *",
            "spec_template": SMALL_SPEC,
            **({"seed_policy": policy} if policy != "fixed" else {}),
        }
        r = client.post(f"{API}/schedules", json=body, headers=acc.headers)
        assert r.status_code == 201, r.text
        assert r.json()["seed_policy"] == policy  # fixed is the default
        ids[policy] = r.json()["id"]
    bad = client.patch(
        f"{API}/schedules/{ids['fixed']}", json={"seed_policy": "random"}, headers=acc.headers
    )
    assert bad.status_code == 422 and bad.json()["field"] == "seed_policy"
    for s in session.scalars(select(Schedule).where(Schedule.id.in_(ids.values()))):
        s.created_at = datetime(2024, 1, 1, tzinfo=UTC)
    session.flush()
    day1 = datetime(2024, 6, 1, 2, 30, tzinfo=UTC)
    seeds = {policy: [] for policy in ids}
    for d in (0, 1):
        made = {
            j.schedule_id: j
            for j in lab_schedules.create_due_jobs(
                get_settings(), session, day1 + timedelta(days=d)
            )
        }
        for policy, sid in ids.items():
            seeds[policy].append(made[sid].spec["seed"])
    assert seeds["fixed"] == [SMALL_SPEC["seed"]] * 2
    due0 = int(datetime(2024, 6, 1, 2, 0, tzinfo=UTC).timestamp())
    assert seeds["due-time"] == [(SMALL_SPEC["seed"] + due0 + d * 86400) % 2**31 for d in (0, 1)]
    assert len(set(seeds["due-time"])) == 2
    # the same due time gives the same seed (the rule is a function of it alone)
    template = session.get(Schedule, ids["due-time"]).spec_template
    again = schedules.run_spec(template, "due-time", datetime(2024, 6, 1, 2, 0, tzinfo=UTC))
    assert again["seed"] == seeds["due-time"][0]
    assert schedules.run_spec(template, "fixed", day1) is template
