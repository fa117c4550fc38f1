"""The datasets pages and a dataset job's validation card in a real chromium against a
real server (the stack and browser of test_browser): a file uploaded through the form
with its progress bar (XMLHttpRequest progress events up to the whole file), a bad
file's error beside its field with nothing stored, the dataset page's facts,
statistics, excitation check and rollout charts (points equal to the file's numbers),
"new job on this dataset" prefilling the submit form with the dataset chosen (a
dataset spec kept on submit), and the job page's measured
against predicted charts and residual autocorrelation with its band, equal to
``GET /api/v1/jobs/{id}/validation`` (checked after every test, as in test_browser:
no request to another host, no console error)."""

from __future__ import annotations

import json
import re

import numpy as np
from playwright.sync_api import expect

from svrobs_core.measured import MeasuredData, excitation
from tests.datasets import files

from . import test_browser as base
from .test_browser import sign_in

browser = base.browser
only_the_server = base.only_the_server
pytestmark = base.pytestmark  # integration, chromium, the embedded stack

A_TRUE = np.array([[0.8, 0.25], [-0.2, 0.75]])
B_TRUE = np.array([[0.4], [1.0]])

DATASET_CHARTS = """() => window.svrobsDataset.charts.map(c => ({channel: c.channel,
  kind: c.kind, lines: c.lines}))"""
VALIDATION = """() => ({
  predictions: window.svrobsValidation.predictions.map(c => ({channel: c.channel,
    rollout: c.rollout, model: c.model, points: c.points})),
  autocorrelation: window.svrobsValidation.autocorrelation.map(c => ({channel: c.channel,
    model: c.model, r: c.r, band: c.band,
    drawn: c.chart.data.datasets.map(d => ({role: d.svrobs.role, y: d.data.map(p => p.y)}))})),
})"""


def upload_bad_csv(page, tmp_path) -> None:
    """Send a CSV with a non-number from the datasets page: its error beside the file
    field."""
    bad = tmp_path / "bad.csv"
    bad.write_text("rollout,k,x1,u1\n0,0,1.0,abc\n0,1,2.0,\n")
    page.set_input_files("#ds-file", str(bad))
    page.fill("#ds-name", "broken")
    page.click("#upload-button")
    expect(page.locator("#err-file")).to_contain_text("'abc' is not a number")


