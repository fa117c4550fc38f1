"""The web UI in a real chromium against a real server (uvicorn + celery worker on the
embedded stack of tests/integration): sign in, submit, live progress (the focus kept
through the table's polls, a poll the server cannot answer said beside the table),
charts equal to the API's summary, cancel, delete, sign out, team scoping, CSRF, and no
request to any host but the server."""

from __future__ import annotations

import json
import re

import numpy as np
import pytest
from playwright.sync_api import expect

from svrobs_cli.serve import api_command
from tests.integration.stack import free_port, submit

from .browser import Browser, needs_chromium

pytestmark = [
    pytest.mark.integration,
    pytest.mark.timeout(600),
    needs_chromium,
    pytest.mark.parametrize("stack", ["embedded"], indirect=True),
]

SPEC = {
    "systems": ["paper-stable", "paper-unstable"],
    "sigma_w": [0.1, 1.0],
    "N": [10, 20, 40],
    "gamma": [0.01, 0.1],
    "estimators": ["ols", "svr"],
    "reps": 3,
    "stages": ["estimate", "bounds"],
    "seed": 11,
}
TINY = {"systems": ["paper-stable"], "sigma_w": [1.0], "N": [10], "reps": 2, "seed": 2}

PLOTTED = """() => window.svrobsCharts.charts.map(c => ({
  panel: c.panel,
  y: c.chart.options.scales.y.type,
  lines: c.chart.data.datasets.filter(d => d.svrobs.role === "mean").map(d => ({
    estimator: d.svrobs.estimator, gamma: d.svrobs.gamma, line: d.svrobs.line || {},
    points: d.data.map(p => [p.x, p.y]), std: d.svrobs.std,
  })),
}))"""


@pytest.fixture(scope="module")
def browser():
    b = Browser()
    try:
        yield b
    finally:
        b.close()


@pytest.fixture(autouse=True)
def only_the_server(browser):
    """After every test: the pages asked nothing of a host but the servers they were
    opened on, and logged no error (an intended 4xx page aside)."""
    browser.requests.clear()
    browser.console_errors.clear()
    yield
    assert browser.requests, "no request was recorded"
    assert browser.foreign_requests() == []
    assert [
        e for e in browser.console_errors if "the server responded with a status of 4" not in e
    ] == []


@pytest.fixture(scope="module")
def team_b_key(stack) -> str:
    return stack.team_key("other-lab")


@pytest.fixture(scope="module")
def access_logged_api(stack) -> str:
    """A second API process of the stack with uvicorn's access log on (``svrobs serve``
    turns it off), to show that the key never reaches it."""
    port = free_port()
    stack.start("api-access", [a for a in api_command("127.0.0.1", port) if a != "--no-access-log"])
    url = f"http://127.0.0.1:{port}"
    stack.wait_http(f"{url}/readyz", "api-access")
    yield url
    stack.stop("api-access")


def sign_in(page, key: str) -> None:
    page.goto("/jobs")
    assert re.search(r"/login\?next=%2Fjobs$", page.url), page.url
    page.fill("#key", key)
    page.click("form[action='/login'] button[type=submit]")
    page.wait_for_url(re.compile(r"/jobs$"))


def follow(page, selector: str) -> None:
    """Click a link and wait for the new page's load event: a click returns once the
    navigation commits, before the deferred scripts (htmx, the page's own) have run,
    and a change made on the page before then has no listener to reach."""
    page.click(selector)
    page.wait_for_load_state("load")


def wait_charts(page, loads: int) -> list[dict]:
    page.wait_for_selector(f"#charts-card[data-loads='{loads}']")  # (the CSP forbids eval)
    return page.evaluate(PLOTTED)


def assert_charts_equal_summary(plotted: list[dict], summary: dict, x: str, metric: str) -> None:
    """Every summary group is one plotted point (x, mean) with its std, nothing else."""
    panel_fields = [f for f in ("system", "sigma_w", "N") if f != x]
    want = {}
    for g in summary["groups"]:
        gamma = None if x == "gamma" else g["gamma"]
        key = ("|".join(str(g[f]) for f in panel_fields), g["estimator"], gamma, g[x])
        want[key] = (g["stats"][metric]["mean"], g["stats"][metric]["std"])
    got = {}
    for chart in plotted:
        for line in chart["lines"]:
            for (xv, y), std in zip(line["points"], line["std"]):
                got[(chart["panel"], line["estimator"], line["gamma"], xv)] = (y, std)
    assert got == want


