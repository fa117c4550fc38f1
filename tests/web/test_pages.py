"""The jobs and job pages through the app (TestClient): filters, search and pages
match the API's own listing, another team's job is a 404 page on every job route,
cancel/delete need CSRF, and chart data are the stored summaries."""

from __future__ import annotations

import html
import json
import re

import pytest

from service.config import Settings
from service.web import charts, figure_charts, spec_form
from svrobs_core import parse_spec
from svrobs_core import report as rpt
from tests.service.svc_fakes import run_job_units
from tests.service.svc_helpers import SMALL_SPEC

from .helpers import csrf_of, sign_in

API = "/api/v1"
ROW = re.compile(r'<tr id="job-(\d+)" data-status="(\w+)">')


@pytest.fixture
def web_pub(build_client):
    return build_client(SECRET_KEY="pages-secret-0123456789")


@pytest.fixture
def web(web_pub):
    return web_pub[0]


@pytest.fixture
def sent(web_pub):
    """The unit ids the app published."""
    return web_pub[1]


def _submit(client, acc, **extra) -> int:
    r = client.post(f"{API}/jobs", json={**SMALL_SPEC, **extra}, headers=acc.headers)
    assert r.status_code == 202, r.text
    return r.json()["id"]


def _rows(html: str) -> list[int]:
    return [int(i) for i, _ in ROW.findall(html)]


def test_filters_search_and_pages_agree_with_the_api(web, session, make_account):
    acc = make_account()
    ids = [
        _submit(web, acc, name=f"Sweep {i}%", tags=["even" if i % 2 else "odd"]) for i in range(30)
    ]
    run_job_units(session, ids[3])
    sign_in(web, acc.key)
    first = web.get("/jobs")
    assert _rows(first.text) == ids[::-1][:25] and "page 1 of 2" in first.text
    assert _rows(web.get("/jobs?page=2").text) == ids[::-1][25:]
    for query in ("status=succeeded", "tag=even", "owner=me", f"owner={acc.user.email}"):
        api = web.get(f"{API}/jobs?{query}&limit=500", headers=acc.headers).json()["items"]
        assert _rows(web.get(f"/jobs?{query}").text) == [j["id"] for j in api][:25], query
    # name search: any case, a part of the name, % and _ are literal characters
    assert _rows(web.get("/jobs?q=sweep 1").text) == [ids[i] for i in range(19, 9, -1)] + [ids[1]]
    assert _rows(web.get("/jobs?q=WEEP 29%").text) == [ids[29]]
    assert _rows(web.get("/jobs?q=_").text) == []
    assert web.get("/jobs?status=bogus").status_code == 422


def test_polling_only_while_a_job_on_the_page_is_active(web, session, make_account):
    acc = make_account()
    jid = _submit(web, acc)
    sign_in(web, acc.key)
    assert 'hx-trigger="every 2s"' in web.get("/jobs/rows").text
    assert 'hx-trigger="every 2s"' in web.get(f"/jobs/{jid}/progress").text
    run_job_units(session, jid)
    assert "hx-trigger" not in web.get("/jobs/rows").text
    done = web.get(f"/jobs/{jid}/progress")
    assert "hx-trigger" not in done.text and done.headers["hx-trigger"] == "svrobs:job-finished"


def test_another_teams_job_is_a_404_page_everywhere(web, session, make_account):
    a, b = make_account(), make_account()
    jid = _submit(web, a)
    sign_in(web, b.key)
    token = csrf_of(web.get("/jobs").text)
    for path in ("", "/progress", "/chart-data", "/tables", "/delete"):
        assert web.get(f"/jobs/{jid}{path}").status_code == 404, path
    for path in ("/cancel", "/delete"):
        r = web.post(f"/jobs/{jid}{path}", data={"csrf_token": token}, follow_redirects=False)
        assert r.status_code == 404 and "not found" in r.text
    for huge in (2**31, 2**63):  # beyond the database's integers: no job, not a 500
        for path in ("", "/report", "/delete"):
            assert web.get(f"/jobs/{huge}{path}").status_code == 404, (huge, path)
        r = web.post(f"/jobs/{huge}/delete", data={"csrf_token": token}, follow_redirects=False)
        assert r.status_code == 404 and "not found" in r.text
    assert _rows(web.get("/jobs").text) == []
    r = web.get(f"{API}/jobs/{jid}", headers=a.headers).json()
    assert r["status"] == "queued"  # untouched


