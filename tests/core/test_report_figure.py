"""A figure built in another process from the few columns it is sent
(``FigureJob`` pickled with ``FIGURE_FIELDS``) is the figure built here from all of
them: the same PNG, notes and emptiness for every figure of the report plan and the
audit on the reduced paper preset, and the same plotted data (CSV), notes and
emptiness on records of other shapes and on constructed records that take the
figures' other branches (a field read but not sent raises there)."""

from __future__ import annotations

import logging
import pickle

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from svrobs_core import parse_spec, run_spec
from svrobs_core import report as rpt
from svrobs_core.paper import paper_specs
from svrobs_core.report.build import FIGURE_FIELDS, FIGURE_PLAN
from svrobs_core.report.columns import Columns
from svrobs_core.report.plotting import figure_csv, new_figure
from tests.core.test_measured import ragged
from tests.core.test_measured import run as measured_run
from tests.core.test_report import make_records, tiny_spec


@pytest.fixture(scope="module")
def experiments():
    specs = paper_specs("reduced")
    return {
        n: {"spec": s, "records": [r for b in run_spec(parse_spec(s)) for r in b]}
        for n, s in specs.items()
    }


class _Sent:
    """A render hook's future: the job pickled, as a helper gets it, drawn on arrival."""

    def __init__(self, job, sent):
        self.wire = pickle.dumps(job)
        sent.append((job, self.wire))

    def result(self):
        return rpt.draw_png(pickle.loads(self.wire))


def _same_figure(job):
    """The figure built from the job as a helper gets it (pickled) is the figure built
    from all the fields: the same plotted data (CSV), notes and emptiness. (Reading a
    field not sent raises there.)"""
    sent, here = pickle.loads(pickle.dumps(job)).figure(), job.figure()
    assert figure_csv(sent) == figure_csv(here)
    assert getattr(sent, "svrobs_notes", []) == getattr(here, "svrobs_notes", [])
    assert getattr(sent, "svrobs_empty", False) == getattr(here, "svrobs_empty", False)


def test_every_figure_sent_its_fields_is_the_figure_built_from_all(experiments):
    sent: list = []
    report = rpt.build_report(experiments, render=lambda job: _Sent(job, sent))
    here = rpt.build_report(experiments)
    names = {fg.name for fg in report.figures}
    assert names == {n for n, *_ in FIGURE_PLAN} | {"fig_bounds_audit"}
    assert [fg.name for fg in here.figures] == [fg.name for fg in report.figures]
    for fg, mine in zip(report.figures, here.figures):  # the pixels, as a page shows them
        assert (fg.notes, fg.empty) == (mine.notes, mine.empty)
        assert mine.empty or fg.png() == mine.png()  # an empty figure is its note only
        assert fg.full_caption == mine.full_caption
        _same_figure(mine.source)
    # what travels is the figure's fields, not the experiment's records
    for job, wire in sent:
        here, there = job.args[0], pickle.loads(wire).args[0]
        pairs = zip(here.values(), there.values()) if isinstance(here, dict) else [(here, there)]
        for whole, narrow in pairs:
            assert set(narrow.data) == set(job.fields) & set(whole.data) < set(whole.data)


def test_a_jobs_figures_are_handed_over_slowest_first_and_shown_in_the_plans_order(experiments):
    sent: list = []
    report = rpt.build_report({"job": experiments["E4"]}, render=lambda job: _Sent(job, sent))
    handed = [job.fn.__name__ for job, _ in sent]
    # coverage (12 panels on the paper's job), the entry-wise figures, then the rest
    assert handed == [
        "fig_coverage",
        "fig2",
        "fig3",
        "fig_rmse",
        "fig5",
        "fig4",
        "fig_certified",
        "fig_svr_ols_diff",
    ]
    assert [fg.name for fg in report.figures] == [n for n, *_ in FIGURE_PLAN if n in handed]


def _constructed():
    """Records that take the branches the preset does not: coverage below one
    (fig_coverage drawn), some ΔJ < 0 (fig4's share panel)."""
    spec = tiny_spec()
    recs = make_records(spec, cost=False)
    for r in recs:
        if r["rep"] == 0:
            r["coverage_A"] = 0.5
    spec4 = paper_specs("reduced")["E4"]
    recs4 = make_records(spec4, seed=3)
    for r in recs4[:5]:
        r["delta_J"] = -1.0
    return [
        ("fig_coverage", rpt.fig_coverage, Columns.from_records(recs), spec),
        ("fig4", rpt.fig4, Columns.from_records(recs4), spec4),
        ("fig5", rpt.fig5, Columns.from_records(recs4), spec4),
        ("fig_certified", rpt.fig_certified, Columns.from_records(recs4), spec4),
    ]


@pytest.mark.parametrize("case", _constructed(), ids=lambda c: c[0])
def test_a_figure_on_constructed_records_sent_its_fields_is_the_same(case):
    name, fn, cols, spec = case
    job = rpt.FigureJob(fn, (cols, spec), {"experiment": "X"}, FIGURE_FIELDS[name])
    assert not getattr(job.figure(), "svrobs_empty", False)
    _same_figure(job)