SYMLOG = """() => { const c = document.createElement("canvas");
  document.body.appendChild(c);
  const ch = new Chart(c, {type: "line", data: {datasets: [{data: [{x: 1, y: -3}, {x: 2, y: 0.004},
    {x: 3, y: 40}]}]}, options: {animation: false, scales: {x: {type: "linear"},
    y: {type: "symlog", linthresh: 0.01}}}});
  const y = ch.scales.y, vs = [-3, -0.01, 0, 0.004, 0.01, 40];
  const out = {ticks: y.ticks.map(t => t.value), px: vs.map(v => y.getPixelForValue(v)),
    back: vs.map(v => y.getValueForPixel(y.getPixelForValue(v)))};
  ch.destroy(); c.remove(); return out; }"""


def check_presets(page, summary: dict) -> None:
    """A figure-series preset draws summary_lines of the API's summary JSON (the
    report's figure curves), with the figure's grouping and scale; presets of fields
    without data are hidden; the symlog axis is monotone and round-trips."""
    from svrobs_core.report import summary_context, summary_lines
    from svrobs_core.report.series import figure_series

    groups = summary["groups"]
    hidden = page.evaluate(
        """() => [...document.querySelectorAll("#chart-preset option[data-field]")]
        .filter(o => o.hidden).map(o => o.value)"""
    )
    assert "fig5/ratio" in hidden and "fig_rmse/rmse_A" not in hidden  # no cost stage
    loads = int(page.get_attribute("#charts-card", "data-loads"))
    for n, (preset, scale) in enumerate(
        (("fig_rmse/rmse_A", "logarithmic"), ("fig_coverage/coverage_A", "linear")), 1
    ):
        page.select_option("#chart-preset", preset)
        plotted = wait_charts(page, loads + n)
        assert page.is_disabled("#chart-metric") and page.is_disabled("#chart-x")
        figure, key = preset.split("/")
        row = figure_series(figure)[key]
        want = {}
        for ln in summary_lines(groups, row, summary_context(groups, SPEC)):
            panel = "|".join(str(v) for v in ln["panel"].values())
            want[(panel, *ln["line"].values())] = [[x, y] for x, y in zip(ln["N"], ln["y"])]
        got = {}
        for chart in plotted:
            assert chart["y"] == scale
            for line in chart["lines"]:
                pts = [p for p in line["points"] if p[1] is not None]
                got[(chart["panel"], *line["line"].values())] = pts
        assert got.keys() == want.keys() and len(got) > 1
        for k in want:
            np.testing.assert_allclose(np.array(got[k]), np.array(want[k]), rtol=1e-12)
        note = page.locator("#chart-band-note").inner_text()
        assert note.startswith(f"(the report's {figure}")
    page.select_option("#chart-preset", "")
    wait_charts(page, loads + 3)
    assert not page.is_disabled("#chart-metric")
    sym = page.evaluate(SYMLOG)
    assert sym["px"] == sorted(sym["px"], reverse=True)  # y pixels grow downwards
    np.testing.assert_allclose(sym["back"], [-3, -0.01, 0, 0.004, 0.01, 40], atol=1e-9)
    assert {0, 0.01, -0.01, 0.1, -1, 10} <= set(sym["ticks"])


def log_text(stack) -> str:
    return "".join(p.read_text(errors="replace") for p in stack.logs.glob("*.log"))


