"""The report's figures checked on the figure objects, not on pixels.

Figures are built from real records (the reduced E2 and E4 grids of the paper
preset, run in process) and from constructed records; each check reads the
drawn artists back (Line2D data, tick labels, text sizes, legend handles).
"""

import csv
import io
import json
import math
from collections import defaultdict

import matplotlib
import numpy as np
import pytest
from matplotlib.collections import PolyCollection
from matplotlib.colors import to_rgba
from matplotlib.lines import Line2D
from matplotlib.patches import Patch
from matplotlib.text import Text

from svrobs_core import parse_spec, run_spec
from svrobs_core import report as rpt
from svrobs_core.paper import paper_specs
from svrobs_core.records import SUMMARY_FIELDS
from svrobs_core.report.style import MIN_FONT_PT, NEUTRAL, ONE_COLUMN_CM, TWO_COLUMN_CM
from tests.core.test_report import make_records, tiny_spec

CM = 1 / 2.54


@pytest.fixture(scope="module")
def real():
    """Records of the reduced E2 (estimation) and E4 (cost) grids, and of A1, A2
    (E2's grid with the self-normalized and the bootstrap boxes)."""
    specs = paper_specs("reduced")
    out = {}
    for name in ("E2", "E4", "A1", "A2"):
        out[name] = (specs[name], [r for b in run_spec(parse_spec(specs[name])) for r in b])
    return out


def all_figures(real):
    """(name, figure) of every figure of the report plan, drawn from its experiment."""
    figs = []
    for name, fn, prefer, *_ in rpt.FIGURE_PLAN:
        exp = "E2" if prefer[0] in ("E1", "E2") else "E4"
        spec, recs = real[exp]
        figs.append((name, fn(recs, spec, experiment=exp)))
    # constructed records with coverage below 1 somewhere: fig_coverage is drawn
    spec = tiny_spec()
    recs = make_records(spec, cost=False)
    for r in recs:
        if r["rep"] == 0:
            r["coverage_A"] = 0.5
    figs.append(("fig_coverage (constructed)", rpt.fig_coverage(recs, spec)))
    # constructed cost records with some ΔJ < 0: fig4 draws its share panel
    spec4 = paper_specs("reduced")["E4"]
    recs4 = make_records(spec4, seed=3)
    for r in recs4[:5]:
        r["delta_J"] = -1.0
    figs.append(("fig4 (constructed)", rpt.fig4(recs4, spec4)))
    figs.append(("fig_bounds_audit", audit_figure(audit_sources(real))))
    # every box covers in every record: no share row, radii only
    inside = {
        m: [{**r, "coverage_A": 1.0, "coverage_B": 1.0} for r in recs]
        for m, recs in audit_sources(real).items()
    }
    figs.append(("fig_bounds_audit (all inside)", audit_figure(inside)))
    return [(n, f) for n, f in figs if not f.svrobs_empty]


AUDIT_EXPERIMENTS = {"paper": "E2", "self-normalized": "A1", "bootstrap": "A2"}


def audit_sources(real):
    return {m: real[e][1] for m, e in AUDIT_EXPERIMENTS.items()}


def audit_figure(sources, delta=0.01):
    return rpt.fig_bounds_audit(sources, delta, experiment="E2 + A1 + A2", seed=0)


@pytest.fixture(scope="module")
def figures(real):
    figs = all_figures(real)
    for _, fig in figs:
        fig.canvas.draw()  # tick labels and layout exist only after a draw
    return figs


def data_lines(ax):
    return [ln for ln in ax.lines if hasattr(ln, "svrobs_key")]


def panels(fig):
    return [ax for ax in fig.axes if ax.get_visible() and data_lines(ax)]


def labelled_ticks(axis, lo, hi):
    n = 0
    for loc, lab in zip(axis.get_majorticklocs(), axis.get_ticklabels()):
        if lab.get_visible() and lab.get_text().strip() and lo <= loc <= hi:
            n += 1
    return n


def test_every_figure_is_drawn_at_a_column_width(figures):
    names = {n for n, _ in figures}
    assert {"fig_rmse", "fig2", "fig3", "fig4", "fig5", "fig_certified"} <= names
    for name, fig in figures:
        w = fig.get_figwidth() / CM
        assert math.isclose(w, ONE_COLUMN_CM, abs_tol=0.01) or math.isclose(
            w, TWO_COLUMN_CM, abs_tol=0.01
        ), name
    assert any(math.isclose(f.get_figwidth() / CM, ONE_COLUMN_CM) for _, f in figures)


