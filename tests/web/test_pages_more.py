"""The results, compare, schedules and share pages through the app (TestClient): the
grid's filters and sort equal the API's, compare's table is the API's compare, a
schedule made from a job's spec, and share links (no key needed; expired, revoked or
another team's is a 404; token stored hashed); a posted form's empty field is not
given."""

from __future__ import annotations

import html
import json
import re
from datetime import UTC, datetime, timedelta

import pytest
from fastapi.testclient import TestClient
from sqlalchemy import select

from service.config import get_settings
from service.db.models import Job, Schedule, ShareLink, utcnow
from service.db.shares import token_hash
from svrobs_lab import schedules as lab_schedules
from svrobs_lab import shares
from tests.service.svc_fakes import run_job_units
from tests.service.svc_helpers import SMALL_SPEC

from .helpers import csrf_of, sign_in

API = "/api/v1"
CELL = re.compile(r'<td class="num" data-field="rmse_A" data-value="([^"]*)">')
ID_CELL = re.compile(r'data-field="(\w+)" data-value="([^"]*)"')


@pytest.fixture
def web(build_client):
    return build_client(SECRET_KEY="pages-secret-0123456789")[0]


@pytest.fixture
def done(web, session, make_account):
    acc = make_account()
    ids = []
    for seed in (7, 8):
        r = web.post(f"{API}/jobs", json={**SMALL_SPEC, "seed": seed}, headers=acc.headers)
        ids.append(r.json()["id"])
        run_job_units(session, ids[-1])
    sign_in(web, acc.key)
    return acc, ids


def _grid_rows(text: str) -> list[dict]:
    rows = []
    for tr in re.findall(r"<tr>(<td.*?)</tr>", text, re.S):
        rows.append(dict(ID_CELL.findall(tr)))
    return rows


def test_results_grid_filters_and_sorts_like_the_api(web, done):
    acc, (jid, _) = done
    q = "system=paper-stable&N=40&rf=rmse_A&rmin=0&rmax=1e9&sort=-rmse_A"
    page = web.get(f"/results?job={jid}&{q}")
    assert page.status_code == 200, page.text
    api = web.get(
        f"{API}/jobs/{jid}/results?system=paper-stable&N=40&rmse_A_gte=0&rmse_A_lt=1e9"
        "&sort=-rmse_A&limit=50",
        headers=acc.headers,
    ).json()
    got = _grid_rows(page.text)
    assert len(got) == min(50, api["total"]) > 0
    assert [float(r["rmse_A"]) for r in got] == [r["rmse_A"] for r in api["items"][: len(got)]]
    assert {r["system"] for r in got} == {"paper-stable"} and {r["N"] for r in got} == {"40"}
    partial = web.get(f"/results/rows?job={jid}&{q}")  # the htmx partial: same grid
    assert _grid_rows(partial.text) == got and "<html" not in partial.text
    bad = web.get(f"/results/rows?job={jid}&rf=rmse_A&rmax=abc")
    assert "rmse_A_lt: must be a number" in bad.text


def test_compare_page_table_is_the_api_compare(web, done):
    acc, ids = done
    page = web.get(f"/compare?jobs={ids[0]}&jobs={ids[1]}&metric=rmse_A&x=N")
    assert page.status_code == 200, page.text
    api = web.get(
        f"{API}/compare?jobs={ids[0]},{ids[1]}&metric=rmse_A&by=N,estimator,gamma",
        headers=acc.headers,
    ).json()
    embedded = json.loads(html.unescape(re.search(r'data-compare="([^"]+)"', page.text).group(1)))
    assert embedded["rows"] == api["rows"] and embedded["x"] == "N"
    assert page.text.count('<tr><td><a href="/jobs/') == len(api["rows"])
    # the chart says what each mean pools: here the systems and noise levels too
    pooled = re.search(r'id="compare-pooled">([^<]*)<', page.text)[1]
    assert "pooled over system and σ_w" in html.unescape(pooled), pooled
    every = "&by=".join(("system", "sigma_w", "estimator", "gamma"))
    kept = web.get(f"/compare?jobs={ids[0]}&metric=rmse_A&by={every}").text
    assert "pooled over" not in re.search(r'id="compare-pooled">([^<]*)<', kept)[1]
    # the API's comma form of ``by`` is the same view as its checkboxes
    commas = web.get(f"/compare?jobs={ids[0]},{ids[1]}&metric=rmse_A&by=N,estimator,gamma")
    same = web.get(f"/compare?jobs={ids[0]}&jobs={ids[1]}&metric=rmse_A&by=N&by=estimator&by=gamma")
    assert commas.status_code == same.status_code == 200
    assert commas.text == same.text
    for name in ("N", "estimator", "gamma"):
        assert re.search(rf'name="by" value="{name}"[^>]*checked', commas.text), name


