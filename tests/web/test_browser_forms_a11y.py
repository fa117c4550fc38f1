"""Forms and charts for keyboards and screen readers, in a real chromium against a real
server (the stack and browser of test_browser): the compare page's checkboxes are
targets of 24 px at phone width; the spec form's grid inputs are named by their field
and described by its help and errors; a schedule form's error list takes the focus and
leads into its fields; the sign-in, submit and upload forms say which field is invalid
and describe fields only by elements that exist; the dataset and validation charts
take the dark theme's colours with a keyboard legend; a dataset job's validation
choices and the scatter view's are in the URL."""

from __future__ import annotations

import re

import numpy as np
import pytest
from playwright.sync_api import expect

from tests.datasets import files
from tests.integration.stack import submit

from . import test_browser as base
from .a11y import violations
from .test_browser import TINY, sign_in
from .test_browser_datasets import upload_bad_csv

browser = base.browser
only_the_server = base.only_the_server
pytestmark = base.pytestmark

DATASET_SPEC = {
    "N": [6, 10],
    "holdout": 4,
    "reps": 2,
    "gamma": [0.05],
    "estimators": ["ols", "svr"],
    "sigma_w": "estimate",
    "seed": 21,
}

# Every aria-describedby id of the page that names no element.
DANGLING = """() => [...document.querySelectorAll("[aria-describedby]")].flatMap(el =>
  el.getAttribute("aria-describedby").split(/\\s+/).filter(id => id && !document.getElementById(id))
    .map(id => (el.id || el.name) + " -> " + id))"""

# Each chart's lines: colour, the HTML legend's buttons, whether the canvas legend shows.
CHARTS = """(charts) => charts.map(c => ({
  colours: c.chart.data.datasets.filter(d => d.svrobs.role !== "band").map(d => d.borderColor),
  canvasLegend: c.chart.options.plugins.legend.display,
  legend: [...c.chart.canvas.closest("figure").querySelectorAll(".legend button")]
    .map(b => b.textContent),
  card: getComputedStyle(c.chart.canvas.closest(".card")).backgroundColor,
}))"""


@pytest.fixture(scope="module")
def site(stack) -> dict:
    """Two simulated jobs (one finished), a schedule, a dataset and a finished job on it."""
    X, U = files.simulate(
        np.array([[0.8, 0.25], [-0.2, 0.75]]), np.array([[0.4], [1.0]]), 17, lengths=(20,) * 14
    )
    with stack.client() as api:
        jobs = [submit(api, {**TINY, "seed": s}, name=f"forms {s}")["id"] for s in (2, 3)]
        stack.wait_job(api, jobs[0])
        r = api.post(
            "/schedules", json={"name": "forms", "cron": "0 2 * * *", "spec_template": TINY}
        )
        assert r.status_code == 201, r.text
        ds = api.post(
            "/datasets",
            files={"file": ("plant.npz", files.npz_bytes(X, U))},
            data={"name": "plant", "sample_time": "0.05"},
        )
        assert ds.status_code == 201, ds.text
        job = submit(api, {**DATASET_SPEC, "dataset": ds.json()["id"]}, name="measured")
        done = stack.wait_job(api, job["id"], timeout=200)
        assert done["status"] == "succeeded", done
        stack.wait_job(api, jobs[1])
    return {
        "jobs": jobs,
        "schedule": r.json()["id"],
        "dataset": ds.json()["id"],
        "dataset_job": job["id"],
    }


@pytest.fixture
def page(browser, stack):
    p = browser.page(stack.base_url)
    sign_in(p, stack.key)
    yield p
    p.context.close()


def luminance(colour: str) -> float:
    """The relative luminance (WCAG) of ``#rrggbb`` or ``rgb(r, g, b)``."""
    if colour.startswith("#"):
        rgb = [int(colour[i : i + 2], 16) for i in (1, 3, 5)]
    else:
        rgb = [int(v) for v in re.findall(r"\d+", colour)[:3]]
    lin = [c / 255 / 12.92 if c <= 10 else ((c / 255 + 0.055) / 1.055) ** 2.4 for c in rgb]
    return 0.2126 * lin[0] + 0.7152 * lin[1] + 0.0722 * lin[2]


def contrast(a: str, b: str) -> float:
    hi, lo = sorted((luminance(a), luminance(b)), reverse=True)
    return (hi + 0.05) / (lo + 0.05)


def test_compare_checkboxes_are_24_px_targets_at_phone_width(browser, stack, site):
    page = browser.page(stack.base_url, width=375, height=667)
    sign_in(page, stack.key)
    a, b = site["jobs"]
    page.goto(f"/compare?jobs={a}&jobs={b}&metric=rmse_A")
    page.wait_for_selector("#compare-card[data-ready=yes]")
    assert page.locator("#compare-jobs input[type=checkbox]").count() >= 2
    assert page.locator("#compare-by input[type=checkbox]").count() >= 2
    assert [v for v in violations(page) if v["id"] == "target-size"] == []
    page.context.close()


