"""Views that live in the URL, in a real chromium against a real server: a filtered,
sorted results view (two sort keys, one chosen from the keyboard, which keeps its focus;
a range, a hidden column) survives a reload and back/forward, and its CSV and JSONL
buttons export the rows shown, in the order shown, as the API's own filtered, sorted
page; Apply asks for the grid again; the job page's chart choices are in the URL, a late
chart response is dropped, and log y follows the data as the job finishes."""

from __future__ import annotations

import csv
import io
import json
import re

import pytest
from playwright.sync_api import expect

from tests.integration.stack import submit

from . import test_browser as base
from .test_browser import sign_in, wait_charts

browser = base.browser
only_the_server = base.only_the_server
pytestmark = base.pytestmark

SPEC = {
    "systems": ["paper-stable", "paper-unstable"],
    "sigma_w": [0.1, 1.0],
    "N": [10, 20],
    "gamma": [0.01, 0.1],
    "reps": 3,
    "seed": 8,
}
KEY = ("system", "sigma_w", "N", "estimator", "gamma", "rep")


@pytest.fixture(scope="module")
def job_id(stack) -> int:
    with stack.client() as api:
        jid = submit(api, SPEC, name="views")["id"]
        stack.wait_job(api, jid)
    return jid


def grid_column(page, field: str) -> list[str]:
    return page.eval_on_selector_all(
        f"#results-grid td[data-field='{field}']", "tds => tds.map(td => td.dataset.value)"
    )


def grid_rows(page) -> list[tuple]:
    cols = [grid_column(page, f) for f in KEY + ("rmse_A",)]
    return list(zip(*cols))


def api_key_of(item: dict) -> tuple:
    return tuple("" if item[f] is None else str(item[f]) for f in KEY + ("rmse_A",))