def test_a_chosen_job_older_than_the_listed_newest_is_listed_as_chosen(web, done, session):
    """The compare page, the results page and a new schedule list the team's 200 newest
    jobs: a job chosen (compared, opened, scheduled) that is older than those is listed
    too, chosen, so the form sends it again and the page describes it."""
    acc, (a, b) = done
    first = session.get(Job, a)
    session.add_all(
        Job(team_id=first.team_id, user_id=first.user_id, name=f"newer {i}", spec=first.spec)
        for i in range(200)
    )
    session.commit()
    page = web.get(f"/compare?jobs={a}&jobs={b}&metric=rmse_A").text
    assert set(re.findall(r'name="jobs" value="(\d+)" checked', page)) == {str(a), str(b)}
    assert "(2 older ones compared, then 200 of the team's newest)" in page
    described = json.loads(html.unescape(re.search(r'data-jobs="([^"]+)"', page)[1]))
    assert [j["id"] for j in described] == [a, b]  # their specs: the labels and the diff
    for path, box in (
        (f"/results?job={a}", "results-job"),
        (f"/schedules/new?job={a}", "schedule-job"),
    ):
        options = re.search(
            rf'<select name="job" id="{box}">(.*?)</select>', web.get(path).text, re.S
        )
        assert re.findall(r'<option value="(\d+)" selected>', options[1]) == [str(a)], path


def test_compare_says_which_jobs_are_still_running(web, done, session):
    """A job compared while queued or running is named with its progress: its lines are
    the cells done so far."""
    acc, (a, _) = done
    queued = web.post(f"{API}/jobs", json={**SMALL_SPEC, "seed": 9}, headers=acc.headers).json()
    page = web.get(f"/compare?jobs={a}&jobs={queued['id']}&metric=rmse_A").text
    note = re.search(r'<p class="flash warn" id="compare-unfinished">(.*?)</p>', page, re.S)
    assert note is not None, page[-3000:]
    cells = f"{queued['n_cells']:,}"
    assert note[1] == (
        f"Job {queued['id']} is queued (0 of {cells} cells done): its lines hold the cells"
        " done so far; reload the page for more."
    )
    assert 'id="compare-unfinished"' not in web.get(f"/compare?jobs={a}&metric=rmse_A").text