def test_sign_in_submit_watch_progress_chart_and_sign_out(browser, stack):
    page = browser.page(stack.base_url)
    sign_in(page, stack.key)
    assert stack.key not in page.content()
    stack.stop("worker1")  # the job waits, so the page sees it run and finish
    try:
        follow(page, "nav a[href='/jobs/new']")
        page.select_option("#preset", "system:paper-unstable")
        follow(page, "#preset-fill")  # the form, filled
        expect(page.locator("#spec")).to_have_value(re.compile("paper-unstable"))
        assert json.loads(page.input_value("#spec"))["systems"] == ["paper-unstable"]
        assert page.input_value("#name") == "paper-unstable sweep"
        page.fill("#spec", json.dumps({**SPEC, "reps": 0}))  # the fields follow the JSON
        assert page.input_value("#f-reps") == "0" and page.is_checked("input[value=json]")
        page.fill("#name", "browser sweep")
        page.fill("#tags", "web, tiny")
        page.click("#submit-job")
        assert page.locator("#err-reps").inner_text() == "reps: must be >= 1"
        assert page.input_value("#name") == "browser sweep"  # the form keeps its values
        upload = {"name": "sweep.json", "mimeType": "application/json"}
        page.set_input_files("#spec_file", files=[{**upload, "buffer": json.dumps(SPEC).encode()}])
        page.click("#submit-job")  # the uploaded file, not the (bad) text, is the spec
        page.wait_for_url(re.compile(r"/jobs/\d+$"))
        job_id = int(page.url.rsplit("/", 1)[1])
        follow(page, "nav a[href='/jobs']")
        row = page.locator(f"#job-{job_id}")
        assert row.get_attribute("data-status") == "queued"
        assert page.get_attribute("#jobs-table", "data-polling") == "yes"
        page.focus(f"#job-{job_id} .run-pick")  # the keyboard's place, kept through the polls
        # a poll the server cannot answer (its database down): the table stays, and says why
        down = (
            '<p class="error-message">The database is unavailable. Try again in a few seconds.</p>'
        )
        page.route(
            "**/jobs/rows*", lambda r: r.fulfill(status=503, body=down, content_type="text/html")
        )
        failed = page.locator("#jobs-table-failed")
        expect(failed).to_have_text(
            "Could not update this part of the page: HTTP 503: The database is unavailable."
            " Try again in a few seconds."
        )
        assert (
            row.get_attribute("data-status") == "queued" and failed.get_attribute("role") == "alert"
        )
        page.unroute("**/jobs/rows*")
        expect(failed).to_have_count(0)  # answered again
        # (the browser and htmx log each refused poll as an error)
        browser.console_errors[:] = [e for e in browser.console_errors if "503" not in e]
        navigations = []
        page.on("framenavigated", lambda frame: navigations.append(frame.url))
        page.evaluate("window.notReloaded = true")
    finally:
        stack.start_worker()
    page.wait_for_selector(f"#job-{job_id}[data-status=succeeded]", timeout=180_000)
    assert page.evaluate("window.notReloaded") is True and navigations == []
    bar = page.locator(f"#job-{job_id} progress")
    assert bar.get_attribute("value") == bar.get_attribute("max") != "0"
    page.wait_for_selector("#jobs-table[data-polling=no]")  # polling stopped
    assert page.evaluate("document.activeElement.id") == f"pick-{job_id}"

    with stack.client() as api:
        summary = api.get(f"/jobs/{job_id}/summary").json()
        assert summary["partial"] is False and len(summary["groups"]) == 2 * 2 * 3 * 3
        job = api.get(f"/jobs/{job_id}").json()
    assert job["name"] == "browser sweep" and job["tags"] == ["web", "tiny"]

    page.click(f"#job-{job_id} a")
    plotted = wait_charts(page, 1)
    assert len(plotted) == 4 and all(c["y"] == "logarithmic" for c in plotted)
    assert_charts_equal_summary(plotted, summary, "N", "rmse_A")
    page.select_option("#chart-x", "sigma_w")
    wait_charts(page, 2)
    page.select_option("#chart-metric", "H_A")
    plotted = wait_charts(page, 3)
    assert_charts_equal_summary(plotted, summary, "sigma_w", "H_A")
    page.select_option("#chart-x", "gamma")
    plotted = wait_charts(page, 4)
    ols = [ln for c in plotted for ln in c["lines"] if ln["estimator"] == "ols"]
    assert ols and all(len({y for _, y in ln["points"]}) == 1 for ln in ols)  # flat line
    page.uncheck("#chart-logy")
    assert {c["y"] for c in page.evaluate(PLOTTED)} == {"linear"}
    hidden = page.evaluate(
        """() => { const c = window.svrobsCharts.charts[0].chart;
        c.options.plugins.legend.onClick(null, {datasetIndex: 0}, c.legend);
        return c.data.datasets.map((d, i) => [d.svrobs.series, c.isDatasetVisible(i)]); }"""
    )
    assert {vis for s, vis in hidden if s == 0} == {False}  # the line and its band
    assert {vis for s, vis in hidden if s != 0} == {True}
    page.uncheck("#chart-bands")
    roles = page.evaluate(
        "() => window.svrobsCharts.charts[0].chart.data.datasets.map(d => d.svrobs.role)"
    )
    assert roles and set(roles) == {"mean"}

    page.check("#chart-bands")
    check_presets(page, summary)
    expect(page.locator("#table2 tbody tr")).to_have_count(2 * 2 * 2)  # system, σ_w, matrix
    assert page.locator("#findings li").count() >= 1

    with stack.client() as api:  # downloads: the API's own streams, under the cookie
        for fmt in ("csv", "jsonl"):
            path = f"/api/v1/jobs/{job_id}/results?format={fmt}"
            href = page.get_attribute(f"a[href='{path}']", "href")
            assert page.request.get(href).text() == api.get(path[len("/api/v1") :]).text
    page.click("#report-link")  # the stored report, with a link back to the job's page
    page.wait_for_load_state()
    assert page.url.endswith(f"/jobs/{job_id}/report") and "Table 2" in page.content()
    with stack.client() as api:  # the API's report under the cookie: the same page
        api_report = page.request.get(f"/api/v1/jobs/{job_id}/report")
        assert (
            api_report.status == 200 and api_report.text() == api.get(f"/jobs/{job_id}/report").text
        )
    page.click("#back-link")
    page.wait_for_url(re.compile(rf"/jobs/{job_id}$"))
    page.click("form[action='/logout'] button")
    page.wait_for_url(re.compile(r"/login$"))
    page.goto(f"/jobs/{job_id}")
    assert "/login?next=" in page.url
    assert stack.key not in log_text(stack)  # uvicorn's access log never saw the key
    assert not [u for u in browser.requests if stack.key in u]  # nor did any URL