def test_every_axis_has_three_labelled_ticks(figures):
    for name, fig in figures:
        for ax in panels(fig):
            for axis, lim, siblings in (
                (ax.yaxis, ax.get_ylim(), ax.get_shared_y_axes().get_siblings(ax)),
                (ax.xaxis, ax.get_xlim(), ax.get_shared_x_axes().get_siblings(ax)),
            ):
                lo, hi = sorted(lim)
                n = labelled_ticks(axis, lo, hi)
                if n == 0:  # labels hidden on an inner panel: a sibling carries them
                    other = [
                        labelled_ticks(s.yaxis if axis is ax.yaxis else s.xaxis, lo, hi)
                        for s in siblings
                        if s is not ax and s.get_visible()
                    ]
                    assert other and max(other) >= 3, (name, ax.get_title(), axis.axis_name)
                else:
                    assert n >= 3, (name, ax.get_title(), axis.axis_name, n)


def test_every_text_is_at_least_8_pt_at_print_size(figures):
    for name, fig in figures:
        texts = [t for t in fig.findobj(Text) if t.get_visible() and t.get_text().strip()]
        assert texts
        small = [(t.get_text(), t.get_fontsize()) for t in texts if t.get_fontsize() < MIN_FONT_PT]
        assert not small, (name, small[:3])


def drawn_texts(fig):
    """The visible texts of a drawn figure, tick labels only where their tick is in view."""
    ticks, texts = set(), []
    for ax in fig.axes:
        for axis in (ax.xaxis, ax.yaxis):
            lo, hi = sorted(axis.get_view_interval())
            for tick in axis.get_major_ticks() + axis.get_minor_ticks():
                ticks.update((id(tick.label1), id(tick.label2)))
                if lo <= tick.get_loc() <= hi:
                    texts += [tick.label1, tick.label2]
    texts += [t for t in fig.findobj(Text) if id(t) not in ticks]
    return [t for t in texts if t.get_visible() and t.get_text().strip()]


def test_every_panel_title_sits_above_its_axes_clear_of_the_other_texts(figures):
    """Panel titles are placed once at the top of their axes (``panel_title``), not
    moved at each draw: drawn, each is above its axes' box and overlaps no other
    visible text of the figure (tick labels, offset texts, labels, legends)."""
    titled = 0
    for name, fig in figures:
        renderer = fig.canvas.get_renderer()
        texts = drawn_texts(fig)
        for ax in fig.axes:
            title = ax.title
            if not (ax.get_visible() and title.get_text()):
                continue
            titled += 1
            box = title.get_window_extent(renderer)
            assert box.y0 >= ax.bbox.y1 - 0.5, (name, title.get_text())
            for t in texts:
                if t is title:
                    continue
                other = t.get_window_extent(renderer)
                assert not box.overlaps(other), (name, title.get_text(), t.get_text())
    assert titled >= 10


def same(a, b):
    a, b = np.asarray(a, float), np.asarray(b, float)
    if a.shape != b.shape or not np.array_equal(np.isnan(a), np.isnan(b)):
        return False
    ok = np.isfinite(a)
    return bool(np.all(np.abs(a[ok] - b[ok]) <= 1e-12 * max(1.0, np.abs(a[ok]).max(initial=0))))


def test_no_two_series_of_a_panel_are_identical_unless_said(figures):
    for name, fig in figures:
        said = " ".join(fig.svrobs_notes).lower()
        for ax in panels(fig):
            lines = data_lines(ax)
            for i, a in enumerate(lines):
                for b in lines[i + 1 :]:
                    if same(a.get_xdata(), b.get_xdata()) and same(a.get_ydata(), b.get_ydata()):
                        labels = a.svrobs_key[1] + b.svrobs_key[1]
                        assert "identical" in labels or "identical" in said, (
                            name,
                            a.svrobs_key,
                            b.svrobs_key,
                        )


def _dashes(ln):
    return ln.get_linestyle(), ln._unscaled_dash_pattern


def test_every_legend_entry_is_a_drawn_artist(figures):
    for name, fig in figures:
        drawn = [ln for ax in fig.axes for ln in ax.lines]
        fills = [c for ax in fig.axes for c in ax.collections if isinstance(c, PolyCollection)]
        legends = list(fig.legends) + [ax.get_legend() for ax in fig.axes if ax.get_legend()]
        assert legends, name
        for leg in legends:
            labels = [t.get_text() for t in leg.get_texts() if t.get_text()]
            assert len(labels) == len(set(labels)), (name, labels)  # no entry twice
            for h, text in zip(leg.legend_handles, leg.get_texts()):
                label = text.get_text()
                if not label:
                    continue  # a blank cell of a row-wise legend
                if isinstance(h, Patch):
                    assert fills, (name, label)
                    continue
                assert isinstance(h, Line2D), (name, label)
                if to_rgba(h.get_color()) == to_rgba(NEUTRAL):  # a line-style entry
                    hits = [ln for ln in drawn if _dashes(ln) == _dashes(h)]
                else:  # a series entry: its colour and marker
                    hits = [
                        ln
                        for ln in drawn
                        if to_rgba(ln.get_color()) == to_rgba(h.get_color())
                        and ln.get_marker() == h.get_marker()
                    ]
                assert hits, (name, label)