def test_cancel_and_delete_need_the_token_and_refuse_active_jobs(web, session, make_account):
    acc = make_account()
    jid = _submit(web, acc)
    sign_in(web, acc.key)
    token = csrf_of(web.get(f"/jobs/{jid}").text)
    assert web.post(f"/jobs/{jid}/cancel", follow_redirects=False).status_code == 403
    r = web.post(f"/jobs/{jid}/delete", data={"csrf_token": token}, follow_redirects=False)
    assert r.status_code == 409 and "cancel it" in r.text
    r = web.post(f"/jobs/{jid}/cancel", data={"csrf_token": token}, follow_redirects=False)
    assert r.status_code == 303
    assert web.get(f"{API}/jobs/{jid}", headers=acc.headers).json()["status"] == "cancelled"
    assert web.post(f"/jobs/{jid}/delete", follow_redirects=False).status_code == 403
    r = web.post(f"/jobs/{jid}/delete", data={"csrf_token": token}, follow_redirects=False)
    assert r.status_code == 303 and r.headers["location"] == f"/jobs?deleted={jid}"
    assert web.get(f"{API}/jobs/{jid}", headers=acc.headers).status_code == 404
    assert web.get(f"/jobs?deleted={jid}").status_code == 200
    bad = web.get("/jobs?deleted=abc")
    assert bad.status_code == 422 and "deleted: job ids, written with the digits 0-9" in bad.text


def test_chart_data_are_the_stored_summaries(web, session, make_account):
    acc = make_account()
    jid = _submit(web, acc)
    run_job_units(session, jid)
    sign_in(web, acc.key)
    summary = web.get(f"{API}/jobs/{jid}/summary", headers=acc.headers).json()["groups"]
    data = web.get(f"/jobs/{jid}/chart-data?metric=rmse_A&x=N").json()
    got = {
        (p["coords"]["system"], p["coords"]["sigma_w"], s["estimator"], s["gamma"], n): (m, sd)
        for p in data["panels"]
        for s in p["series"]
        for n, m, sd in zip(p["x"], s["mean"], s["std"])
    }
    want = {
        (g["system"], g["sigma_w"], g["estimator"], g["gamma"], g["N"]): (
            g["stats"]["rmse_A"]["mean"],
            g["stats"]["rmse_A"]["std"],
        )
        for g in summary
    }
    assert got == want and data["positive"] is True and "metrics" not in data
    fields = web.get(f"/jobs/{jid}/chart-data?metric=rmse_A&metrics=1").json()["metrics"]
    stored = {f for g in summary for f, s in g["stats"].items() if s["mean"] is not None}
    assert set(fields) == stored and "rmse_A" in fields
    assert "rmse_B" not in fields  # every value NaN (null): nothing to plot
    r = web.get(f"/jobs/{jid}/chart-data?metric=A_hat")
    assert r.status_code == 422 and r.json()["field"] == "metric"
    assert web.get(f"/jobs/{jid}/chart-data?x=rep").json()["field"] == "x"


def _jsonl(client, acc, jid) -> list[dict]:
    r = client.get(f"{API}/jobs/{jid}/results?format=jsonl", headers=acc.headers)
    return [json.loads(line) for line in r.text.splitlines() if line.strip()]