def test_runs_table_sorts_shows_a_metric_and_deletes_the_ticked(web, done, session):
    acc, (a, b) = done
    noisy = {**SMALL_SPEC, "sigma_w": [4.0], "seed": 3}  # a job whose RMSE differs
    r = web.post(f"{API}/jobs", json=noisy, headers=acc.headers)
    run_job_units(session, r.json()["id"])
    means = {}
    for jid in (a, b, r.json()["id"]):  # the oracle: the cells' own values at N = 40
        items = web.get(
            f"{API}/jobs/{jid}/results", params={"N": 40, "limit": 1000}, headers=acc.headers
        ).json()["items"]
        values = [r["rmse_A"] for r in items if r["rmse_A"] is not None]
        means[jid] = sum(values) / len(values)
    page = web.get("/jobs?metric=rmse_A&at=40&sort=-metric").text
    shown = dict(
        re.findall(r'<tr id="job-(\d+)".*?data-col="metric" data-value="([^"]*)"', page, re.S)
    )
    assert {int(k): float(v) for k, v in shown.items()} == pytest.approx(means, rel=1e-12)
    order = [int(i) for i in re.findall(r'<tr id="job-(\d+)"', page)]
    assert order == sorted(means, key=lambda j: (means[j], j), reverse=True)  # ties: newest
    assert len(set(means.values())) == 2
    assert 'aria-sort="descending"' in page and "RMSE Â at N = 40" in page
    asc = web.get("/jobs?metric=rmse_A&at=40&sort=metric").text
    asc_order = [int(i) for i in re.findall(r'<tr id="job-(\d+)"', asc)]
    assert asc_order == sorted(means, key=lambda j: (means[j], -j))
    by_name = web.get("/jobs?sort=name,-id").text  # two keys
    assert "<sup>1</sup>" in by_name and "<sup>2</sup>" in by_name
    assert web.get("/jobs?sort=owner").status_code == 422
    assert web.get("/jobs?metric=N&at=10").status_code == 422  # a grid coordinate
    confirm = web.get(f"/jobs/delete?jobs={a}&jobs={b}")
    assert confirm.status_code == 200 and "Delete 2 jobs?" in confirm.text
    token = csrf_of(confirm.text)
    gone = web.post(
        "/jobs/delete", data={"csrf_token": token, "jobs": [a, b]}, follow_redirects=False
    )
    assert gone.headers["location"] == f"/jobs?deleted={a},{b}"
    assert f"Jobs {a}, {b} deleted." in web.get(gone.headers["location"]).text
    assert web.get(f"{API}/jobs/{a}", headers=acc.headers).status_code == 404
    assert web.post("/jobs/delete", data={"jobs": [a]}).status_code == 403  # no CSRF


def test_schedule_from_a_job(web, done, session):
    acc, (jid, _) = done
    form = web.get(f"/schedules/new?job={jid}")
    token = csrf_of(form.text)
    data = {"csrf_token": token, "job": jid, "name": "nightly", "cron": "0 3 * * *"}
    bad = web.post("/schedules/new", data={**data, "cron": "every night"})
    assert bad.status_code == 422 and "cron:" in bad.text
    no_csrf = {k: v for k, v in data.items() if k != "csrf_token"}
    assert web.post("/schedules/new", data=no_csrf).status_code == 403
    assert web.get(f"{API}/schedules", headers=acc.headers).json() == []
    made = web.post(
        "/schedules/new", data={**data, "seed_policy": "due-time"}, follow_redirects=False
    )
    assert made.status_code == 303, made.text
    (s,) = web.get(f"{API}/schedules", headers=acc.headers).json()
    job = web.get(f"{API}/jobs/{jid}", headers=acc.headers).json()
    assert s["spec_template"] == job["spec"] and s["seed_policy"] == "due-time"
    page = web.get(made.headers["location"])
    assert "due-time" in page.text and "No runs yet" in page.text
    row = session.get(Schedule, s["id"])
    row.created_at = datetime(2024, 1, 1, tzinfo=UTC)
    session.commit()
    (run_job,) = lab_schedules.create_due_jobs(
        get_settings(), session, datetime(2024, 6, 1, 4, tzinfo=UTC)
    )
    session.commit()
    page = web.get(made.headers["location"])
    assert f'<a href="/jobs/{run_job.id}">job {run_job.id}</a>' in page.text
    assert run_job.spec["seed"] != job["spec"]["seed"]  # due-time: a fresh seed
    web.post(f"/schedules/{s['id']}/enabled", data={"csrf_token": token, "enabled": "no"})
    assert web.get(f"{API}/schedules/{s['id']}", headers=acc.headers).json()["enabled"] is False