def test_the_key_never_reaches_the_access_log(browser, stack, access_logged_api):
    page = browser.page(access_logged_api)
    sign_in(page, stack.key)
    page.click("form[action='/logout'] button")
    page.wait_for_url(re.compile(r"/login$"))
    log = (stack.logs / "api-access.log").read_text(errors="replace")
    assert '"POST /login HTTP/1.1" 303' in log and '"GET /jobs HTTP/1.1" 200' in log
    secret = stack.key.split("_", 2)[2]  # as the service splits it: the secret may start with "_"
    assert len(secret) >= 32 and stack.key not in log and secret not in log


def test_cancel_then_delete_with_confirmation(browser, stack):
    stack.stop("worker1")
    try:
        with stack.client() as api:
            job_id = submit(api, TINY, name="to delete")["id"]
        page = browser.page(stack.base_url)
        sign_in(page, stack.key)
        page.goto(f"/jobs/{job_id}")
        assert page.locator("#delete-job").count() == 0  # a queued job is cancelled first
        asked = []
        page.once("dialog", lambda d: (asked.append(d.message), d.dismiss()))
        page.click("#cancel-job")  # asked, and declined: nothing happens
        assert asked and f"Cancel job {job_id}?" in asked[0]
        with stack.client() as api:
            assert api.get(f"/jobs/{job_id}").json()["status"] == "queued"
        page.once("dialog", lambda d: d.accept())
        page.click("#cancel-job")
        page.wait_for_selector("#job-status:text('cancelled')")
        page.click("#delete-job")
        assert page.url.endswith(f"/jobs/{job_id}/delete")
        with stack.client() as api:  # asking is not deleting
            assert api.get(f"/jobs/{job_id}").status_code == 200
        page.click("#confirm-delete")
        page.wait_for_url(re.compile(rf"/jobs\?deleted={job_id}$"))
        assert page.locator(f"#job-{job_id}").count() == 0
        with stack.client() as api:
            assert api.get(f"/jobs/{job_id}").status_code == 404
        page.goto(f"/jobs/{job_id}")
        assert "404" in page.inner_text("h1")
    finally:
        stack.start_worker()


def test_other_team_gets_404_and_posts_need_the_csrf_token(browser, stack, team_b_key):
    with stack.client() as api:
        job_id = submit(api, TINY, name="team a")["id"]
        stack.wait_job(api, job_id)
    page = browser.page(stack.base_url)
    sign_in(page, team_b_key)
    assert page.locator(f"#job-{job_id}").count() == 0
    for path in (f"/jobs/{job_id}", f"/jobs/{job_id}/delete"):
        response = page.goto(path)
        assert response.status == 404 and "not found" in page.inner_text("main").lower()
    for path in (f"/jobs/{job_id}/chart-data", f"/api/v1/jobs/{job_id}/report"):
        assert page.request.get(path).status == 404

    page.goto("/jobs")
    status = page.evaluate(
        """async (id) => (await fetch(`/jobs/${id}/cancel`, {method: "POST"})).status""", job_id
    )
    assert status == 403  # no token, though the browser sends the session cookie
    own = page.evaluate(
        """async () => { const r = await fetch("/logout", {method: "POST",
             headers: {"X-CSRF-Token": "forged"}}); return r.status; }"""
    )
    assert own == 403
    assert page.goto("/jobs").url.endswith("/jobs")  # still signed in
