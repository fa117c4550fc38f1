"""A newcomer's path in a real chromium, with no JSON typed: sign in, submit two jobs
from a preset and a few fields of the spec form, wait for them, compare them on the
compare page (checkboxes), make a labelled share link of one and open it signed
out; and a cell's page, opened from its results row, showing the matrices of the
API's record for that cell."""

from __future__ import annotations

import re

import pytest

from svrobs_core.records import FIELD_GLOSSARY, MATRIX_FIELDS
from tests.integration.stack import submit

from . import test_browser as base

browser = base.browser
only_the_server = base.only_the_server
pytestmark = base.pytestmark
DONE = "#job-progress[data-status=succeeded]"
KEYS = ("system", "sigma_w", "N", "estimator", "gamma", "rep")


def submit_from_the_form(page, *, name: str, seed: int) -> int:
    """The spec form filled by a preset, then narrowed in its fields; the job's id."""
    base.follow(page, "header nav a[href='/jobs/new']")
    page.select_option("#preset", "system:paper-stable")
    page.click("#preset-fill")  # opens the filled form
    page.wait_for_url(re.compile(r"preset=system%3Apaper-stable"))
    page.fill("#name", name)
    page.fill("#f-sigma_w", "1.0")
    page.fill("input[name='r.N.stop']", "30")
    page.fill("#f-gamma", "0.05")
    page.fill("#f-reps", "2")
    page.fill("#f-seed", str(seed))
    page.check("input[name='f.stages'][value=gain]")
    assert page.is_checked("input[name=source][value=form]")
    page.click("#submit-job")
    page.wait_for_url(re.compile(r"/jobs/\d+$"))
    return int(page.url.rsplit("/", 1)[1])


def test_sign_in_submit_two_compare_and_share_without_json(browser, stack):
    page = browser.page(stack.base_url)
    page.goto("/")
    page.wait_for_url(re.compile(r"/login"))
    page.fill("#key", stack.key)
    page.click("form[action='/login'] button[type=submit]")
    page.wait_for_url(re.compile(r"/jobs$"))

    ids = [submit_from_the_form(page, name=f"first try seed {s}", seed=s) for s in (21, 22)]
    with stack.client() as api:
        for i in ids:
            job = api.get(f"/jobs/{i}").json()
            assert job["name"] == f"first try seed {21 + ids.index(i)}"
            assert job["spec"]["N"] == [10, 20, 30] and job["spec"]["sigma_w"] == [1.0]
            assert "gain" in job["spec"]["stages"]
    for i in ids:
        page.goto(f"/jobs/{i}")
        page.wait_for_selector(DONE, timeout=300_000)  # the progress card polls

    base.follow(page, "header nav a[href='/compare']")
    for i in ids:
        page.check(f"#compare-jobs input[value='{i}']")
    page.select_option("#compare-metric", "rmse_A")
    page.click("#compare-form button[type=submit]")
    page.wait_for_selector("#compare-card[data-ready=yes]")
    by = page.eval_on_selector_all("#compare-by input:checked", "els => els.map(e => e.value)")
    with stack.client() as api:
        want = api.get(
            "/compare",
            params={"jobs": ",".join(map(str, ids)), "metric": "rmse_A", "by": ",".join(by)},
        ).json()
    means = page.locator("#compare-table tbody td.num:nth-last-child(3)").all_inner_texts()
    assert means == ["%.4g" % r["mean"] for r in want["rows"]] and means
    assert {
        int(t) for t in page.locator("#compare-table tbody td:first-child").all_inner_texts()
    } == set(ids)
    assert "seed" in page.inner_text("#spec-diff")  # what differs: the seed

    page.click(f"#compare-table tbody a[href='/jobs/{ids[0]}']")
    page.wait_for_url(re.compile(rf"/jobs/{ids[0]}$"))
    page.click("#share-link")
    page.fill("#share-label", "for my supervisor")
    page.click("#share-form button[type=submit]")
    page.wait_for_selector("#share-created[data-state=shown]")
    url = page.input_value("#new-share-url")
    assert re.search(r"/s/[\w-]{40,}$", url), url
    assert page.inner_text("#share-links tr.just-made .share-label") == "for my supervisor"
    with stack.client() as api:
        links = api.get(f"/jobs/{ids[0]}/shares").json()
    assert [s["label"] for s in links] == ["for my supervisor"]

    guest = browser.page(stack.base_url)  # signed out: no cookie
    response = guest.goto(url)
    assert response.status == 200 and f"Job {ids[0]}" in guest.inner_text("h1")
    guest.wait_for_selector("#charts-card[data-state=ready] canvas")
    assert guest.locator("header nav a[href='/jobs']").count() == 0
    assert guest.goto("/jobs").url.endswith("/login?next=%2Fjobs")  # and no more


@pytest.fixture(scope="module")
def gain_job(stack) -> int:
    spec = {
        "systems": ["paper-stable"],
        "sigma_w": [1.0],
        "N": [20],
        "gamma": [0.05],
        "reps": 2,
        "stages": ["estimate", "bounds", "gain"],
        "seed": 9,
    }
    with stack.client() as api:
        jid = submit(api, spec, name="cell page")["id"]
        stack.wait_job(api, jid)
    return jid


def test_a_cells_page_shows_the_apis_matrices(browser, stack, gain_job):
    page = browser.page(stack.base_url)
    base.sign_in(page, stack.key)
    page.goto(f"/jobs/{gain_job}")
    base.follow(page, f"a[href='/results?job={gain_job}']")
    page.select_option("select[data-filter=estimator]", "svr")
    page.wait_for_selector("#results-grid[data-query*='estimator=svr']")
    row = page.locator("#results-grid tbody tr").nth(1)
    coords = {k: row.locator(f"td[data-field='{k}']").get_attribute("data-value") for k in KEYS}
    row.locator("a.cell-link").click()
    page.wait_for_url(re.compile(r"/results/cell\?"))
    got = page.evaluate(
        """() => Object.fromEntries([...document.querySelectorAll("figure.matrix")].map(f => [
          f.dataset.field,
          [...f.querySelectorAll("tbody tr")].map(tr => [...tr.querySelectorAll("td")].map(
            td => td.dataset.value === "" ? null : Number(td.dataset.value)))]))"""
    )
    params = {**coords, "gamma": coords["gamma"] or "null"}
    api = page.request.get(f"/api/v1/jobs/{gain_job}/results", params=params).json()
    assert api["total"] == 1
    record = api["items"][0]
    assert set(got) == set(MATRIX_FIELDS)  # estimate, bounds and gain: all six
    for field in MATRIX_FIELDS:
        assert got[field] == record[field], field
        caption = page.inner_text(f"#matrix-{field} figcaption")
        label, unit, _ = FIELD_GLOSSARY[field]
        assert caption.startswith(label) and unit in caption
    for field in ("system", "N", "rep"):  # the coordinates it names
        assert page.get_attribute(f"#cell-keys dd[data-field={field}]", "data-value") == str(
            record[field]
        )
    base.follow(page, "#cell-back")  # back to the same filtered view
    page.wait_for_selector("#results-grid[data-query*='estimator=svr']")
