"""Charts told apart without colour and read as text, in a real chromium against a real
server (the stack and browser of test_browser): the lines of a job chart, the scatter's
categories, a dataset's rollouts, a validation chart's series and the compare page's
groups differ in dash pattern or point style, and each legend swatch draws them; under every chart of a figure a "Data table" holds the
plotted numbers (the job chart's equal to the API's summary means), follows the chart
when its data change, is cut at 500 rows with a note that points to the page's
exports, and passes axe, open, on the job, dataset job and dataset pages (and at phone
width, with no sideways scroll)."""

from __future__ import annotations

import numpy as np
import pytest
from playwright.sync_api import expect

from tests.datasets import files
from tests.integration.stack import submit

from . import test_browser as base
from . import test_browser_forms_a11y as forms
from .test_browser import sign_in
from .test_browser_a11y import check

browser = base.browser
only_the_server = base.only_the_server
page = forms.page  # a signed-in page
pytestmark = base.pytestmark

JOB = {
    "systems": ["paper-stable"],
    "sigma_w": [1.0],
    "N": [10, 20],
    "gamma": [0.01, 0.05],
    "estimators": ["ols", "svr"],
    "reps": 2,
    "seed": 7,
}
STEPS = 600  # of each rollout of the dataset: more rows than a data table shows
MEASURED = {
    "N": [6, 10],
    "holdout": 4,
    "reps": 2,
    "gamma": [0.05],
    "sigma_w": "estimate",
    "seed": 3,
}

# The lines (or points) of the first chart drawn in ``box``: each one's label, dash,
# point style and numbers, and its legend swatch's dash and marker.
LINES = """(box) => {
  const chart = Chart.getChart(document.querySelector(box + " figure canvas"));
  const fig = chart.canvas.closest("figure");
  return chart.data.datasets.filter(d => d.svrobs.role === "mean" || d.svrobs.legend).map(d => {
    const sw = fig.querySelector(`.legend button[data-series="${d.svrobs.series}"] .swatch`);
    return {label: d.label, svrobs: {estimator: d.svrobs.estimator, gamma: d.svrobs.gamma},
            dash: (d.borderDash || []).join(" "), point: d.pointStyle || "circle",
            swatch: [sw.dataset.dash, sw.dataset.point], points: d.data.map(p => [p.x, p.y])};
  });
}"""

# The first data table of ``box`` (its figure's chart's columns beside it).
TABLE = """(box) => {
  const fig = document.querySelector(box + " figure");
  const chart = Chart.getChart(fig.querySelector("canvas")), t = fig.querySelector("details.chart-data table");
  const note = fig.querySelector(".chart-data-note");
  return {open: fig.querySelector("details.chart-data").open, caption: t.caption.textContent,
    name: chart.canvas.getAttribute("aria-label"),
    columns: [chart.options.scales.x.title.text].concat(chart.data.datasets.map(d => d.label)),
    head: [...t.tHead.rows[0].cells].map(c => c.textContent),
    rows: [...t.tBodies[0].rows].map(r => [...r.cells].map(c => c.textContent)),
    note: note.hidden ? "" : note.textContent,
    links: [...note.querySelectorAll("a")].map(a => a.getAttribute("href"))};
}"""

OPEN_TABLES = (
    "() => document.querySelectorAll('details.chart-data').forEach(d => { d.open = true; })"
)


@pytest.fixture(scope="module")
def site(stack) -> dict:
    """A finished job of three lines (OLS and SVR at two γ), a dataset of long rollouts
    and a finished job on a dataset of short ones (its validation card)."""
    A, B = np.array([[0.8, 0.25], [-0.2, 0.75]]), np.array([[0.4], [1.0]])
    with stack.client() as api:
        job = submit(api, JOB, name="charts a11y")["id"]
        ds = [
            api.post(
                "/datasets",
                files={
                    "file": (f"{name}.npz", files.npz_bytes(*files.simulate(A, B, 9, lengths=T)))
                },
                data={"name": name, "sample_time": "0.1"},
            )
            for name, T in (("long", (STEPS,) * 3), ("short", (20,) * 14))
        ]
        assert [r.status_code for r in ds] == [201, 201], [r.text for r in ds]
        measured = submit(api, {**MEASURED, "dataset": ds[1].json()["id"]}, name="measured")["id"]
        assert stack.wait_job(api, job)["status"] == "succeeded"
        assert stack.wait_job(api, measured, timeout=200)["status"] == "succeeded"
        summary = api.get(f"/jobs/{job}/summary").json()
    return {"job": job, "dataset": ds[0].json()["id"], "measured": measured, "summary": summary}


def assert_told_apart(lines: list[dict]) -> None:
    """Two or more series, no two of the same dash and marker, each swatch drawing its
    series' (the marker alone where no line is drawn, the line alone without points)."""
    assert len(lines) > 1
    assert len({(ln["dash"], ln["point"]) for ln in lines}) == len(lines), lines
    for ln in lines:
        assert ln["swatch"][0] in (ln["dash"], None), ln
        assert ln["swatch"][1] in (ln["point"], None), ln
        assert ln["swatch"] != [None, None], ln


def cells(table: dict, column: str) -> dict[float, float | None]:
    """A data table's column by its head, as {x: y} (None where it shows "–")."""
    j = table["head"].index(column)
    return {float(r[0]): None if r[j] == "–" else float(r[j]) for r in table["rows"]}