def read_csv(text):
    rows = defaultdict(list)
    for r in csv.DictReader(io.StringIO(text)):
        y = float(r["value"]) if r["value"] else math.nan
        rows[(r["panel"], r["series"], r["quantity"])].append((float(r["N0"]), y))
    return rows


def test_each_figure_csv_equals_the_plotted_data(figures):
    for name, fig in figures:
        rows = read_csv(rpt.figure_csv(fig))
        keys = set()
        for ax in fig.axes:
            for ln in ax.lines:
                if not hasattr(ln, "svrobs_key"):
                    assert getattr(ln, "svrobs_ref", False), (name, ln.get_label())
                    continue
                assert ln.svrobs_key not in keys, (name, ln.svrobs_key)  # keys are unique
                keys.add(ln.svrobs_key)
                got = rows[ln.svrobs_key]
                x, y = np.asarray(ln.get_xdata(), float), np.asarray(ln.get_ydata(), float)
                assert len(got) == len(x), (name, ln.svrobs_key)
                np.testing.assert_array_equal(np.array([g[0] for g in got]), x)
                np.testing.assert_array_equal(np.array([g[1] for g in got]), y)
        assert keys == set(rows), name


def test_bands_are_drawn_where_the_label_says(real):
    spec, recs = real["E4"]
    fig = rpt.fig4(recs, spec)
    ax = fig.axes[0]
    assert "5-95 % band" in ax.get_ylabel()
    fills = [c for c in ax.collections if isinstance(c, PolyCollection)]
    rows = read_csv(rpt.figure_csv(fig))
    series = sorted({k[1] for k in rows if k[2] == "q05"})
    assert len(fills) == len(series) == 4
    for fill, s in zip(fills, series):
        lo = [y for _, y in rows[("delta_J", s, "q05")]]
        hi = [y for _, y in rows[("delta_J", s, "q95")]]
        ys = fill.get_paths()[0].vertices[:, 1]
        assert min(ys) == pytest.approx(min(lo)) and max(ys) == pytest.approx(max(hi))
        # the band is the 5 % and 95 % quantiles of ΔJ over the repetitions
        g = float(s.split("=")[1])
        N0 = rows[("delta_J", s, "q05")][0][0]
        v = [
            r["delta_J"]
            for r in recs
            if r["system"] == "paper-stable"
            and r["gamma"] == g
            and r["N0"] == N0
            and r["delta_J"] is not None
        ]
        assert len(v) == spec["reps"]
        assert lo[0] == pytest.approx(float(np.quantile(v, 0.05)), rel=1e-12)
        assert hi[0] == pytest.approx(float(np.quantile(v, 0.95)), rel=1e-12)


def test_log_and_symlog_axes_follow_the_data(figures):
    for name, fig in figures:
        for ax in panels(fig):
            v = np.concatenate([np.asarray(ln.get_ydata(), float) for ln in data_lines(ax)])
            v = v[np.isfinite(v)]
            scale = ax.get_yscale()
            if scale == "log":
                assert (v > 0).all(), name
            if scale == "symlog":
                assert (v < 0).any() and (v > 0).any(), (name, ax.get_title())
                lt = ax.yaxis.get_transform().linthresh
                q = float(np.quantile(np.abs(v[v != 0]), 0.1))
                assert lt <= q < 10 * lt, (name, lt, q)  # the linear region fits the data
            if (v > 0).all() and v.max() / v.min() > 10:
                assert scale == "log", (name, ax.get_title(), scale)


def test_fig_rmse_plots_the_mean_rmse_per_N(real):
    """Oracle: plain-Python means of rmse_A over the repetitions at each N."""
    spec, recs = real["E2"]
    fig = rpt.fig_rmse(recs, spec)
    rows = read_csv(rpt.figure_csv(fig))
    for est, g, series in (("ols", None, "σ_w=1 OLS"), ("svr", 0.05, "σ_w=1 SVR γ=0.05")):
        got = rows[("paper-stable: A", series, "rmse_A")]
        assert got
        for N0, y in got:
            v = [
                r["rmse_A"]
                for r in recs
                if r["system"] == "paper-stable"
                and r["sigma_w"] == 1.0
                and r["estimator"] == est
                and r["gamma"] == g
                and r["N0"] == N0
            ]
            assert y == pytest.approx(sum(v) / len(v), rel=1e-12)