def test_table2_findings_and_figure_presets_on_the_job_page(web, session, make_account):
    """Table 2 on the page is the report's table2 of the stored records (JSONL export);
    a preset's chart data are summary_lines of the API's summary JSON."""
    acc = make_account()
    jid = _submit(web, acc)
    run_job_units(session, jid)
    sign_in(web, acc.key)
    page = web.get(f"/jobs/{jid}").text
    assert f'hx-get="/jobs/{jid}/tables"' in page
    tables = web.get(f"/jobs/{jid}/tables").text
    records = _jsonl(web, acc, jid)
    rows = re.findall(
        r'<tr data-system="([^"]+)" data-sigma-w="([^"]+)" data-matrix="(\w)">\s*'
        r"<td>[^<]*</td><td>[^<]*</td><td>\w</td>\s*"
        r'<td class="num" data-value="([^"]*)">[^<]*</td>\s*<td class="num" data-value="([^"]*)">',
        tables,
    )
    want = rpt.table2(records)
    assert len(rows) == len(want) == 2 * 2 * 2
    for (system, sigma_w, mat, ols, svr), t in zip(rows, want):
        assert (system, float(sigma_w), mat) == (t["system"], t["sigma_w"], t["matrix"])
        for got, exp in ((ols, t["ols"]), (svr, t["svr"])):
            assert (got == "None") if exp is None else float(got) == pytest.approx(exp, rel=1e-12)
    found = re.findall(r"<li>(\[[^<]*)</li>", tables)
    assert found and all(html.unescape(f) in rpt.findings(records, SMALL_SPEC) for f in found)

    summary = web.get(f"{API}/jobs/{jid}/summary", headers=acc.headers).json()["groups"]
    row = figure_charts.PRESETS["fig_rmse/rmse_A"]
    assert 'value="fig_rmse/rmse_A" data-field="rmse_A"' in page
    data = web.get(f"/jobs/{jid}/chart-data?preset=fig_rmse/rmse_A").json()
    lines = rpt.summary_lines(summary, row, rpt.summary_context(summary, SMALL_SPEC))
    got = {
        (p["coords"]["system"], tuple(s["line"].items()), n): m
        for p in data["panels"]
        for s in p["series"]
        for n, m in zip(p["x"], s["mean"])
        if m is not None
    }
    assert got == {
        (ln["panel"]["system"], tuple(ln["line"].items()), n): y
        for ln in lines
        for n, y in zip(ln["N"], ln["y"])
    }
    assert data["scale"] == "log" and data["preset"]["band"] is None
    r = web.get(f"/jobs/{jid}/chart-data?preset=fig2/err_A")  # derived: needs records
    assert r.status_code == 422 and r.json()["field"] == "preset"


def test_chart_gaps_flat_ols_and_non_positive_means():
    stats = lambda m: {"rmse_A": {"mean": m, "std": 0.5, "count": 3}}  # noqa: E731
    groups = [
        dict(system="s", sigma_w=1.0, N=10, estimator="ols", gamma=None, stats=stats(2.0)),
        dict(system="s", sigma_w=1.0, N=10, estimator="svr", gamma=0.1, stats=stats(1.0)),
        dict(system="s", sigma_w=1.0, N=10, estimator="svr", gamma=0.5, stats=stats(-1.0)),
        dict(system="s", sigma_w=1.0, N=20, estimator="svr", gamma=0.1, stats=stats(None)),
    ]
    by_n = charts.chart_data(groups, metric="rmse_A", x="N")
    (panel,) = by_n["panels"]
    assert panel["x"] == [10, 20] and by_n["positive"] is False
    assert [(s["label"], s["mean"]) for s in panel["series"]] == [
        ("ols", [2.0, None]),  # no N = 20 group: a gap
        ("svr γ=0.1", [1.0, None]),  # a null mean: a gap
        ("svr γ=0.5", [-1.0, None]),
    ]
    by_gamma = charts.chart_data(groups, metric="rmse_A", x="gamma")
    first = by_gamma["panels"][0]
    assert first["x"] == [0.1, 0.5] and first["title"] == "system = s · σ_w = 1 · N = 10"
    ols, svr = first["series"]
    assert ols["label"] == "ols (no γ)" and ols["flat"] and ols["mean"] == [2.0, 2.0]
    assert svr["label"] == "svr" and svr["mean"] == [1.0, -1.0]