BASE = {"systems": ["paper-stable"], "sigma_w": [1.0], "N": [10, 20], "reps": 2, "seed": 5}
SHAPES = {
    "ols, estimate + bounds": {**BASE, "estimators": ["ols"], "stages": ["estimate", "bounds"]},
    "svr, estimate only": {**BASE, "estimators": ["svr"], "gamma": [0.05], "stages": ["estimate"]},
    "both, up to the cost": {
        **BASE,
        "systems": ["paper-stable", "paper-unstable"],
        "gamma": [0.01, 0.1],
        "stages": ["estimate", "bounds", "gain", "cost"],
    },
    "both, every stage but sls": {
        **BASE,
        "gamma": [0.05],
        "stages": ["estimate", "bounds", "gain", "cost", "cost_bound"],
        "bounds_method": "self-normalized",
    },
}


def _records(shape):
    if shape != "measured":
        spec = SHAPES[shape]
        return spec, [r for b in run_spec(parse_spec(spec)) for r in b]
    spec = {"dataset": 6, "N": [10, 20], "holdout": 2, "reps": 2, "sigma_w": "estimate"}
    spec["stages"] = ["estimate", "bounds", "gain", "cost", "cost_bound"]
    return spec, measured_run(spec, ragged(4, 30))[1]


@pytest.mark.parametrize("shape", [*SHAPES, "measured"])
def test_every_figure_on_records_of_each_shape_sent_its_fields_is_the_same(shape):
    """Each figure of the plan on records it may have no data for (a stage not run, one
    estimator only, measured data without a true system): its no-data branches read
    what it is sent too."""
    spec, records = _records(shape)
    cols = Columns.from_records(records)
    plan = [(n, fn, (cols, spec)) for n, fn, *_ in FIGURE_PLAN]
    plan.append(("fig_bounds_audit", rpt.fig_bounds_audit, ({"paper": cols, "x": cols}, 0.01)))
    for name, fn, args in plan:
        _same_figure(rpt.FigureJob(fn, args, {"experiment": "X"}, FIGURE_FIELDS[name]))


def test_a_field_not_sent_is_a_key_error_not_another_figure():
    spec = tiny_spec()
    cols = Columns.from_records(make_records(spec, cost=False))
    fields = tuple(f for f in FIGURE_FIELDS["fig_rmse"] if f != "rmse_B")
    job = rpt.FigureJob(rpt.fig_rmse, (cols, spec), {}, fields)
    with pytest.raises(KeyError, match="rmse_B"):
        rpt.draw_png(pickle.loads(pickle.dumps(job)))


texts = st.one_of(st.none(), st.sampled_from(["svr", "ols", "shrunk-ols", "", "é"]))


@given(
    st.lists(st.tuples(texts, st.floats(allow_nan=True), st.sampled_from([0.1, 1.0, None]))),
    st.booleans(),
)
def test_columns_pickled_are_the_same_columns(rows, factorised):
    """Text fields travel as codes and come back as the same values; floats (NaN
    included) and every cached code as they were."""
    recs = [{"estimator": e, "rmse_A": x, "gamma": g} for e, x, g in rows]
    cols = Columns.from_records(recs)
    if factorised:
        cols.codes("estimator"), cols.codes("gamma")
    back = pickle.loads(pickle.dumps(cols.only(["estimator", "rmse_A", "gamma", "absent"])))
    assert len(back) == len(cols) and set(back.data) == {"estimator", "rmse_A", "gamma"}
    assert back["estimator"].dtype == object
    assert back["estimator"].tolist() == cols["estimator"].tolist()
    np.testing.assert_array_equal(back["rmse_A"], cols["rmse_A"])
    np.testing.assert_array_equal(back["gamma"], cols["gamma"])
    for f in ("estimator", "gamma"):
        c, v = back.codes(f)
        np.testing.assert_array_equal(c, cols.codes(f)[0])
        assert v == cols.codes(f)[1]


def _small(*_):
    fig, axes = new_figure(1, 1, (3.0, 2.0))
    axes[0, 0].plot([1, 2, 3], [3, 1, 2])
    return fig


class _Failed:
    """A pool whose every submission gives this failed future."""

    def __init__(self, future):
        self.future = future

    def submit(self, *_):
        return self.future


def test_a_reproduction_figure_whose_worker_failed_is_drawn_here(caplog):
    from concurrent.futures import Future

    from svrobs_cli import reproduce

    job = rpt.FigureJob(_small, ())
    failed: Future = Future()
    failed.set_exception(KeyError("rmse_A (not sent with the figure)"))
    with caplog.at_level(logging.WARNING, logger="svrobs_lab.figure_pool"):
        drawn = reproduce._renderer(_Failed(failed))(job).result()
    assert drawn == rpt.draw_files(job) and drawn.png and drawn.svg and drawn.pdf and drawn.csv
    assert "KeyError" in caplog.text and "drawn in process" in caplog.text