def test_coinciding_curves_get_a_difference_and_the_largest_gap(real):
    spec, recs = real["E2"]
    fig = rpt.fig3(recs, spec)
    rows = read_csv(rpt.figure_csv(fig))
    gaps = []
    for panel in ("paper-stable: A", "paper-unstable: A", "paper-stable: B", "paper-unstable: B"):
        mat = panel[-1]
        ref = dict(rows[(panel, "γ=0.005", f"entry_error_{mat}")])
        for g in ("γ=0.01", "γ=0.05", "γ=0.1"):
            for N0, y in rows[(panel, g, f"entry_error_{mat}")]:
                gaps.append(abs(y - ref[N0]))
    text = " ".join(fig.svrobs_notes)
    assert "lie on top of each other" in text or "differ by up to" in text
    assert f"largest gap is {max(gaps):.2g}" in text


def test_empty_share_panel_is_a_note(real):
    spec, recs = real["E4"]
    fig = rpt.fig4(recs, spec)
    dJ = [r["delta_J"] for r in recs if r["system"] == "paper-stable" and r["delta_J"] is not None]
    n_neg = sum(1 for v in dJ if v < 0)
    assert n_neg == 0  # Theorem 3's bound holds on the reduced grid
    assert f"ΔJ < 0 in 0 of {len(dJ):,} cells" in " ".join(fig.svrobs_notes)
    assert not any("share" in ax.get_ylabel() for ax in fig.axes if ax.get_visible())


def test_pdf_embeds_its_fonts_and_style_does_not_leak(real):
    size_before = matplotlib.rcParams["font.size"]
    spec, recs = real["E4"]
    fig = rpt.fig5(recs, spec)
    pdf = rpt.figure_bytes(fig, "pdf")
    assert pdf.startswith(b"%PDF-") and b"/FontFile2" in pdf and b"/Type3" not in pdf
    assert rpt.figure_bytes(fig, "pdf") == pdf  # deterministic
    assert matplotlib.rcParams["font.size"] == size_before


def test_figure_series_is_shared_data():
    rows = json.loads(json.dumps(rpt.figure_series_json()))
    # every figure: the plan's and the audit's (made when two bounds_methods ran)
    figures = {name for name, *_ in rpt.FIGURE_PLAN} | {"fig_bounds_audit"}
    assert {r["figure"] for r in rows} == figures
    for r in rows:
        assert set(r) >= {"field", "stat", "where", "panels", "lines", "band", "x", "derived"}
        if not r["derived"]:  # the dashboard reads these from the summaries
            assert r["field"] in SUMMARY_FIELDS, r
    keys = [(r["figure"], r["key"]) for r in rows]
    assert len(keys) == len(set(keys))


def test_summary_lines_give_the_figures_curves(real):
    """The dashboard's reading of FIGURE_SERIES (summaries) against the figures'
    own (records): the same curves for every row the summaries can give."""
    from svrobs_core import summarize
    from svrobs_core.report.columns import as_columns, select, spec_meta
    from svrobs_core.report.series import (
        context,
        series_lines,
        summary_context,
        summary_lines,
    )

    checked = 0
    for exp in ("E2", "E4"):
        spec, recs = real[exp]
        groups = summarize(recs)
        cols, meta = as_columns(recs), spec_meta(spec)
        ctx, sctx = context(cols, meta), summary_context(groups, spec)
        assert {k: ctx[k] for k in sctx} == sctx
        for s in rpt.FIGURE_SERIES:
            if s.derived or s.stat not in ("mean", "ratio_of_means"):
                with pytest.raises(ValueError):
                    summary_lines(groups, s, sctx)
                continue
            for line in summary_lines(groups, s, sctx):
                pm = select(cols, **line["panel"]) if s.panels == ("system",) else None
                if pm is None:
                    pm = select(
                        cols, system=line["panel"]["system"], sigma_w=line["panel"]["sigma_w"]
                    )
                mine = [ln for ln in series_lines(cols, meta, s, pm, ctx) if ln.key == line["line"]]
                assert len(mine) == 1, (s.figure, s.key, line["line"])
                np.testing.assert_array_equal(mine[0].N, line["N"])
                np.testing.assert_allclose(mine[0].y, line["y"], rtol=1e-12)
                checked += 1
    assert checked > 20


