"""The job page's Table 2, findings and figure presets from summaries, against the
report computed from the records themselves (svrobs_core.report on every record)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from service.web import figure_charts, job_tables
from svrobs_core import parse_spec, run_spec, summarize
from svrobs_core import report as rpt
from svrobs_core.paper import paper_specs
from svrobs_core.report.columns import as_columns, select, spec_meta
from svrobs_core.report.findings import findings
from svrobs_core.report.series import context, series_lines
from tests.core.test_report import make_records, tiny_spec


def _uneven(recs):
    """Some repetitions without an RMSE: counts differ between groups and N, so a
    count-weighted mean and Table 2's mean over N of per-N means differ."""
    for i, r in enumerate(recs):
        if r["rep"] == 0 and r["N"] == 10 and i % 3 == 0:
            r["rmse_A"] = None
        if r["rep"] in (1, 2) and r["N"] == 30 and r["estimator"] == "svr":
            r["rmse_B"] = None
    return recs


@pytest.fixture(scope="module")
def recs():
    return _uneven(make_records(tiny_spec(), seed=5, cost=False))


def test_table2_from_summaries_is_the_reports_table2(recs):
    groups = summarize(recs)
    mine = job_tables.summary_tables(groups)[0]
    theirs = rpt.table2(recs)
    assert len(mine) == len(theirs) == 2 * 2 * 2
    for m, t in zip(mine, theirs):
        for k in ("system", "sigma_w", "matrix", "gamma", "n_N", "reps_per_N"):
            assert m[k] == t[k], k
        for k in ("ols", "svr", "svr_minus_ols"):
            assert m[k] == pytest.approx(t[k], rel=1e-12, abs=0)
    assert min(r["reps_per_N"] for r in mine) < 4  # the uneven counts were seen
    # Table 2 is the mean over N of per-N means, not a count-weighted mean of all cells
    row = mine[0]
    cells = [
        r["rmse_A"]
        for r in recs
        if r["system"] == row["system"] and r["sigma_w"] == row["sigma_w"]
        if r["estimator"] == "ols" and r["rmse_A"] is not None
    ]
    assert not math.isclose(float(np.mean(cells)), row["ols"], rel_tol=1e-9)


def test_rmse_findings_from_summaries_are_the_reports(recs):
    mine = job_tables.summary_tables(summarize(recs))[1]
    assert mine and mine[0].startswith(("[holds]", "[partly]", "[does not hold]"))
    assert all(f in findings(recs, tiny_spec()) for f in mine)


E4 = paper_specs("reduced")["E4"]


@pytest.mark.parametrize(
    "spec, recs",
    [
        pytest.param(E4, None, id="E4 reduced, run"),
        # two σ_w: Fig. 4 and 5 rows pool them (neither selected nor a line)
        pytest.param({**E4, "sigma_w": [0.1, 1.0]}, 3, id="E4 two sigma_w, constructed"),
    ],
)
def test_every_preset_is_the_figures_curve_with_std_bands(spec, recs):
    if recs is None:
        recs = [r for b in run_spec(parse_spec(spec)) for r in b]
    else:
        recs = make_records(spec, seed=recs)
    groups = summarize(recs)
    cols, meta = as_columns(recs), spec_meta(spec)
    ctx = context(cols, meta)
    drawn = 0
    for pid, s in figure_charts.PRESETS.items():
        data = figure_charts.preset_chart(groups, spec, s)
        assert data["preset"]["band"] == (figure_charts.BAND_LABEL if s.band else None)
        for p in data["panels"]:
            pm = select(cols, **p["coords"])
            for ser in p["series"]:
                mine = [ln for ln in series_lines(cols, meta, s, pm, ctx) if ln.key == ser["line"]]
                assert len(mine) == 1, pid
                got = [(n, y) for n, y in zip(p["x"], ser["mean"]) if y is not None]
                np.testing.assert_array_equal([n for n, _ in got], mine[0].N)
                np.testing.assert_allclose([y for _, y in got], mine[0].y, rtol=1e-12)
                if s.band:  # mean ± std of the same repetitions, from the records
                    for n, sd in zip(p["x"], ser["std"]):
                        m = pm & select(cols, estimator="svr", gamma=ser["gamma"])
                        m &= select(cols, system=ctx["system_S"])
                        v = cols[s.field][m & (cols["N"] == n)]
                        assert sd == pytest.approx(float(np.std(v[np.isfinite(v)])), rel=1e-9)
                drawn += 1
        values = [
            y for p in data["panels"] for ser in p["series"] for y in ser["mean"] if y is not None
        ]
        if s.scale == "linear" or not values:
            assert data["scale"] == "linear"
        elif min(values) > 0:
            assert data["scale"] == "log"
    assert drawn > 10


def test_symlog_is_sized_to_the_data_as_the_figures():
    import matplotlib.pyplot as plt

    from svrobs_core.report.plotting import symlog_axis

    s = figure_charts.PRESETS["fig4/delta_J"]
    values = [-0.5, 0.02, 3.0, 0.3, 0.004, -0.07]
    fig, ax = plt.subplots()
    symlog_axis(ax, np.array(values))  # the figures' own choice of the linear region
    want = ax.yaxis.get_transform().linthresh
    plt.close(fig)
    assert figure_charts.y_scale(s, values) == {"scale": "symlog", "linthresh": want}
    assert figure_charts.y_scale(s, [0.5, 2.0]) == {"scale": "log"}
    assert figure_charts.y_scale(s, [0.0, 2.0]) == {"scale": "linear"}
    certified = figure_charts.PRESETS["fig_certified/certified"]
    assert figure_charts.y_scale(certified, [0.5]) == {"scale": "linear"}