def test_series_differ_beyond_colour_and_so_do_their_swatches(page, site):
    page.goto(f"/jobs/{site['job']}")
    page.wait_for_selector("#charts-card[data-state=ready] #charts canvas")
    lines = page.evaluate(LINES, "#charts")
    assert [ln["label"] for ln in lines] == ["ols", "svr γ=0.01", "svr γ=0.05"]
    assert_told_apart(lines)
    assert all(ln["swatch"] == [ln["dash"], ln["point"]] for ln in lines)
    page.click("#scatter-view summary")
    page.wait_for_selector("#views-card[data-scatter=ready]")
    assert_told_apart(page.evaluate(LINES, "#scatter-charts"))

    page.goto(f"/datasets/{site['dataset']}")
    page.wait_for_selector("#dataset-plot[data-loads='1']")
    assert_told_apart(page.evaluate(LINES, "#rollout-charts"))

    page.goto(f"/jobs/{site['measured']}")
    page.wait_for_selector("#validation-card[data-loads='1']")
    assert_told_apart(page.evaluate(LINES, "#prediction-charts"))


def test_job_chart_table_is_the_summary_follows_the_chart_and_passes_axe(page, site):
    page.goto(f"/jobs/{site['job']}")
    page.wait_for_selector("#charts-card[data-state=ready] #charts canvas")
    lines = page.evaluate(LINES, "#charts")
    page.locator("#charts figure details.chart-data summary").first.click()
    expect(page.locator("#charts figure details.chart-data table").first).to_be_visible()
    table = page.evaluate(TABLE, "#charts")
    assert table["name"] in table["caption"]
    assert table["head"] == table["columns"] and len(table["head"]) == 1 + 3 * 3  # bands
    assert table["note"] == ""
    groups = site["summary"]["groups"]
    for ln in lines:
        shown = cells(table, ln["label"])
        assert shown == pytest.approx({x: y for x, y in ln["points"]}, rel=1e-5)
        means = {
            g["N"]: g["stats"]["rmse_A"]["mean"]
            for g in groups
            if (g["estimator"], g["gamma"]) == (ln["svrobs"]["estimator"], ln["svrobs"]["gamma"])
        }
        assert shown == pytest.approx(means, rel=1e-5)

    # the bands off: the chart drawn again, its table still open, without their columns
    page.uncheck("#chart-bands")
    page.wait_for_function(
        "() => Chart.getChart(document.querySelector('#charts canvas')).data.datasets.length === 3"
    )
    table = page.evaluate(TABLE, "#charts")
    labels = [ln["label"] for ln in lines]
    assert table["open"] and table["head"] == table["columns"] and table["head"][1:] == labels

    page.click("#scatter-view summary")
    page.wait_for_selector("#views-card[data-scatter=ready]")
    page.evaluate(OPEN_TABLES)
    scatter = page.evaluate(TABLE, "#scatter-charts")
    plotted = sum(len(ln["points"]) for ln in page.evaluate(LINES, "#scatter-charts"))
    assert plotted and len(scatter["rows"]) == plotted  # a row per point (one series each)
    problems: list = []
    check(page, "job, tables open", problems)
    assert problems == []


@pytest.mark.parametrize("width", [1280, 375])
def test_dataset_and_validation_tables_pass_axe_and_a_long_one_is_cut(browser, stack, site, width):
    page = browser.page(stack.base_url, width=width)
    sign_in(page, stack.key)
    page.goto(f"/jobs/{site['measured']}")
    page.wait_for_selector("#validation-card[data-loads='1']")
    page.evaluate(OPEN_TABLES)
    for box in ("#prediction-charts", "#autocorrelation-charts"):
        table = page.evaluate(TABLE, box)
        assert table["head"] == table["columns"] and table["rows"] and not table["note"], table
    problems: list = []
    check(page, "dataset job, tables open", problems)

    page.goto(f"/datasets/{site['dataset']}")
    page.wait_for_selector("#dataset-plot[data-loads='1']")
    page.evaluate(OPEN_TABLES)
    table = page.evaluate(TABLE, "#rollout-charts")
    assert table["head"] == table["columns"] == ["time (s)", "rollout 0", "rollout 1", "rollout 2"]
    assert len(table["rows"]) == 500
    assert table["rows"][1][0] == "0.1"
    rows = STEPS + 1  # (the states of a rollout of STEPS steps)
    assert table["note"].startswith(f"The first 500 of {rows} rows; {rows - 500} left out")
    assert table["links"] == [
        f"/api/v1/datasets/{site['dataset']}/file",
        f"/api/v1/datasets/{site['dataset']}",
    ]
    check(page, "dataset, tables open", problems)
    assert problems == []
    page.context.close()


def test_compare_groups_differ_in_marker_and_jobs_in_dash(page, site):
    page.goto(f"/compare?jobs={site['job']}&metric=rmse_A")
    page.wait_for_selector("#compare-card[data-ready=yes]")
    lines = page.evaluate(
        """() => window.svrobsCompare.chart.data.datasets.filter(d => d.svrobs.role === "mean")
          .map(d => ({dash: (d.borderDash || []).join(" "), point: d.pointStyle || "circle",
            swatch: document.querySelector(`#compare-legend button[data-series="${d.svrobs.series}"] .swatch`)
              .dataset.point}))"""
    )
    assert len(lines) > 1
    assert {ln["dash"] for ln in lines} == {""}  # one job: one dash
    assert len({ln["point"] for ln in lines}) == len(lines)
    assert [ln["swatch"] for ln in lines] == [ln["point"] for ln in lines]