def test_spec_form_grid_inputs_are_named_and_described_by_their_field(page):
    page.goto("/jobs/new?preset=system%3Apaper-stable")  # N as start / stop / step
    assert page.is_checked("input[name='m.N'][value=range]")
    page.fill("#f-sigma_w", "-1")
    page.fill("input[name='r.N.start']", "0")
    page.click("#submit-job")
    page.wait_for_selector("#form-errors")
    sigma = page.get_by_role("textbox", name="sigma_w values", exact=True)
    expect(sigma).to_have_attribute("aria-describedby", "help-sigma_w err-sigma_w")
    expect(sigma).to_have_attribute("aria-invalid", "true")
    expect(page.locator("#err-sigma_w")).to_contain_text("sigma_w[0]")
    for part in ("start", "stop", "step"):
        box = page.get_by_role("textbox", name=f"N {part}", exact=True)
        expect(box).to_have_attribute("aria-describedby", "help-N err-N")
        expect(box).to_have_attribute("aria-invalid", "true")
    expect(page.locator("#err-N")).to_be_visible()
    gamma = page.get_by_role("textbox", name="gamma values", exact=True)  # valid
    expect(gamma).to_have_attribute("aria-describedby", "help-gamma")
    assert gamma.get_attribute("aria-invalid") is None
    assert page.locator("fieldset.grid-field[aria-describedby]").count() == 0
    assert page.evaluate(DANGLING) == []


def schedule_errors_lead_into_their_fields(page) -> None:
    """The page after a schedule form sent with a bad cron and time zone: the focus on
    its error list, whose links move it into each field."""
    page.wait_for_load_state("load")
    assert page.evaluate("document.activeElement.id") == "form-errors"
    summary = page.locator("#form-errors")
    expect(summary).to_have_attribute("role", "alert")
    expect(summary).to_have_attribute("tabindex", "-1")
    for field in ("cron", "timezone"):
        summary.locator(f"a[href='#schedule-{field}']").click()
        assert page.evaluate("document.activeElement.id") == f"schedule-{field}"
        expect(page.locator(f"#schedule-{field}")).to_have_attribute("aria-invalid", "true")


@pytest.mark.parametrize("form", ["new", "edit"])
def test_schedule_form_errors_take_the_focus_and_link_their_fields(page, site, form):
    if form == "new":
        page.goto(f"/schedules/new?job={site['jobs'][0]}")
        scope = "#schedule-form"
    else:
        page.goto(f"/schedules/{site['schedule']}")
        page.click("#schedule-edit summary")
        scope = "#schedule-edit-form"
    page.fill(f"{scope} input[name=cron]", "61 * * * *")
    page.fill(f"{scope} input[name=timezone]", "Mars/Olympus")
    page.click(f"{scope} button[type=submit]")
    schedule_errors_lead_into_their_fields(page)


def test_invalid_fields_are_marked_and_describedby_names_what_exists(browser, stack, tmp_path):
    page = browser.page(stack.base_url)
    page.goto("/login")
    assert page.evaluate(DANGLING) == []
    assert page.get_attribute("#key", "aria-invalid") is None
    page.fill("#key", "svr_nope_nope")
    page.click("form[action='/login'] button[type=submit]")
    page.wait_for_selector("#key-error")
    expect(page.locator("#key")).to_have_attribute("aria-invalid", "true")
    expect(page.locator("#key")).to_have_attribute("aria-describedby", "key-error")

    sign_in(page, stack.key)
    page.goto("/jobs/new")
    assert page.evaluate(DANGLING) == []

    page.goto("/datasets")
    upload_bad_csv(page, tmp_path)
    expect(page.locator("#ds-file")).to_have_attribute("aria-invalid", "true")
    # sent again with no name (past the browser's own check): the marks are cleared,
    # then set on the field of the new error alone
    page.fill("#ds-name", "")
    page.dispatch_event("#upload-form", "submit")  # (its errors cleared at once)
    expect(page.locator("#upload-form .field-error:not([hidden])")).to_have_count(1)
    marked = "s => [...document.querySelectorAll(s)].map(e => e.name)"
    invalid = page.evaluate(marked, "#upload-form .invalid")
    assert (
        len(invalid) == 1 and page.evaluate(marked, "#upload-form [aria-invalid=true]") == invalid
    )
    page.context.close()