def _post_spec(web, token: str, spec_text: str, **fields):
    data = {"csrf_token": token, "spec": spec_text, **fields}
    return web.post("/jobs/new", data=data, follow_redirects=False)


@pytest.mark.parametrize(
    ("spec", "fields", "where", "shown"),
    [
        (
            {"systems": [{"name": "x", "A": [[1, 2]], "B": [[1]]}], "sigma_w": [1], "N": [10]},
            {},
            "err-systems",
            "<code>systems[0].A</code>: must be square, got 1x2",
        ),
        ({**SMALL_SPEC, "N": "100"}, {}, "err-N", "<code>N</code>: must be a non-empty list"),
        ({**SMALL_SPEC, "bogus": 1}, {}, "form-errors", "<code>bogus</code></a>: unknown field"),
        (
            SMALL_SPEC,
            {"name": "n" * 201},
            "name-error",
            "<code>name</code>: must be at most 200 characters long",
        ),
        (
            SMALL_SPEC,
            {"tags": "ok, " + "t" * 101},
            "tags-error",
            "<code>tags[1]</code>: must be at most 100 characters long",
        ),
        (
            SMALL_SPEC,
            {"tags": ", ".join(f"t{i}" for i in range(51))},
            "tags-error",
            "<code>tags</code>: must have at most 50 entries (51 given)",
        ),
        (
            SMALL_SPEC,
            {"name": "a\x01b"},
            "name-error",
            "<code>name</code>: must be printable text (no control characters)",
        ),
        ("{not json", {}, "spec-error", "<code>spec</code>: not valid JSON"),
        ('{"a":' * 3000 + "1" + "}" * 3000, {}, "spec-error", "not valid JSON: nested too deeply"),
        (
            '{"systems": ["paper-stable"], "sigma_w": [1], "N": [10], "seed": ' + "9" * 5000 + "}",
            {},
            "spec-error",
            "<code>spec</code>: an integer of more than 4,300 digits",
        ),
        ("[1, 2]", {}, "spec-error", "<code>spec</code>: must be a JSON object"),
        ("", {}, "spec-error", "<code>spec</code>: paste a spec"),
    ],
)
def test_submit_errors_are_shown_beside_their_field(
    web, sent, make_account, spec, fields, where, shown
):
    acc = make_account()
    sign_in(web, acc.key)
    token = csrf_of(web.get("/jobs/new").text)
    text = spec if isinstance(spec, str) else json.dumps(spec)
    r = _post_spec(web, token, text, **fields)  # no "source": the JSON text, as before
    assert r.status_code == 422
    error = re.search(rf'<(p|div)[^>]* id="{where}"[^>]*>(.*?)</(p|div)>', r.text, re.S)
    assert error is not None and shown in error.group(2), r.text[-3000:]
    summary = re.search(r'<div class="card error-summary" role="alert".*?</div>', r.text, re.S)
    assert summary is not None and len(re.findall("<li>", summary.group(0))) == 1
    kept = re.search(r"<textarea[^>]*>(.*?)</textarea>", r.text, re.S).group(1)
    assert html.unescape(kept) == text  # kept for correcting it
    assert sent.published == []
    assert web.get(f"{API}/jobs", headers=acc.headers).json()["total"] == 0