def test_schedule_form_errors_at_once_edit_and_run_now(web, done):
    acc, (jid, _) = done
    token = csrf_of(web.get(f"/schedules/new?job={jid}").text)
    data = {"csrf_token": token, "job": jid, "name": "", "cron": "every night"}
    bad = web.post("/schedules/new", data={**data, "timezone": "Mars/Olympus", "tags": "x" * 101})
    assert bad.status_code == 422
    errors = dict(re.findall(r'id="err-(\w+)">\w+: ([^<]*)</p>', bad.text))
    assert set(errors) == {"name", "cron", "timezone", "tags"}, errors  # all four at once
    assert "5 fields" in errors["cron"] and "Mars/Olympus" in html.unescape(errors["timezone"])
    assert errors["name"] == "must not be empty"  # in plain words, not pydantic's
    assert errors["tags"] == "must be at most 100 characters long"
    good = {**data, "name": "nightly", "cron": "0 3 * * *", "timezone": "Europe/Paris"}
    made = web.post("/schedules/new", data=good, follow_redirects=False)
    assert made.status_code == 303, made.text
    sid = int(made.headers["location"].rsplit("/", 1)[1])
    page = web.get(f"/schedules/{sid}").text
    assert "Europe/Paris (" in page and " UTC)" in page  # the next run in its own zone
    edit = {"csrf_token": token, "name": "nightly", "cron": "@hourly", "timezone": "Nope"}
    refused = web.post(f"/schedules/{sid}/edit", data={**edit, "seed_policy": "often"})
    assert refused.status_code == 422
    assert set(re.findall(r'id="err-(\w+)"', refused.text)) == {"timezone", "seed_policy"}
    ok = {**edit, "timezone": "UTC", "seed_policy": "due-time", "tags": "a, b", "name": "hourly"}
    saved = web.post(f"/schedules/{sid}/edit", data=ok, follow_redirects=False)
    assert saved.status_code == 303
    s = web.get(f"{API}/schedules/{sid}", headers=acc.headers).json()
    assert (s["name"], s["cron"], s["timezone"], s["seed_policy"], s["tags"]) == (
        "hourly",
        "@hourly",
        "UTC",
        "due-time",
        ["a", "b"],
    )
    ran = web.post(f"/schedules/{sid}/run", data={"csrf_token": token}, follow_redirects=False)
    assert ran.status_code == 303
    job = web.get(f"{API}{ran.headers['location']}", headers=acc.headers).json()
    assert job["schedule_id"] == sid and "schedule:hourly" in job["tags"]
    assert job["name"].startswith("hourly @ ") and job["name"].endswith("(run now)")
    assert {k: v for k, v in job["spec"].items() if k != "seed"} == {
        k: v for k, v in s["spec_template"].items() if k != "seed"
    }  # due-time: only the seed differs
    assert web.get(f"{API}/schedules/{sid}/runs", headers=acc.headers).json() == []
    assert web.post(f"/schedules/{sid}/run", data={}).status_code == 403  # no CSRF


def test_run_now_refusals_have_their_own_status(build_client, session, make_account):
    """Run now over the team's cap on queued jobs is a 429 page (not a 422 "spec
    refused"), and on a schedule deleted since its page was read a 404."""
    web = build_client(SECRET_KEY="pages-secret-0123456789", MAX_QUEUED_JOBS_PER_TEAM=1)[0]
    acc = make_account()
    spec = {**SMALL_SPEC, "seed": 1}
    assert web.post(f"{API}/jobs", json=spec, headers=acc.headers).status_code == 202
    body = {"name": "s", "cron": "0 2 * * *", "spec_template": spec}
    sid = web.post(f"{API}/schedules", json=body, headers=acc.headers).json()["id"]
    sign_in(web, acc.key)
    token = csrf_of(web.get(f"/schedules/{sid}").text)
    full = web.post(f"/schedules/{sid}/run", data={"csrf_token": token})
    assert full.status_code == 429 and "SVROBS_MAX_QUEUED_JOBS_PER_TEAM" in full.text
    assert web.delete(f"{API}/schedules/{sid}", headers=acc.headers).status_code == 204
    gone = web.post(f"/schedules/{sid}/run", data={"csrf_token": token})
    assert gone.status_code == 404