def check_dark_charts(page, charts: str, legends: list[list[str]] | None = None) -> list[dict]:
    """The charts of ``window.<charts>`` in the dark theme: lines of the dark palette
    (or its text colour), 3:1 against their card, no canvas legend, a legend of buttons."""
    drawn = page.evaluate(f"() => ({CHARTS})(window.{charts})")
    palette = page.evaluate("window.svrobsChartKit.palette()")
    fg = page.evaluate("getComputedStyle(document.documentElement).getPropertyValue('--fg').trim()")
    assert drawn
    for chart in drawn:
        assert chart["canvasLegend"] is False
        assert set(chart["colours"]) <= set(palette) | {fg}, chart
        assert all(contrast(c, chart["card"]) >= 3 for c in chart["colours"]), chart
    if legends is not None:
        assert [c["legend"] for c in drawn] == legends
    return drawn


def press_legend_button(page, selector: str, hidden: str) -> None:
    """Space on the first legend button of ``selector`` hides its line(s): ``hidden``, a
    function of the chart's datasets' visibility, is then true."""
    button = page.locator(selector).first
    button.focus()
    page.keyboard.press("Space")
    expect(button).to_have_attribute("aria-pressed", "false")
    assert page.evaluate(hidden)


def test_dataset_and_validation_charts_in_the_dark_theme_with_keyboard_legends(
    browser, stack, site
):
    page = browser.page(stack.base_url, dark=True)
    sign_in(page, stack.key)
    page.goto(f"/datasets/{site['dataset']}")
    page.wait_for_selector("#dataset-plot[data-loads='1']")
    assert page.evaluate("document.documentElement.dataset.scheme") == "dark"
    drawn = check_dark_charts(page, "svrobsDataset.charts")
    assert drawn[0]["legend"] == [f"rollout {i}" for i in range(len(drawn[0]["colours"]))]
    press_legend_button(
        page,
        "#rollout-charts figure .legend button",
        "() => !window.svrobsDataset.charts[0].chart.isDatasetVisible(0)",
    )

    page.goto(f"/jobs/{site['dataset_job']}")
    page.wait_for_selector("#validation-card[data-loads='1']")
    check_dark_charts(
        page, "svrobsValidation.predictions", [["measured", "predicted", "simulated"]] * 2
    )
    check_dark_charts(page, "svrobsValidation.autocorrelation", [["r_k", "±99 % band"]] * 2)
    press_legend_button(  # the band: both its lines hidden
        page,
        "#autocorrelation-charts figure .legend li:nth-child(2) button",
        """() => { const c = window.svrobsValidation.autocorrelation[0].chart;
          return !c.isDatasetVisible(1) && !c.isDatasetVisible(2) && c.isDatasetVisible(0); }""",
    )


def test_validation_and_scatter_choices_live_in_the_url(page, site):
    job = site["dataset_job"]
    page.goto(f"/jobs/{job}")
    page.wait_for_selector("#validation-card[data-loads='1']")
    page.wait_for_selector("#charts-card[data-loads]")
    chart_query = re.search(r"metric=[^&]+", page.url).group(0)  # (the field that has data)
    model = page.locator("#val-model option").nth(1).inner_text()
    page.select_option("#val-model", "1")
    page.select_option("#val-rollout", "2")
    rollout = page.locator("#val-rollout option").nth(2).get_attribute("data-key")
    page.click("#scatter-view summary")
    page.wait_for_selector("#views-card[data-scatter=ready]")
    field = page.locator("#scatter-metric option").nth(1).get_attribute("value")
    page.select_option("#scatter-metric", field)
    page.select_option("#scatter-colour", "system")
    for key in ("model", "rollout", "scatter", "scatter_field", "scatter_colour"):
        assert f"{key}=" in page.url, (key, page.url)
    assert chart_query in page.url  # the chart's own choice kept

    page.reload()
    page.wait_for_selector("#validation-card[data-loads='1']")
    page.wait_for_selector("#views-card[data-scatter=ready]")
    expect(page.locator("#val-model")).to_have_value("1")
    expect(page.locator("#val-rollout")).to_have_value("2")
    first = page.evaluate("window.svrobsValidation.predictions[0]")
    assert (first["model"], str(first["rollout"])) == (model, rollout)
    assert page.evaluate("document.getElementById('scatter-view').open")
    expect(page.locator("#scatter-metric")).to_have_value(field)
    expect(page.locator("#scatter-colour")).to_have_value("system")
    labels = page.evaluate(
        "window.svrobsViews.scatter[0].chart.data.datasets.map(d => d.label + '|' + d.data.length)"
    )
    assert labels and all(label.startswith("system") for label in labels), labels

    # back: the colouring, then the field, then the scatter closed, step by step; the
    # job's charts are not asked again
    requests = page.evaluate("window.svrobsCharts.requests")
    page.go_back()
    expect(page.locator("#scatter-colour")).to_have_value("estimator")
    page.go_back()
    expect(page.locator("#scatter-metric")).not_to_have_value(field)
    page.go_back()
    expect(page.locator("#scatter-charts")).to_be_hidden()  # the scatter closed
    page.go_back()
    expect(page.locator("#val-rollout")).to_have_value("0")
    assert page.evaluate("window.svrobsCharts.requests") == requests