def test_an_unknown_field_is_shown_beside_the_json_view(web, sent, make_account):
    """A field no input of the form shows (``bogus``) is the JSON view's error: beside
    the textarea, which is marked invalid, and linked from the list at the top."""
    acc = make_account()
    sign_in(web, acc.key)
    token = csrf_of(web.get("/jobs/new").text)
    spec = {"systems": ["paper-stable"], "sigma_w": [0.5], "N": [20], "bogus": 1}
    r = _post_spec(web, token, json.dumps(spec), source="json")
    assert r.status_code == 422
    beside = re.search(r'<div id="spec-error" class="field-error">(.*?)</div>', r.text, re.S)
    assert beside is not None, r.text[-3000:]
    assert "<code>bogus</code>: unknown field" in beside.group(1)
    textarea = re.search(r"<textarea[^>]*>", r.text).group(0)
    assert 'aria-invalid="true"' in textarea and "spec-error" in textarea
    assert '<a href="#spec"><code>bogus</code></a>: unknown field' in r.text
    assert sent.published == []


def _posted(spec: dict, **edits) -> dict:
    """The spec form as the browser posts it ({name: [values]}), filled with ``spec``,
    then ``edits`` ({input name: text}) typed in."""
    form, lists = spec_form.as_posted(spec_form.values_of(spec))
    form.update(edits)
    return {**{k: [v] for k, v in form.items()}, **lists}


def test_the_form_fields_submit_the_spec_they_show(web, sent, make_account):
    acc = make_account()
    sign_in(web, acc.key)
    page = web.get("/jobs/new?preset=system:paper-unstable").text
    token = csrf_of(page)
    assert 'name="name" value="paper-unstable sweep"' in page  # a preset names and tags
    assert 'name="tags" value="sweep, paper-unstable"' in page
    assert 'name="r.N.stop" value="100"' in page and 'value="range" checked' in page
    spec = {**SMALL_SPEC, "sigma_w": [0.5, 1.0], "stages": ["estimate", "bounds", "gain"]}
    data = _posted(spec, **{"f.reps": "3"})
    data.update(csrf_token=token, source="form", name="by fields")
    r = web.post("/jobs/new", data=data, follow_redirects=False)
    assert r.status_code == 303, r.text[-2000:]
    job = web.get(f"{API}{r.headers['location']}", headers=acc.headers).json()
    assert job["spec"] == parse_spec({**spec, "reps": 3}).to_dict() and job["name"] == "by fields"


def test_the_form_shows_every_error_at_once_beside_its_field(web, sent, make_account):
    acc = make_account()
    sign_in(web, acc.key)
    token = csrf_of(web.get("/jobs/new").text)
    data = _posted(
        SMALL_SPEC,
        **{"f.sigma_w": "-1, 1", "f.reps": "ten", "f.gamma": "0", "f.delta": "2"},
    )
    r = web.post("/jobs/new", data={**data, "csrf_token": token, "source": "form"})
    assert r.status_code == 422
    beside = dict(re.findall(r'id="err-([\w.-]+)"><p><code>[^<]*</code>: ([^<]*)</p>', r.text))
    assert beside == {
        "sigma_w": "must be &gt;= 0",
        "reps": "&#39;ten&#39; is not an integer (digits 0-9)",
        "gamma": "must be &gt; 0",
        "delta": "must be &lt; 1",
    }
    assert "4 errors to fix" in r.text  # listed at the top as the fields are on the page
    listed = re.findall(r'<li><a href="#field-([\w.-]+)">', r.text)
    assert listed == ["sigma_w", "gamma", "reps", "delta"]
    assert 'value="-1, 1"' in r.text and 'value="ten"' in r.text  # as typed
    assert sent.published == []