def test_upload_with_progress_then_the_dataset_page_and_a_job_on_it(browser, stack, tmp_path):
    X, U = files.simulate(A_TRUE, B_TRUE, 41, lengths=(30,) * 20)
    path = tmp_path / "bench-runs.csv"
    path.write_bytes(files.csv_bytes(X, U))
    page = browser.page(stack.base_url)
    sign_in(page, stack.key)
    page.click("nav a[href='/datasets']")
    page.wait_for_url(re.compile(r"/datasets$"))

    # a bad file: its error beside the file field, nothing stored
    upload_bad_csv(page, tmp_path)
    assert "invalid" in page.get_attribute("#ds-file", "class")
    with stack.client() as api:
        assert api.get("/datasets").json()["total"] == 0

    # the good file: the bar follows the bytes sent, then the dataset's page opens
    page.set_input_files("#ds-file", str(path))
    page.fill("#ds-name", "bench runs")
    page.fill("#ds-sample-time", "0.02")
    page.click("#upload-button")
    page.wait_for_url(re.compile(r"/datasets/\d+$"))
    dataset_id = int(page.url.rsplit("/", 1)[1])
    with stack.client() as api:
        stored = api.get(f"/datasets/{dataset_id}").json()
    assert (stored["rollouts"], stored["n"], stored["m"]) == (20, 2, 1)
    assert stored["sample_time"] == 0.02 and stored["name"] == "bench runs"

    # the dataset page: facts, statistics, excitation, the first rollouts per channel
    expect(page.locator("#fact-rollouts")).to_have_text("20")
    rows = page.locator("#stats-table tbody tr")
    expect(rows).to_have_count(3)
    x1 = page.locator("#stats-table tr[data-channel='x1'] td").all_inner_texts()
    assert float(x1[2]) == float(f"{stored['stats']['states']['x1']['mean']:.4g}")
    ex = excitation(MeasuredData(X=X, U=U))
    shown = float(page.inner_text("#ex-lambda-min"))
    assert abs(shown - ex.lambda_min) <= 1e-3 * ex.lambda_min
    expect(page.locator("#ex-ok")).to_be_visible()
    page.wait_for_selector("#dataset-plot[data-loads='1']")
    charts = page.evaluate(DATASET_CHARTS)
    assert [(c["channel"], c["kind"]) for c in charts] == [
        ("x1", "state"),
        ("x2", "state"),
        ("u1", "input"),
    ]
    for c in charts:
        assert [ln["rollout"] for ln in c["lines"]] == [0, 1, 2, 3, 4]
        source, j = (X, ["x1", "x2"].index(c["channel"])) if c["kind"] == "state" else (U, 0)
        for ln in c["lines"]:
            want = [[k * 0.02, v] for k, v in enumerate(source[ln["rollout"]][:, j])]
            np.testing.assert_allclose(np.array(ln["points"]), np.array(want), rtol=0, atol=1e-15)

    # "new job on this dataset": the submit form prefilled with a spec on it
    page.click("#new-job-link")
    page.wait_for_url(re.compile(rf"/jobs/new\?dataset={dataset_id}$"))
    spec = json.loads(page.input_value("#spec"))
    assert spec["dataset"] == dataset_id and spec["holdout"] == 4 and spec["N"] == [4, 8, 16]
    # the dataset is chosen in the form's list of the team's datasets; the fields are a
    # dataset job's (no systems, σ_w one level), and choosing none shows a simulation's
    expect(page.locator("#f-dataset")).to_have_value(str(dataset_id))
    expect(page.locator("#f-dataset option")).to_have_count(2)  # none, and this one
    expect(page.locator("#field-systems")).to_be_hidden()
    expect(page.locator("#field-T0")).to_be_hidden()
    expect(page.locator("#f-holdout")).to_have_value("4")
    expect(page.locator("#f-dataset_sigma_w")).to_have_value("estimate")
    page.select_option("#f-dataset", "")
    expect(page.locator("#field-systems")).to_be_visible()
    expect(page.locator("#field-holdout")).to_be_hidden()
    simulated = json.loads(page.input_value("#spec"))
    assert "dataset" not in simulated and "holdout" not in simulated and "T0" in simulated
    page.select_option("#f-dataset", str(dataset_id))
    expect(page.locator("#field-systems")).to_be_hidden()
    again = json.loads(page.input_value("#spec"))
    assert again == spec  # the JSON the fields give is the one the server wrote
    page.fill("#name", "measured from the page")
    page.click("#submit-job")
    page.wait_for_url(re.compile(r"/jobs/\d+$"))
    job_id = int(page.url.rsplit("/", 1)[1])
    with stack.client() as api:
        done = stack.wait_job(api, job_id, timeout=200)
        assert done["status"] == "succeeded", done
        assert done["spec"]["dataset"] == dataset_id and done["spec"]["holdout"] == 4
        assert done["spec"]["N"] == [4, 8, 16] and "systems" not in done["spec"]
        validation = api.get(f"/jobs/{job_id}/validation").json()

    # the job page: measured vs predicted and the residual autocorrelation, as served
    page.reload()
    page.wait_for_selector("#validation-card[data-loads='1']")
    # its charts: the default field (rmse_A) has no values on measured data, so the first
    # field that has is shown, and said so; σ_w estimated reads "estimate"; no N0 axis
    # (a dataset job has no T0)
    page.wait_for_function("window.svrobsCharts && window.svrobsCharts.charts.length > 0")
    metric = page.input_value("#chart-metric")
    assert metric != "rmse_A" and f"metric={metric}" in page.url
    assert "rmse_A has no values in this job" in page.inner_text("#chart-status")
    titles = page.locator("#charts .chart-panel h3").all_inner_texts()
    assert titles and all("σ_w = estimate" in t for t in titles), titles
    assert page.evaluate("Object.keys(window.svrobsCharts.charts[0].chart.options.scales)") == [
        "x",
        "y",
    ]
    grid = page.request.get(f"{stack.base_url}/results?job={job_id}&limit=5").text()
    assert '<option value="-1.0">estimate</option>' in grid
    assert '<td class="num" data-field="sigma_w" data-value="-1.0">estimate</td>' in grid
    drawn = page.evaluate(VALIDATION)
    ols = validation["models"][0]["validation"]
    measured = validation["plots"]["measured"][0]
    assert [p["channel"] for p in drawn["predictions"]] == ["x1", "x2"]
    for j, chart in enumerate(drawn["predictions"]):
        assert chart["model"] == "ols" and chart["rollout"] == 16
        assert chart["points"]["measured"] == [[k * 0.02, row[j]] for k, row in enumerate(measured)]
        assert chart["points"]["predicted"] == [
            [(k + 1) * 0.02, row[j]] for k, row in enumerate(ols["predicted"][0])
        ]
        assert chart["points"]["simulated"] == [
            [k * 0.02, row[j]] for k, row in enumerate(ols["simulated"][0])
        ]
    for j, chart in enumerate(drawn["autocorrelation"]):
        assert chart["r"] == ols["autocorrelation"][j] and chart["band"] == ols["band"]
        roles = {d["role"]: d["y"] for d in chart["drawn"]}
        assert roles["r"] == ols["autocorrelation"][j]
        bands = [d["y"] for d in chart["drawn"] if d["role"] == "band"]
        assert sorted(b[0] for b in bands) == [-ols["band"], ols["band"]]
    table = page.locator("#validation-table tbody tr")
    expect(table).to_have_count(len(validation["models"]))
    first = page.locator("#validation-table tbody tr").first.locator("td").all_inner_texts()
    assert first[0] == "ols" and float(first[1]) == round(ols["one_step_fit"][0], 1)

    # the dark theme: the measured line in the theme's text colour, axes in its muted one
    page.click("#theme-toggle")
    assert page.evaluate("document.documentElement.dataset.theme") == "dark"
    css = "n => getComputedStyle(document.documentElement).getPropertyValue(n).trim()"
    fg, muted = page.evaluate(css, "--fg"), page.evaluate(css, "--muted")
    drawn = page.evaluate(
        """() => window.svrobsValidation.predictions.concat(window.svrobsValidation.autocorrelation)
          .map(c => ({measured: (c.chart.data.datasets.find(d => d.svrobs.role === "measured")
                                 || {}).borderColor,
                      ticks: c.chart.options.scales.x.ticks.color,
                      title: c.chart.options.scales.y.title.color}))"""
    )
    assert fg == "#e3e8ee" and all(d["ticks"] == d["title"] == muted for d in drawn), drawn
    assert [d["measured"] for d in drawn if d["measured"]] == [fg] * 2
    page.click("#theme-toggle")  # back to light

    # another model and another held-out rollout redraw the charts
    page.select_option("#val-model", "1")
    page.select_option("#val-rollout", "2")
    drawn = page.evaluate(VALIDATION)
    svr = validation["models"][1]["validation"]
    assert (
        drawn["predictions"][0]["model"].startswith("svr")
        and drawn["predictions"][0]["rollout"] == 18
    )
    assert drawn["predictions"][0]["points"]["predicted"] == [
        [(k + 1) * 0.02, row[0]] for k, row in enumerate(svr["predicted"][2])
    ]


