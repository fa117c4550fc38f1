"""The results, compare, schedules and share pages and the API docs in a real chromium
against a real server (the stack and browser of test_browser): the grid filters and
sorts like the API, the compare chart plots the API's compare, a schedule is made from
a job, a share link opens without cookies and is a 404 once revoked, and /docs and
/redoc load nothing from another host (checked after every test, as in test_browser)."""

from __future__ import annotations

import re

import pytest

from tests.integration.stack import submit

from . import test_browser as base
from .test_browser import assert_charts_equal_summary, follow, sign_in, wait_charts

# the module's chromium and the after-each-test check (no foreign request, no error)
browser = base.browser
only_the_server = base.only_the_server

pytestmark = base.pytestmark  # integration, chromium, the embedded stack

SPEC = {
    "systems": ["paper-stable", "paper-unstable"],
    "sigma_w": [0.1, 1.0],
    "N": [10, 20],
    "gamma": [0.01, 0.1],
    "estimators": ["ols", "svr"],
    "reps": 2,
    "seed": 5,
}


@pytest.fixture(scope="module")
def two_jobs(stack) -> list[int]:
    with stack.client() as api:
        ids = [submit(api, {**SPEC, "seed": s}, name=f"sweep seed {s}")["id"] for s in (5, 6)]
        for i in ids:
            stack.wait_job(api, i)
    return ids


@pytest.fixture(scope="module")
def estimate_only(stack) -> int:
    """A job that differs from two_jobs in N, γ, reps, stages and seed: no bounds stage,
    so no values of H_A."""
    spec = {**SPEC, "N": [10, 30], "gamma": [0.05], "reps": 3, "stages": ["estimate"], "seed": 7}
    with stack.client() as api:
        jid = submit(api, spec, name="estimate only")["id"]
        stack.wait_job(api, jid)
    return jid


MEAN_LINES = """() => window.svrobsCompare.chart.data.datasets
  .filter(d => d.svrobs.role === "mean").map(d => [d.svrobs.job, d.label])"""


def open_compare(page, jobs: list[int], metric: str) -> list[list]:
    """/compare of these jobs and metric: its lines as [job, label]."""
    page.goto(f"/compare?{'&'.join(f'jobs={j}' for j in jobs)}&metric={metric}")
    page.wait_for_selector("#compare-card[data-ready=yes]")
    return page.evaluate(MEAN_LINES)


def grid_values(page, field: str) -> list[str]:
    return page.eval_on_selector_all(
        f"#results-grid td[data-field='{field}']", "tds => tds.map(td => td.dataset.value)"
    )