def test_share_link_lifecycle(web, done, session, make_account):
    acc, (jid, other_job) = done
    page = web.get(f"/jobs/{jid}/share")
    token = csrf_of(page.text)
    form = {"csrf_token": token, "days": "7", "label": " for the reviewers "}
    made = web.post(f"/jobs/{jid}/share", data=form, follow_redirects=False)
    assert made.status_code == 303  # POST-redirect-GET, the token in the fragment only
    where, _, fragment = made.headers["location"].partition("#new=")
    secret = fragment
    rows = session.scalars(select(ShareLink).where(ShareLink.job_id == jid)).all()
    assert where == f"/jobs/{jid}/share?created={rows[0].id}"
    assert [r.token_hash for r in rows] == [token_hash(secret)]  # stored hashed only
    assert rows[0].label == "for the reviewers"
    shown = web.get(where).text
    assert 'id="share-created" data-share="%d"' % rows[0].id in shown
    assert "“for the reviewers”" in shown and secret not in shown
    path = f"/s/{secret}"
    assert secret not in json.dumps([r.token_hash for r in rows])
    anon = TestClient(web.app)  # no cookie, no key
    opened = anon.get(path)
    assert opened.status_code == 200 and f"Job {jid}" in opened.text
    chart = anon.get(f"{path}/chart-data?metric=rmse_A&x=N").json()
    mine = web.get(f"/jobs/{jid}/chart-data?metric=rmse_A&x=N").json()
    assert chart == mine
    report = anon.get(f"{path}/report")
    assert report.status_code == 200
    # the back link, then the report as the page's one <main> landmark
    page = report.text
    assert 0 < page.index('id="back-link"') < page.index('<main id="main">')
    assert report.text.count("<main") == 1 and report.text.rstrip().endswith(
        "</main></body></html>"
    )
    signed_out = anon.get(f"/jobs/{jid}", follow_redirects=False)  # the link opens nothing else
    assert signed_out.status_code == 303 and signed_out.headers["location"].startswith("/login")
    assert anon.get("/s/" + "x" * 43).status_code == 404
    # another team cannot revoke it; the owner can, and then it is a 404
    other = make_account()
    stranger = TestClient(web.app)
    sign_in(stranger, other.key)
    stoken = csrf_of(stranger.get("/jobs").text)
    assert (
        stranger.post(f"/shares/{rows[0].id}/revoke", data={"csrf_token": stoken}).status_code
        == 404
    )
    for page_path in (
        f"/jobs/{jid}/share",
        f"/results?job={jid}",
        f"/results/rows?job={jid}",
        f"/compare?jobs={jid}&metric=rmse_A",
        f"/schedules/new?job={jid}",
    ):
        assert stranger.get(page_path).status_code == 404, page_path  # not this team's
    assert web.post(f"/shares/{rows[0].id}/revoke", data={}).status_code == 403  # no CSRF
    assert anon.get(path).status_code == 200
    web.post(f"/shares/{rows[0].id}/revoke", data={"csrf_token": token})
    for p in (path, f"{path}/chart-data", f"{path}/report"):
        assert anon.get(p).status_code == 404, p
    # an expired link is a 404 too
    r = web.post(f"{API}/jobs/{jid}/shares", json={"days": 1}, headers=acc.headers)
    assert r.status_code == 201, r.text
    late = r.json()["url"].split("testserver", 1)[1]
    assert anon.get(late).status_code == 200
    link = session.get(ShareLink, r.json()["id"])
    link.expires_at = utcnow() - timedelta(seconds=1)
    session.commit()
    assert anon.get(late).status_code == 404
    listed = web.get(f"{API}/jobs/{jid}/shares", headers=acc.headers).json()
    assert [s["live"] for s in listed] == [False, False] and all(s["url"] is None for s in listed)
    assert [s["label"] for s in listed] == [None, "for the reviewers"]
    named = web.post(f"{API}/jobs/{jid}/shares", json={"label": "x" * 201}, headers=acc.headers)
    assert named.status_code == 422 and named.json()["field"] == "label"
    assert web.delete(f"{API}/shares/{listed[0]['id']}", headers=other.headers).status_code == 404