def test_submit_text_upload_and_preset_create_jobs_once(web, sent, make_account):
    acc = make_account()
    sign_in(web, acc.key)
    form = web.get("/jobs/new").text
    token = csrf_of(form)
    key = re.search(r'name="idempotency_key" value="([^"]+)"', form).group(1)
    fields = {"name": "pasted", "tags": "a, b", "idempotency_key": key}
    r = _post_spec(web, token, json.dumps(SMALL_SPEC), **fields)
    assert r.status_code == 303
    jid = int(r.headers["location"].rsplit("/", 1)[1])
    again = _post_spec(web, token, json.dumps(SMALL_SPEC), **fields)  # a double submit
    assert again.headers["location"] == f"/jobs/{jid}"
    job = web.get(f"{API}/jobs/{jid}", headers=acc.headers).json()
    assert (job["name"], job["tags"], job["owner"]) == ("pasted", ["a", "b"], acc.user.email)
    cap = Settings().fair_share()[0]  # the team alone: the pool's size
    assert len(sent.published) == min(job["progress"]["total"], cap)  # published once

    upload = {"spec_file": ("s.json", json.dumps({**SMALL_SPEC, "seed": 9}), "application/json")}
    r = web.post("/jobs/new", data={"csrf_token": token, "spec": "ignored"}, files=upload)
    assert r.status_code == 200 and r.url.path.startswith("/jobs/")
    uploaded = web.get(f"{API}{r.url.path}", headers=acc.headers).json()
    assert uploaded["spec"]["seed"] == 9

    preset = web.get("/jobs/new?preset=paper-section-6:E1:reduced").text
    text = html.unescape(re.search(r"<textarea[^>]*>(.*?)</textarea>", preset, re.S).group(1))
    name = html.unescape(re.search(r'name="name" value="([^"]*)"', preset).group(1))
    r = _post_spec(web, token, text, name=name, tags="paper-section-6, E1")
    job = web.get(f"{API}{r.headers['location']}", headers=acc.headers).json()
    from svrobs_core.paper import paper_specs

    assert job["spec"] == parse_spec(paper_specs("reduced")["E1"]).to_dict()
    assert job["name"] == "paper-section-6 E1 (reduced)" and job["tags"] == [
        "paper-section-6",
        "E1",
    ]
    assert web.post("/jobs/new", data={"spec": text}).status_code == 403  # no token


def test_a_ranged_grid_in_error_marks_its_range_inputs_invalid(web, sent, make_account):
    """A grid field posted as start / stop / step with an error: its three range
    inputs carry aria-invalid (the list input, hidden in that mode, does not), and the
    list at the top links to the field."""
    from service.web import spec_form

    acc = make_account()
    sign_in(web, acc.key)
    token = csrf_of(web.get("/jobs/new").text)
    form, lists = spec_form.as_posted(spec_form.values_of(SMALL_SPEC))
    form.update({"m.gamma": "range", "r.gamma.start": "1", "r.gamma.stop": "0"})
    form.update({"r.gamma.step": "0.1", "source": "form", "csrf_token": token})
    r = web.post("/jobs/new", data={**form, **lists}, follow_redirects=False)
    assert r.status_code == 422, r.text[-2000:]
    field = re.search(
        r'<div class="spec-field has-error" id="field-gamma".*?</fieldset>', r.text, re.S
    )
    assert field is not None, r.text[-3000:]
    ranged = re.findall(r'<input name="r\.gamma\.\w+"[^>]*>', field.group(0))
    assert len(ranged) == 3 and all('aria-invalid="true"' in i for i in ranged), ranged
    listed = re.search(r'<input name="f\.gamma"[^>]*>', field.group(0)).group(0)
    assert "aria-invalid" not in listed
    assert '<a href="#field-gamma"><code>gamma.stop</code></a>' in r.text
    assert sent.published == []


def test_the_form_hints_match_each_fields_kind(web, make_account):
    """N's list hints integers, σ_w's decimals; an optional number says it has a default."""
    sign_in(web, make_account().key)
    page = web.get("/jobs/new").text

    def placeholder(input_id):
        return re.search(rf'id="{input_id}"[^>]*placeholder="([^"]*)"', page)[1]

    assert placeholder("f-N") == "e.g. 10, 20, 50"
    assert placeholder("f-sigma_w") == "e.g. 0.1, 1.0"
    assert placeholder("f-mc_reps") == "default"