def test_results_filter_and_sort(browser, stack, two_jobs):
    job_id = two_jobs[0]
    page = browser.page(stack.base_url)
    sign_in(page, stack.key)
    follow(page, "nav a[href='/results']")
    page.select_option("#results-job", str(job_id))
    page.click("#results-job-form button[type=submit]")
    page.wait_for_url(re.compile(rf"/results\?job={job_id}$"))
    with stack.client() as api:
        everything = api.get(f"/jobs/{job_id}/results", params={"limit": 1}).json()["total"]
        want = api.get(
            f"/jobs/{job_id}/results",
            params={"system": "paper-unstable", "N": 20, "sort": "-rmse_A", "limit": 50},
        ).json()
    assert page.get_attribute("#results-grid", "data-total") == str(everything)
    page.evaluate("window.notReloaded = true")
    page.select_option("select[name=system]", "paper-unstable")  # htmx replaces the grid
    page.wait_for_selector(f"#results-grid[data-total='{everything // 2}']")
    page.select_option("select[name=N]", "20")
    page.wait_for_selector(f"#results-grid[data-total='{want['total']}']")
    assert set(grid_values(page, "system")) == {"paper-unstable"}
    assert set(grid_values(page, "N")) == {"20"}
    page.click("th a[data-sort-field='rmse_A']")  # ascending, then descending
    page.wait_for_selector("#results-grid[data-sort='rmse_A']")
    page.click("th a[data-sort-field='rmse_A']")
    page.wait_for_selector("#results-grid[data-sort='-rmse_A']")
    got = [float(v) for v in grid_values(page, "rmse_A")]
    assert got == [r["rmse_A"] for r in want["items"]]
    assert got == sorted(got, reverse=True)
    assert page.input_value("#results-sort") == "-rmse_A"  # the filters keep the sort
    # a range of a numeric field, as the API's rmse_A_lt
    cut = got[len(got) // 2]
    page.select_option(".range-field", "rmse_A")
    page.fill(".range-max", repr(cut))
    page.click("#results-filters button[type=submit]")
    n_below = sum(v < cut for v in got)
    page.wait_for_selector(f"#results-grid[data-total='{n_below}']")
    below = [float(v) for v in grid_values(page, "rmse_A")]
    assert below == sorted((v for v in got if v < cut), reverse=True)
    assert page.evaluate("window.notReloaded") is True


def test_compare_two_jobs_plots_the_api_compare(browser, stack, two_jobs):
    page = browser.page(stack.base_url)
    sign_in(page, stack.key)
    follow(page, "nav a[href='/compare']")
    for i in two_jobs:  # a labelled checkbox per job
        page.get_by_label(re.compile(rf"#{i} sweep seed \d")).check()
    page.select_option("#compare-metric", "rmse_B")
    assert page.locator("#compare-metric option[value=N]").count() == 0  # not a metric
    page.click("#compare-form button[type=submit]")
    page.wait_for_selector("#compare-card[data-ready=yes]")
    plotted = page.evaluate(
        """() => window.svrobsCompare.chart.data.datasets.filter(d => d.svrobs.role === "mean")
          .map(d => ({label: d.label, job: d.svrobs.job, estimator: d.svrobs.group.estimator,
            gamma: d.svrobs.group.gamma, points: d.data.map(p => [p.x, p.y])}))"""
    )
    assert not page.is_checked("#compare-bands")  # six lines: no bands unless asked
    page.check("#compare-bands")
    assert "bands=1" in page.url
    bands = page.evaluate(
        """() => window.svrobsCompare.chart.data.datasets.filter(d => d.svrobs.role === "band")
          .length"""
    )
    with stack.client() as api:
        cmp = api.get(
            "/compare",
            params={
                "jobs": ",".join(map(str, two_jobs)),
                "metric": "rmse_B",
                "by": "N,estimator,gamma",
            },
        ).json()
    want: dict[tuple, list] = {}
    for r in cmp["rows"]:
        want.setdefault((r["job_id"], r["estimator"], r["gamma"]), []).append([r["N"], r["mean"]])
    got = {(p["job"], p["estimator"], p["gamma"]): p["points"] for p in plotted}
    assert got == {k: sorted(v) for k, v in want.items()}
    assert len(plotted) == 2 * 3 and bands == 2 * len(plotted)  # a ± std band per line
    assert page.locator("#compare-table tbody tr").count() == len(cmp["rows"])
    # the legend says what differs: the jobs' seeds, the estimator and γ; nothing else
    labels = {(p["job"], p["estimator"], p["gamma"]): p["label"] for p in plotted}
    a, b = two_jobs
    assert labels[(a, "ols", None)] == "seed=5 · ols"
    assert labels[(b, "svr", 0.01)] == "seed=6 · svr γ=0.01"
    heads = page.locator("#spec-diff-table thead th").all_inner_texts()
    rows = [r.split("\t") for r in page.inner_text("#spec-diff-table tbody").split("\n")]
    seeds = {f"job {a}": "5", f"job {b}": "6"}
    assert rows == [["seed", *(seeds[h.split(" · ")[0]] for h in heads[1:])]]
    # another comparison from the form keeps the bands and log-y choices of the URL
    page.uncheck("#compare-logy")
    assert "logy=0" in page.url
    page.select_option("#compare-metric", "rmse_A")
    page.click("#compare-form button[type=submit]")
    page.wait_for_url(re.compile(r"metric=rmse_A"))
    page.wait_for_selector("#compare-card[data-ready=yes]")
    assert "logy=0" in page.url and "bands=1" in page.url
    assert not page.is_checked("#compare-logy") and page.is_checked("#compare-bands")


def test_compare_labels_tell_every_job_apart(browser, stack, two_jobs, estimate_only):
    page = browser.page(stack.base_url)
    sign_in(page, stack.key)
    a, b = two_jobs  # these two differ only by their seed
    lines = open_compare(page, [a, b, estimate_only], "rmse_A")
    assert {job for job, _ in lines} == {a, b, estimate_only}
    for job, label in lines:
        assert not [j for j, other in lines if other == label and j != job], label
    prefix = {job: label.split(" · ")[0] for job, label in lines}
    assert prefix[a] == "seed=5" and prefix[b] == "seed=6" and prefix[estimate_only] == "N=[10,30]"


def test_compare_names_the_jobs_without_values(browser, stack, two_jobs, estimate_only):
    page = browser.page(stack.base_url)
    sign_in(page, stack.key)
    a = two_jobs[0]
    lines = open_compare(page, [a, estimate_only], "H_A")
    assert {job for job, _ in lines} == {a}
    assert page.inner_text("#compare-missing") == (
        f"No values of H_A (H_A) in job {estimate_only}: it has no line."
    )
    assert open_compare(page, [estimate_only], "H_A") == []
    missing = page.inner_text("#compare-missing")
    assert missing == f"No values of H_A (H_A) in job {estimate_only}: nothing to draw."
    open_compare(page, [a], "H_A")
    assert page.locator("#compare-missing").count() == 0


def test_create_a_schedule_from_a_job(browser, stack, two_jobs):
    job_id = two_jobs[1]
    page = browser.page(stack.base_url)
    sign_in(page, stack.key)
    page.goto(f"/jobs/{job_id}")
    page.click("#schedule-link")
    page.fill("input[name=name]", "nightly from the browser")
    page.fill("input[name=cron]", "30 1 * * *")
    page.check("input[name=seed_policy][value=due-time]")
    page.click("#schedule-form button[type=submit]")
    page.wait_for_url(re.compile(r"/schedules/\d+$"))
    sid = int(page.url.rsplit("/", 1)[1])
    assert page.inner_text("#schedule-seed-policy").startswith("due-time")
    assert page.inner_text("#schedule-enabled") == "yes"
    page.click("#schedule-toggle")
    page.wait_for_selector("#schedule-enabled:text('no')")
    with stack.client() as api:
        s = api.get(f"/schedules/{sid}").json()
        job = api.get(f"/jobs/{job_id}").json()
    assert s["spec_template"] == job["spec"] and s["seed_policy"] == "due-time"
    assert s["cron"] == "30 1 * * *" and s["enabled"] is False
    follow(page, "nav a[href='/schedules']")
    assert page.locator(f"tr[data-schedule='{sid}']").count() == 1


def test_share_link_opens_without_cookies_and_404s_once_revoked(browser, stack, two_jobs):
    job_id = two_jobs[0]
    page = browser.page(stack.base_url)
    sign_in(page, stack.key)
    page.goto(f"/jobs/{job_id}")
    page.click("#share-link")
    page.context.grant_permissions(["clipboard-read", "clipboard-write"])
    page.fill("#share-label", "for the reviewers")
    page.click("#share-form button[type=submit]")
    page.wait_for_selector("#share-created[data-state=shown]")
    url = page.input_value("#new-share-url")
    assert url.startswith(stack.base_url + "/s/") and stack.key not in url
    assert page.url == f"{stack.base_url}/jobs/{job_id}/share"  # no token left in the URL
    page.click("#copy-share-url")
    page.wait_for_selector(".copy-status:text('Copied.')")
    assert page.evaluate("navigator.clipboard.readText()") == url
    row = page.locator("#share-links tr.just-made")
    assert row.locator(".share-label").inner_text() == "for the reviewers"
    page.reload()  # POST-redirect-GET: a reload posts nothing and shows no token
    assert page.locator("#share-created").count() == 0
    assert page.locator("#share-links tbody tr").count() == 1
    with stack.client() as api:
        listed = api.get(f"/jobs/{job_id}/shares").json()
    assert [s["label"] for s in listed] == ["for the reviewers"]

    guest = browser.page(stack.base_url)  # a fresh context: no cookie, no key
    assert guest.context.cookies() == []
    response = guest.goto(url)
    assert response.status == 200 and f"Job {job_id}" in guest.inner_text("h1")
    with stack.client() as api:
        summary = api.get(f"/jobs/{job_id}/summary").json()
    assert_charts_equal_summary(wait_charts(guest, 1), summary, "N", "rmse_A")
    report = guest.request.get(guest.get_attribute("#shared-report", "href"))
    assert report.status == 200 and "Table 2" in report.text()
    assert guest.goto(f"/jobs/{job_id}").url.startswith(stack.base_url + "/login")

    page.goto(f"/jobs/{job_id}/share")
    assert page.locator("#share-links button.danger").count() == 1
    page.once("dialog", lambda d: d.dismiss())  # asked first; declined, nothing changes
    page.click("#share-links button.danger")
    assert guest.goto(url).status == 200
    page.once("dialog", lambda d: d.accept())
    page.click("#share-links button.danger")
    page.wait_for_selector("#share-links td:text('revoked')")
    assert guest.goto(url).status == 404
    assert guest.request.get(url + "/chart-data").status == 404


def test_api_docs_load_nothing_from_another_host(browser, stack):
    page = browser.page(stack.base_url)
    page.goto("/docs")
    page.wait_for_selector(".swagger-ui .info .title")
    assert page.locator("button.authorize").count() == 1  # the declared bearer scheme
    page.click("button.authorize")
    page.wait_for_selector("input[aria-label='auth-bearer-value'], .auth-container input")
    page.goto("/redoc")
    page.wait_for_selector("redoc .api-info, [role=navigation], h1")
    assert "svrobs" in page.inner_text("body")


def test_api_docs_try_it_out_under_the_web_session(browser, stack, two_jobs):
    job_id = two_jobs[0]
    page = browser.page(stack.base_url)
    page.goto("/docs")
    page.wait_for_selector(".swagger-ui .info .title")
    assert page.locator("#docs-session").is_hidden()  # not signed in: the key, as before
    sign_in(page, stack.key)
    page.goto("/docs#/shares/create_share_api_v1_jobs__job_id__shares_post")
    page.wait_for_selector("#docs-session:not([hidden])")
    assert "Signed in to the dashboard" in page.inner_text("#docs-session")
    op = page.locator("#operations-shares-create_share_api_v1_jobs__job_id__shares_post")
    op.locator(".opblock-summary").first.wait_for()
    if not op.locator(".try-out__btn").is_visible():
        op.locator(".opblock-summary").first.click()
    op.locator(".try-out__btn").click()
    op.locator("input[placeholder='job_id']").fill(str(job_id))
    op.locator("textarea.body-param__text").fill('{"days": 1, "label": "from the docs"}')
    with page.expect_response(lambda r: r.url.endswith(f"/jobs/{job_id}/shares")) as made:
        op.locator("button.execute").click()
    assert made.value.status == 201  # a write, with no key: the session and its token
    assert made.value.request.headers.get("x-csrf-token")
    assert "authorization" not in made.value.request.headers
    with stack.client() as api:
        labels = [s["label"] for s in api.get(f"/jobs/{job_id}/shares").json()]
    assert "from the docs" in labels