def test_upload_progress_follows_the_whole_body(browser, stack, tmp_path):
    """A file of a few MB with a bad number in its last row: XMLHttpRequest reports the
    bytes sent to the bar up to the whole body, then the row is named beside the file
    field and nothing is stored."""
    X, U = files.simulate(A_TRUE, B_TRUE, 43, lengths=(400,) * 60)
    text = files.csv_bytes(X, U).decode().rstrip("\n").splitlines()
    text[-2] = text[-2].rsplit(",", 1)[0] + ",1e999x"
    path = tmp_path / "big.csv"
    path.write_text("\n".join(text) + "\n")
    page = browser.page(stack.base_url)
    sign_in(page, stack.key)
    page.goto("/datasets")
    with stack.client() as api:
        before = api.get("/datasets").json()["total"]
    page.set_input_files("#ds-file", str(path))
    page.fill("#ds-name", "big")
    page.click("#upload-button")
    expect(page.locator("#err-file")).to_contain_text(f"row {len(text) - 1}")
    upload = page.evaluate("() => window.svrobsDataset.upload")
    assert upload["status"] == 422
    sent = upload["progress"]
    assert sent and sent[-1][0] == sent[-1][1] >= path.stat().st_size  # the whole body
    assert [a for a, _ in sent] == sorted(a for a, _ in sent)
    assert page.is_hidden("#upload-progress") and page.is_enabled("#upload-button")
    with stack.client() as api:
        assert api.get("/datasets").json()["total"] == before