def test_fig_bounds_audit_plots_the_shares_and_radii(real):
    """Oracle: plain-Python shares (coverage_A = coverage_B = 1) and mean r_A over
    the repetitions at each N0, σ_w = 1, SVR at γ = 0.05 and OLS, per method."""
    sources = audit_sources(real)
    fig = audit_figure(sources)
    rows = read_csv(rpt.figure_csv(fig))
    checked = {"all_inside": 0, "r_A": 0}
    for (panel, series, quantity), pts in rows.items():
        if "(identical)" in series:
            continue  # the shared line; each series' own markers carry its curve
        system = panel.split(":")[0]
        method, est = series.split(" ")[0], series.split(" ")[1].lower()
        for N0, y in pts:
            mine = [
                r
                for r in sources[method]
                if r["system"] == system
                and r["sigma_w"] == 1.0
                and r["estimator"] == est
                and (r["gamma"] is None if est == "ols" else r["gamma"] == 0.05)
                and r["N0"] == N0
            ]
            assert len(mine) == 3  # the reduced grid's repetitions
            if quantity == "all_inside":
                want = sum(r["coverage_A"] == 1 and r["coverage_B"] == 1 for r in mine) / 3
            else:
                want = sum(r["r_A"] for r in mine) / 3
            assert y == pytest.approx(want, rel=1e-12), (panel, series, N0)
            checked[quantity] += 1
    assert checked["all_inside"] > 0 and checked["r_A"] >= 3 * 2 * 2 * 3
    # a method inside in every record of a system is a note there, not a flat line
    for method in AUDIT_EXPERIMENTS:
        for system in ("paper-stable", "paper-unstable"):
            ys = [
                y
                for (p, s, q), pts in rows.items()
                if q == "all_inside" and p.startswith(system) and s.startswith(method + " ")
                for _, y in pts
            ]
            every = [
                r["coverage_A"] == 1 and r["coverage_B"] == 1
                for r in sources[method]
                if r["system"] == system and r["sigma_w"] == 1.0 and r["gamma"] in (None, 0.05)
            ]
            assert (not ys) == all(every), (method, system)
    text = " ".join(fig.svrobs_notes)
    n = sum(
        1
        for m in ("paper", "self-normalized")
        for r in sources[m]
        if r["sigma_w"] == 1.0 and r["gamma"] in (None, 0.05)
    )
    assert all(
        r["coverage_A"] == 1 and r["coverage_B"] == 1
        for m in ("paper", "self-normalized")
        for r in sources[m]
        if r["sigma_w"] == 1.0 and r["gamma"] in (None, 0.05)
    )  # on the reduced grid (what the note below rests on)
    assert (
        f"The paper and self-normalized boxes contain every entry of A and of B in all {n:,}"
        in text
    )


def _legend_labels(fig):
    return [t.get_text() for leg in fig.legends for t in leg.get_texts() if t.get_text()]


def test_fig_bounds_audit_axes_and_reference_line(real):
    """Shares on a linear axis with the 1 − δ line (and its legend entry), r_A on a
    log axis; with every box covering everywhere, no share row and no 1 − δ entry."""
    delta = 0.01
    fig = audit_figure(audit_sources(real), delta)
    fig.canvas.draw()
    share = [ax for ax in panels(fig) if ax.get_ylabel().startswith("share")]
    radius = [ax for ax in panels(fig) if ax.get_ylabel().startswith("mean r_A")]
    assert share and len(radius) == 2
    for ax in share:
        assert ax.get_yscale() == "linear"
        refs = [ln for ln in ax.lines if getattr(ln, "svrobs_ref", False)]
        assert [tuple(ln.get_ydata()) for ln in refs] == [(1 - delta, 1 - delta)]
        lo, hi = ax.get_ylim()
        assert lo < 1 - delta < hi and hi < 1.05  # a share, zoomed to the data
    for ax in radius:
        assert ax.get_yscale() == "log"
    assert "1 − δ = 0.99" in _legend_labels(fig)
    inside = {
        m: [{**r, "coverage_A": 1.0, "coverage_B": 1.0} for r in recs]
        for m, recs in audit_sources(real).items()
    }
    fig1 = audit_figure(inside, delta)
    assert not any(ax.get_ylabel().startswith("share") for ax in fig1.axes)
    assert not any(getattr(ln, "svrobs_ref", False) for ax in fig1.axes for ln in ax.lines)
    assert not any("δ" in lab for lab in _legend_labels(fig1))
    assert "The paper, self-normalized and bootstrap boxes contain every entry" in " ".join(
        fig1.svrobs_notes
    )