def test_results_view_survives_reload_and_exports_what_is_shown(browser, stack, job_id):
    page = browser.page(stack.base_url)
    sign_in(page, stack.key)
    page.goto(f"/results?job={job_id}")
    page.select_option("select[name=system]", "paper-unstable")
    page.wait_for_selector("#results-grid[data-query*='system=paper-unstable']")
    page.click("th a[data-sort-field='rmse_A']")
    page.wait_for_selector("#results-grid[data-sort='rmse_A']")
    page.focus("th a[data-sort-field='rmse_A']")  # from the keyboard: the grid is replaced,
    page.keyboard.press("Enter")  # and the focus stays on the head pressed
    page.wait_for_selector("#results-grid[data-sort='-rmse_A']")
    assert page.evaluate("document.activeElement.dataset.sortField") == "rmse_A"
    page.click("th a[data-sort-field='N']", modifiers=["Shift"])  # the second key
    page.wait_for_selector("#results-grid[data-sort='-rmse_A,N']")
    assert page.inner_text("th[data-field='N'] sup") == "2"
    assert page.get_attribute("th[data-field='rmse_A']", "aria-sort") == "descending"
    page.click("#results-columns summary")
    page.uncheck("#results-columns input[value=rmse_B]")
    assert page.locator("th[data-field='rmse_B']").is_hidden()
    # a range of a field, as the API's rmse_A_lt
    values = sorted(float(v) for v in grid_column(page, "rmse_A"))
    cut = values[len(values) * 2 // 3]
    page.select_option(".range-field", "rmse_A")
    page.fill(".range-max", repr(cut))
    page.click("#results-filters button[type=submit]")
    page.wait_for_selector(f"#results-grid[data-query*='rmax={cut!r}']")
    shown = grid_rows(page)
    assert 0 < len(shown) < len(values)
    url = page.url
    assert "sort=-rmse_A%2CN" in url and "system=paper-unstable" in url and "hide=rmse_B" in url

    with stack.client() as api:
        params = {"system": "paper-unstable", "sort": "-rmse_A,N", "rmse_A_lt": repr(cut)}
        want = api.get(f"/jobs/{job_id}/results", params={**params, "limit": 1000}).json()
    assert want["total"] == len(shown)  # (one page of 50 at most holds them all)
    assert shown == [api_key_of(i) for i in want["items"]]

    page.reload()  # the same view from its URL alone
    assert grid_rows(page) == shown
    assert page.input_value("#results-sort") == "-rmse_A,N"
    assert page.eval_on_selector(
        "select[name=system]", "s => [...s.selectedOptions].map(o => o.value)"
    ) == ["paper-unstable"]
    assert page.input_value(".range-max") == repr(cut)
    assert page.locator("th[data-field='rmse_B']").is_hidden()

    for fmt in ("csv", "jsonl"):  # the buttons export the view: same rows, same order
        href = page.get_attribute(f"#results-{fmt}", "href")
        body = page.request.get(href).text()
        if fmt == "csv":
            rows = list(csv.DictReader(io.StringIO(body)))
        else:
            rows = [json.loads(line) for line in body.splitlines()]
        assert [api_key_of(r) for r in rows] == [api_key_of(i) for i in want["items"]], fmt

    back(page, page.go_back)  # the view before the range: reloaded from its URL
    assert page.get_attribute("#results-grid", "data-sort") == "-rmse_A,N"
    assert not re.search(r"rmax=[^&]", page.url) and len(grid_rows(page)) == len(values)
    steps = 1
    while page.get_attribute("#results-grid", "data-sort") == "-rmse_A,N" and steps < 5:
        back(page, page.go_back)  # (choosing the range field was a view of its own)
        steps += 1
    assert page.get_attribute("#results-grid", "data-sort") == "-rmse_A"  # one sort key
    assert "sort=-rmse_A&" in page.url + "&"
    back(page, page.go_forward)
    assert page.get_attribute("#results-grid", "data-sort") == "-rmse_A,N"


def test_back_to_the_view_the_page_was_opened_on(browser, stack, job_id):
    """The first filter pushes a view; Back shows the unfiltered grid again (the entry
    the page opened on is marked as a results view too)."""
    page = browser.page(stack.base_url)
    sign_in(page, stack.key)
    page.goto(f"/results?job={job_id}")
    everything = page.get_attribute("#results-grid", "data-total")
    page.select_option("select[name=estimator]", "svr")
    page.wait_for_selector("#results-grid[data-query*='estimator=svr']")
    assert page.get_attribute("#results-grid", "data-total") != everything
    back(page, page.go_back)
    assert page.url.endswith(f"/results?job={job_id}")
    assert page.get_attribute("#results-grid", "data-total") == everything
    picked = "s => [...s.selectedOptions].map(o => o.value)"
    assert page.eval_on_selector("select[name=estimator]", picked) == []


def test_results_bad_sort_key_stays_with_its_error(browser, stack, job_id):
    page = browser.page(stack.base_url)
    sign_in(page, stack.key)
    page.goto(f"/results?job={job_id}")
    sent = []
    page.on("request", lambda r: sent.append(r.url) if "/results/rows" in r.url else None)
    for typed, key in (("-nope", "Enter"), ("-zzz", "Tab")):
        page.fill("#results-sort", typed)
        page.press("#results-sort", key)
        expect(page.locator("#results-grid .error-message")).to_contain_text(typed[1:])
        assert page.input_value("#results-sort") == typed  # what was typed stays
        assert page.get_attribute("#results-grid", "data-sort") == typed
        assert re.search(rf"sort={typed}(&|$)", page.url)
    page.wait_for_load_state("networkidle")
    assert [re.search(r"sort=([^&]*)", u).group(1) for u in sent] == ["-nope", "-zzz"]
    page.fill("#results-sort", "-rmse_A")  # a good key again
    page.press("#results-sort", "Enter")
    page.wait_for_selector("#results-grid[data-sort='-rmse_A'] table")
    assert page.locator("#results-grid .error-message").count() == 0


def test_an_edit_made_while_the_grid_is_on_its_way_is_applied(browser, stack, job_id):
    """A bound typed while the grid of the range's field is still on its way is sent by
    Apply once that grid lands: the grid in place is compared with what it was made
    from, not with the boxes."""
    page = browser.page(stack.base_url)
    sign_in(page, stack.key)
    page.goto(f"/results?job={job_id}")
    held = []
    page.route(re.compile(r"/results/rows\?"), lambda route: held.append(route))
    page.select_option(".range-field", "rmse_A")  # its grid is held on the way
    for _ in range(400):  # until the route has the request
        if held:
            break
        page.wait_for_timeout(25)
    page.fill(".range-max", "0.05")  # typed meanwhile (no change event yet)
    held[0].continue_()
    page.unroute(re.compile(r"/results/rows\?"))
    page.wait_for_selector("#results-grid[data-query*='rf=rmse_A']")
    page.click("#results-filters button[type=submit]")
    page.wait_for_selector("#results-grid[data-query*='rmax=0.05']")
    values = [float(v) for v in grid_column(page, "rmse_A")]
    assert values and max(values) < 0.05


def test_apply_asks_again_for_an_unchanged_view_and_once_for_an_edit(browser, stack, job_id):
    """Apply, or Enter in a box, with nothing changed asks for the grid again (a running
    job's new rows), also when every field of the form is filled; a box edited, then
    Apply: one request (the box's change and the button's submit are one action)."""
    page = browser.page(stack.base_url)
    sign_in(page, stack.key)
    page.goto(f"/results?job={job_id}&rep=0&rf=rmse_A&rmin=0&rmax=1e9&sort=N&hide=rmse_B")
    sent = []
    page.on("request", lambda r: sent.append(r.url) if "/results/rows" in r.url else None)
    apply = "#results-filters button[type=submit]"
    for act in (lambda: page.click(apply), lambda: page.press("#results-sort", "Enter")):
        page.eval_on_selector("#results-grid", "g => { g.dataset.stale = 'yes'; }")
        act()
        page.wait_for_selector("#results-grid:not([data-stale])", timeout=5000)
    page.fill("#results-sort", "-N")
    page.click(apply)
    page.wait_for_selector("#results-grid[data-sort='-N']")
    page.wait_for_load_state("networkidle")
    assert [re.search(r"sort=([^&]*)", u).group(1) for u in sent] == ["N", "N", "-N"]
    assert "sort=-N&" in page.url and "hide=rmse_B" in page.url


def test_job_chart_link_with_a_bad_field_says_why_and_falls_back(browser, stack, job_id):
    page = browser.page(stack.base_url)
    sign_in(page, stack.key)
    for bad in ("nope", "sigma_w"):  # no field; a grid coordinate
        page.goto(f"/jobs/{job_id}?metric={bad}&x=sigma_w")
        status = page.locator("#chart-status")
        expect(status).to_contain_text("metric: must be a numeric record field of the summaries")
        wait_charts(page, 1)
        expect(status).to_contain_text(f"“{bad}”")
        assert page.input_value("#chart-metric") == "rmse_A"
        assert page.input_value("#chart-x") == "sigma_w"  # the rest of the view kept
        fields = page.eval_on_selector_all("#chart-metric option", "os => os.map(o => o.value)")
        assert bad not in fields and {"rmse_A", "H_A", "eps_A"} <= set(fields)
        assert "metric=" not in page.url and "x=sigma_w" in page.url
    page.select_option("#chart-metric", "H_A")
    wait_charts(page, 2)
    assert page.evaluate(Y_TITLE).startswith("H_A")
    assert "must be" not in page.inner_text("#chart-status")
    assert page.eval_on_selector_all("#chart-metric option", "os => os.length") == len(fields)


def back(page, step) -> None:
    """Back or forward, then wait for the page the URL names (a fresh document)."""
    page.evaluate("window.svrobsOld = true")
    step()
    page.wait_for_function(
        "() => window.svrobsOld === undefined && !!document.getElementById('results-grid')"
    )


Y_TITLE = "() => window.svrobsCharts.charts[0].chart.options.scales.y.title.text"


def test_job_chart_choices_live_in_the_url_and_a_late_answer_is_dropped(browser, stack, job_id):
    page = browser.page(stack.base_url)
    sign_in(page, stack.key)
    page.goto(f"/jobs/{job_id}")
    wait_charts(page, 1)
    page.select_option("#chart-x", "sigma_w")
    wait_charts(page, 2)
    page.select_option("#chart-metric", "H_A")
    wait_charts(page, 3)
    panel = page.eval_on_selector("#chart-panel", "s => s.options[2].value")
    page.click("#chart-panel-next")  # all -> the first panel -> the second
    page.click("#chart-panel-next")
    assert page.input_value("#chart-panel") == panel
    page.uncheck("#chart-bands")
    assert re.search(r"x=sigma_w", page.url) and "metric=H_A" in page.url and "bands=0" in page.url
    page.reload()
    wait_charts(page, 1)
    assert page.input_value("#chart-x") == "sigma_w" and page.input_value("#chart-metric") == "H_A"
    assert page.input_value("#chart-panel") == panel and not page.is_checked("#chart-bands")
    assert page.evaluate("window.svrobsCharts.charts.length") == 1
    assert page.evaluate(Y_TITLE).startswith("H_A")  # the glossary's label and unit
    assert "Theorem 1" in page.inner_text("#chart-field-help")
    for _ in range(4):  # bands on again, the first panel, all panels, then rmse_A
        page.go_back()
    page.wait_for_function(
        "() => window.svrobsCharts.data.metric === 'rmse_A'"
        " && document.getElementById('charts-card').dataset.state === 'ready'"
    )
    assert (
        page.input_value("#chart-metric") == "rmse_A" and page.input_value("#chart-x") == "sigma_w"
    )
    loads = int(page.get_attribute("#charts-card", "data-loads"))
    sent = page.evaluate("window.svrobsCharts.requests")

    held = []  # the answer for eps_A is held back until r_A's has been drawn
    page.route(re.compile(r"/chart-data\?metric=eps_A"), lambda route: held.append(route))
    page.select_option("#chart-metric", "eps_A")
    page.wait_for_function(f"() => window.svrobsCharts.requests === {sent + 1}")
    page.select_option("#chart-metric", "r_A")
    wait_charts(page, loads + 1)
    assert held, "the eps_A request was not sent"
    dropped = page.evaluate("window.svrobsCharts.dropped")  # before the late answer can land
    held[0].continue_()
    page.wait_for_function(f"() => window.svrobsCharts.dropped === {dropped + 1}")
    assert page.evaluate("window.svrobsCharts.data.metric") == "r_A"
    assert page.input_value("#chart-metric") == "r_A"
    assert page.evaluate(Y_TITLE).startswith("r_A")
    assert page.get_attribute("#charts-card", "data-loads") == str(loads + 1)
    page.unroute(re.compile(r"/chart-data\?metric=eps_A"))


def test_job_page_progress_in_cells_and_log_y_as_the_data_arrive(browser, stack):
    stack.stop("worker1")
    try:
        with stack.client() as api:
            jid = submit(api, {**SPEC, "seed": 9}, name="arriving")["id"]
        page = browser.page(stack.base_url)
        sign_in(page, stack.key)
        page.goto(f"/jobs/{jid}")
        wait_charts(page, 1)
        assert "No summaries yet" in page.inner_text("#chart-status")
        assert not page.is_checked("#chart-logy")  # nothing to plot: no log axis yet
        assert page.inner_text("#job-progress-text") == "0 of 72 cells"
    finally:
        stack.start_worker()
    page.wait_for_selector("#job-status:text('succeeded')", timeout=180_000)
    page.wait_for_function(
        "() => window.svrobsCharts.data && window.svrobsCharts.data.status === 'succeeded'"
        " && window.svrobsCharts.data.panels.length === 4"
    )
    assert page.is_checked("#chart-logy")  # every mean > 0: the log axis, as on a fresh load
    assert {
        c
        for c in page.evaluate(
            "() => window.svrobsCharts.charts.map(c => c.chart.options.scales.y.type)"
        )
    } == {"logarithmic"}
    assert page.inner_text("#job-progress-text") == "72 of 72 cells"
    fresh = browser.page(stack.base_url)
    sign_in(fresh, stack.key)
    fresh.goto(f"/jobs/{jid}")
    wait_charts(fresh, 1)
    assert fresh.is_checked("#chart-logy")


# the preset form's submits, counted and held (until svrobsSubmits is set to null)
COUNT_SUBMITS = """() => {
  window.svrobsSubmits = 0;
  document.getElementById("preset-form").addEventListener("submit", (e) => {
    if (window.svrobsSubmits === null) return;
    window.svrobsSubmits += 1;
    e.preventDefault();
  });
}"""


def test_spec_form_json_in_sync_and_every_error_at_once(browser, stack):
    page = browser.page(stack.base_url)
    sign_in(page, stack.key)
    page.goto("/jobs/new")
    page.fill("#name", "mine")
    page.focus("#preset")
    page.evaluate(COUNT_SUBMITS)
    page.keyboard.press("ArrowDown")  # a choice in the list is no submit (WCAG 3.2.2)
    assert page.input_value("#preset") == "system:paper-stable"
    assert page.evaluate("window.svrobsSubmits") == 0
    assert page.input_value("#name") == "mine" and "preset=" not in page.url
    page.evaluate("window.svrobsSubmits = null")  # the button goes on
    page.click("#preset-fill")
    page.wait_for_url(re.compile(r"preset=system%3Apaper-stable"))
    assert page.input_value("#name") == "paper-stable sweep"
    assert page.input_value("#tags") == "sweep, paper-stable"
    assert page.is_checked("input[name='m.N'][value=range]")
    assert page.input_value("input[name='r.N.stop']") == "100"
    assert page.is_hidden("#field-S")  # an option of another bounds method
    page.select_option("#f-bounds_method", "self-normalized")
    assert page.is_visible("#field-S")
    page.select_option("#f-bounds_method", "paper")
    # fields -> JSON
    page.fill("#f-sigma_w", "-1, 1")
    page.fill("#f-gamma", "0, 0.1")
    spec = json.loads(page.input_value("#spec"))
    assert spec["sigma_w"] == [-1, 1] and spec["gamma"] == [0, 0.1] and "S" not in spec
    assert page.is_checked("input[name=source][value=form]")
    # JSON -> fields; a seed beyond 2^53 (a JS number would round it) kept digit for digit
    page.fill("#spec", json.dumps({**spec, "reps": 0, "seed": 2**63 - 1}))
    assert page.input_value("#f-reps") == "0"
    assert page.input_value("#f-seed") == str(2**63 - 1)
    page.fill("#f-M", "1.2")  # the fields again: the JSON keeps reps = 0
    assert json.loads(page.input_value("#spec"))["reps"] == 0
    assert json.loads(page.input_value("#spec"))["seed"] == 2**63 - 1
    page.fill("#f-seed", "9007199254740993")  # typed in the field: the JSON has it
    assert json.loads(page.input_value("#spec"))["seed"] == 9007199254740993
    page.click("#submit-job")
    page.wait_for_selector("#form-errors")
    beside = {f: page.inner_text(f"#err-{f}") for f in ("sigma_w", "reps", "gamma")}
    assert beside == {
        "sigma_w": "sigma_w[0]: must be >= 0",
        "reps": "reps: must be >= 1",
        "gamma": "gamma[0]: must be > 0",
    }
    assert page.locator("#form-errors li").count() == 3
    assert page.evaluate("document.activeElement.id") == "form-errors"
    page.click("#form-errors a[href='#field-gamma']")  # the list's link: into the field
    assert page.evaluate("document.activeElement.id") == "f-gamma"
    assert page.input_value("#f-sigma_w") == "-1, 1"  # as typed
    assert page.locator("#f-reps[aria-invalid=true]").count() == 1
    page.fill("#f-sigma_w", "0.5")
    page.fill("#f-gamma", "0.05")
    page.fill("#f-reps", "2")
    page.click("#submit-job")
    page.wait_for_url(re.compile(r"/jobs/\d+$"))
    with stack.client() as api:
        job = api.get(f"/jobs/{page.url.rsplit('/', 1)[1]}").json()
    assert job["name"] == "paper-stable sweep" and job["tags"] == ["sweep", "paper-stable"]
    assert job["spec"]["sigma_w"] == [0.5] and job["spec"]["M"] == 1.2
    assert job["spec"]["seed"] == 9007199254740993
    assert job["spec"]["N"] == list(range(10, 101, 10)) and job["spec"]["reps"] == 2


def test_scatter_and_certificates_views(browser, stack, job_id):
    page = browser.page(stack.base_url)
    sign_in(page, stack.key)
    page.goto(f"/jobs/{job_id}")
    page.click("#scatter-view summary")
    page.wait_for_selector("#views-card[data-scatter=ready]")
    page.select_option("#scatter-metric", "eps_A")
    drawn = page.evaluate(
        """() => window.svrobsViews.scatter.map(s => ({x: s.x, points: s.chart.data.datasets
          .flatMap(d => d.data.map(p => [p.g.system, p.g.sigma_w, p.g.N, p.g.estimator,
            p.g.gamma, p.x, p.y]))}))"""
    )
    with stack.client() as api:
        groups = api.get(f"/jobs/{job_id}/summary").json()["groups"]
        rows = api.get(f"/jobs/{job_id}/results", params={"limit": 1000}).json()["items"]
    for panel in drawn:
        want = sorted(
            [
                g["system"],
                g["sigma_w"],
                g["N"],
                g["estimator"],
                g["gamma"],
                g[panel["x"]],
                g["stats"]["eps_A"]["mean"],
            ]
            for g in groups
            if g[panel["x"]] is not None
        )
        assert sorted(panel["points"]) == want, panel["x"]
    assert {p["x"] for p in drawn} == {"gamma", "N", "sigma_w"}

    page.click("#certificates-view summary")
    page.wait_for_selector("#views-card[data-certificates=ready]")
    cells = page.eval_on_selector_all(
        "#certificates-table td.cert[data-n]",
        """tds => tds.map(td => { const r = td.parentElement.cells;
          return [r[0].textContent, r[1].textContent, r[2].textContent, r[3].textContent,
            Number(td.dataset.n), Number(td.dataset.stable)]; })""",
    )
    got = {tuple(c[:5]): c[5] for c in cells}
    share: dict = {}  # the oracle: the result rows themselves
    for r in rows:
        gamma = "—" if r["gamma"] is None else f"{r['gamma']:g}"
        k = (r["system"], f"{r['sigma_w']:g}", r["estimator"], gamma, r["N"])
        share.setdefault(k, []).append(r["stable_certified"])
    assert "Bounds method: paper" in page.inner_text("#certificates-note")
    assert set(got) == set(share) and len(got) == 2 * 2 * 3 * 2
    for k, flags in share.items():
        known = [f for f in flags if f is not None]
        assert abs(got[k] - sum(known) / len(known)) < 1e-12, k


def test_runs_table_ticks_runs_to_compare_and_chooses_columns(browser, stack, job_id):
    with stack.client() as api:
        other = submit(api, {**SPEC, "seed": 10}, name="views other")["id"]
        stack.wait_job(api, other)
    page = browser.page(stack.base_url)
    sign_in(page, stack.key)
    assert page.is_disabled("#compare-selected")
    page.check(f"#job-{job_id} .run-pick")
    page.check(f"#job-{other} .run-pick")
    assert page.inner_text("#runs-selected").startswith("2 runs ticked")
    assert page.inner_text(f"#job-{job_id} td[data-col=duration]").endswith(" s")
    page.click("#runs-columns summary")
    page.uncheck("#runs-columns input[value=owner]")
    assert page.locator("#jobs-table th[data-col=owner]").is_hidden()
    assert "hide=owner" in page.url
    page.click("#compare-selected")
    page.wait_for_selector("#compare-card[data-ready=yes]")
    assert sorted(page.evaluate("window.svrobsCompare.data.jobs")) == sorted([job_id, other])
    page.go_back()
    page.wait_for_selector("#jobs-table")
    assert page.locator("#jobs-table th[data-col=owner]").is_hidden()  # from the URL


def test_runs_table_deletes_the_ticked_after_a_confirmation(browser, stack):
    tiny = {"systems": ["paper-stable"], "sigma_w": [1.0], "N": [10], "reps": 2}
    with stack.client() as api:
        ids = [submit(api, {**tiny, "seed": s}, name=f"to delete {s}")["id"] for s in (1, 2)]
        for i in ids:
            stack.wait_job(api, i)
    page = browser.page(stack.base_url)
    sign_in(page, stack.key)
    page.goto("/jobs?sort=-duration,id&metric=rmse_A&at=10")
    assert page.locator("#jobs-table th[data-col=metric]").inner_text() == "RMSE Â at N = 10"
    for i in ids:
        page.check(f"#job-{i} .run-pick")
    page.click("#delete-selected")
    page.wait_for_url(re.compile(r"/jobs/delete\?"))
    assert page.locator("#delete-list li").count() == 2
    with stack.client() as api:  # asking is not deleting
        assert all(api.get(f"/jobs/{i}").status_code == 200 for i in ids)
    page.click("#confirm-delete-many")
    page.wait_for_selector("#deleted-flash")
    with stack.client() as api:
        assert all(api.get(f"/jobs/{i}").status_code == 404 for i in ids)