def test_an_empty_field_of_a_posted_form_is_not_given(web, session, make_account):
    """An optional field of a posted form left empty is as if not sent (its default
    applies): the share form, the schedule form, the dataset upload (an empty "CSV
    input columns" is the columns u1..um, not no inputs); a required one left empty is
    a 422 naming it."""
    acc = make_account()
    jid = web.post(f"{API}/jobs", json=SMALL_SPEC, headers=acc.headers).json()["id"]
    sign_in(web, acc.key)
    token = csrf_of(web.get(f"/jobs/{jid}/share").text)
    form = {"csrf_token": token, "label": "", "days": ""}
    assert web.post(f"/jobs/{jid}/share", data=form, follow_redirects=False).status_code == 303
    link = session.scalars(select(ShareLink).where(ShareLink.job_id == jid)).one()
    days = (link.expires_at - link.created_at) / timedelta(days=1)
    assert link.label is None and days == pytest.approx(shares.DEFAULT_DAYS)
    for typed, says in [
        ("0", "a link lasts from one hour (0.0417 days) to 90 days, not 0"),
        ("91", "a link lasts from one hour (0.0417 days) to 90 days, not 91"),
        ("nan", "must be finite"),
        ("inf", "must be finite"),
        ("a week", "must be a number"),
    ]:
        r = web.post(f"/jobs/{jid}/share", data={**form, "days": typed}, follow_redirects=False)
        assert r.status_code == 422 and says in html.unescape(r.text), (typed, r.text[-600:])
    assert session.scalars(select(ShareLink).where(ShareLink.job_id == jid)).all() == [link]
    data = {"csrf_token": token, "job": jid, "name": "nightly", "cron": "0 3 * * *"}
    empty = {"timezone": "", "seed_policy": "", "tags": ""}
    made = web.post("/schedules/new", data={**data, **empty}, follow_redirects=False)
    assert made.status_code == 303, made.text
    (s,) = web.get(f"{API}/schedules", headers=acc.headers).json()
    assert (s["timezone"], s["seed_policy"], s["tags"]) == ("UTC", "fixed", [])
    runs = b"rollout,k,x1,u1\n" + b"".join(
        b"%d,%d,%d,1\n" % (r, k, k) for r in range(3) for k in range(9)
    )
    fields = ("description", "sample_time", "state_columns", "input_columns", "state_names")
    upload = {"csrf_token": token, "name": "runs", **dict.fromkeys(fields, "")}
    headers = {"X-CSRF-Token": token}
    r = web.post(
        "/datasets/upload", files={"file": ("runs.csv", runs)}, data=upload, headers=headers
    )
    assert r.status_code == 201, r.text
    stored = web.get(f"{API}/datasets/{r.json()['id']}", headers=acc.headers).json()
    assert (stored["n"], stored["m"], stored["description"]) == (1, 1, None)
    # a required field left empty
    refused = web.post("/schedules/new", data={**data, "job": ""})
    assert refused.status_code == 422 and "job: field required" in refused.text
    r = web.post("/datasets/upload", files={"file": ("", b"")}, data=upload, headers=headers)
    assert (r.status_code, r.json()["field"]) == (422, "file"), r.text
    r = web.post(
        "/datasets/upload",
        files={"file": ("runs.csv", runs)},
        data={**upload, "name": ""},
        headers=headers,
    )
    assert (r.status_code, r.json()) == (422, {"detail": "is required", "field": "name"})
