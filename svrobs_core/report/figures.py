"""The report's figures on estimation: Table 2's curves, coverage and SVR minus
OLS, and what the other figure modules share (Figs. 2-3 of the paper are in
``entry_figures``, the cost figures in ``cost_figures``).

Each is ``f(records, spec=None, *, experiment=...) -> matplotlib.figure.Figure``;
records are record dicts (docs/spec.md#record-fields) or
:class:`~svrobs_core.report.columns.Columns`.
What is plotted comes from :data:`~svrobs_core.report.series.FIGURE_SERIES`;
the look from :mod:`~svrobs_core.report.style`. Curves that coincide get a
difference panel and a caption note with the largest gap (``fig.svrobs_notes``).
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from typing import TYPE_CHECKING, Any, TypeAlias

import numpy as np

from ..array_types import Array, FloatArray
from .columns import Columns, Meta, as_columns, fmt_num, n0_ratio, select, spec_meta, systems_of
from .plotting import (
    MERGED_NOTE,
    differences,
    figure_legend,
    figure_title,
    fmt_gap,
    grid_legend,
    label_panel,
    legend_line,
    mark,
    new_figure,
    no_data_panel,
    no_data_reason,
    note,
    overlap_text,
    panel_title,
    plot_line,
    plot_merged,
    ref_line,
    series_handle,
    value_axis,
)
from .series import Line, context, figure_series, series_lines
from .style import LINESTYLES, series_style, size, styled

if TYPE_CHECKING:
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure
    from matplotlib.lines import Line2D

Records: TypeAlias = Columns | Iterable[dict[str, Any]]
Styles: TypeAlias = dict[str, dict[str, Any]]  # series name -> its plot style


def series_name(key: dict[str, Any]) -> str:
    """A line's name from its group key: "OLS", "SVR γ=0.05", "σ_w=1", ..."""
    parts = []
    if "sigma_w" in key:
        parts.append(f"σ_w={fmt_num(key['sigma_w'])}")
    if "estimator" in key:
        parts.append("OLS" if key["estimator"] == "ols" else "SVR")
    if "gamma" in key and key["gamma"] is not None:
        parts.append(f"γ={fmt_num(key['gamma'])}")
    return " ".join(parts) if parts else "all"


def draw(ax: Axes, ln: Line, panel: str, series: str, quantity: str, **style: Any) -> Line2D:
    """Plot a :class:`~.series.Line` (recorded for the CSV)."""
    return plot_line(ax, ln.x, ln.y, panel=panel, series=series, quantity=quantity, **style)


def _panels(cols: Columns) -> list[tuple[str, Array]]:
    systems = systems_of(cols) or ["(none)"]
    return [(s, select(cols, system=s)) for s in systems]


def _diff_panel(
    ax: Any,
    fig: Any,
    panel: str,
    lines: list[tuple[str, Any]],
    ref: tuple[str, Any],
    styles: dict[str, dict[str, Any]],
    what: str,
) -> Any:
    """Each line minus ``ref`` in ``ax``; returns the largest gap (value, name, x)."""
    diffs, big = differences([(n, ln.x, ln.y) for n, ln in lines], (ref[0], ref[1].x, ref[1].y))
    for name, x, d in diffs:
        plot_line(ax, x, d, panel=panel, series=name, quantity=what, **styles[name])
    ref_line(ax, 0.0)
    value_axis(ax)
    return big


# ---------------------------------------------------------------------------
# fig_rmse
# ---------------------------------------------------------------------------


@styled
def fig_rmse(
    records: Records,
    spec: Any = None,
    *,
    experiment: str | None = "E1",
    gamma: float | None = None,
) -> Figure:
    """RMSE of Ã and B̃ per N (the curves behind Table 2): OLS (solid, filled
    markers) and SVR (dashed, open markers), one colour and marker per σ_w; below
    each, SVR − OLS."""
    cols, meta = as_columns(records), spec_meta(spec)
    ctx = context(cols, meta, table=gamma)
    rows = figure_series("fig_rmse")
    panels = _panels(cols)
    fig, axes = new_figure(
        4, len(panels), size("two", 19), sharex=True, height_ratios=[2, 1.1, 2, 1.1]
    )
    ratio = n0_ratio(cols)
    sig_styles: dict[Any, int] = {}
    gaps: list[tuple[float, str, float]] = []
    for c, (system, pm) in enumerate(panels):
        for r, mat in enumerate(("A", "B")):
            s = rows[f"rmse_{mat}"]
            ax, axd = axes[2 * r, c], axes[2 * r + 1, c]
            lines = series_lines(cols, meta, s, pm, ctx)
            if not lines:
                no_data_panel(ax, no_data_reason(cols, pm, (s.field,), meta))
                axd.set_visible(False)
                continue
            panel = f"{system}: {mat}"
            by_sig: dict[Any, dict[str, Line]] = {}
            for ln in lines:
                sw = ln.key["sigma_w"]
                j = sig_styles.setdefault(sw, len(sig_styles))
                st = series_style(j, line=False)
                ols = ln.key["estimator"] == "ols"
                # OLS: small filled marker on top; SVR: larger open marker around it
                # the same marker positions for both estimators of a σ_w
                step = max(2, len(ln.x) // 8)
                st["markevery"] = (j % step, step) if len(ln.x) > 10 else None
                if ols:
                    st.update(markerfacecolor=st["color"], zorder=3)
                else:
                    st.update(markerfacecolor="none", markersize=6.5, zorder=2)
                name = series_name(ln.key) + ("" if ols else f" γ={fmt_num(ctx['table'])}")
                draw(ax, ln, panel, name, s.field, ls="-" if ols else "--", **st)
                by_sig.setdefault(sw, {})["ols" if ols else "svr"] = ln
            value_axis(ax)
            label_panel(ax, f"{s.label} (mean)", panel, ratio, xlabel=False)
            pairs = {sw: d for sw, d in by_sig.items() if "ols" in d and "svr" in d}
            if not pairs:
                axd.set_visible(False)
                continue
            for sw, d in pairs.items():
                name = f"σ_w={fmt_num(sw)}"
                [(_, x, dy)], big = differences(
                    [(name, d["svr"].x, d["svr"].y)], ("OLS", d["ols"].x, d["ols"].y)
                )
                st = dict(series_style(sig_styles[sw], line=False), ls="-")
                plot_line(
                    axd, x, dy, panel=panel, series=name, quantity=f"{s.field} SVR − OLS", **st
                )
                gaps.append((big[0], f"{system} {mat}, {name}, N0={big[2]:g}", big[3]))
            ref_line(axd, 0.0)
            value_axis(axd)
            label_panel(axd, "SVR − OLS", None, ratio, xlabel=r == 1)
    handles = [
        series_handle(f"σ_w={fmt_num(sw)}", series_style(j, line=False))
        for sw, j in sig_styles.items()
    ]
    est = [
        legend_line(ls="-", label="OLS (filled markers)"),
        legend_line(ls="--", label=f"SVR γ={fmt_num(ctx['table'])} (open markers)"),
    ]
    grid_legend(fig, [handles, est])
    if gaps:
        g = max(gaps, key=lambda t: t[0])
        note(
            fig,
            overlap_text(
                f"The OLS and SVR γ={fmt_num(ctx['table'])} RMSE curves",
                max(t[2] for t in gaps),
                "OLS",
            )
            + f"; the difference panels show SVR − OLS; the largest |SVR − OLS| is "
            f"{fmt_gap(g[0])} ({g[1]}).",
        )
    figure_title(
        fig,
        f"RMSE per sample length behind Table 2 (OLS vs SVR γ={fmt_num(ctx['table'])})",
        experiment,
        meta,
    )
    return fig


# ---------------------------------------------------------------------------
# coverage and SVR minus OLS
# ---------------------------------------------------------------------------


@styled
def fig_coverage(records: Records, spec: Any = None, *, experiment: str | None = "E2") -> Figure:
    """Empirical coverage of the Lemma 2 intervals vs N0 with the 1 − δ line:
    rows (system, A/B), columns σ_w; one line per estimator / γ, identical lines
    drawn once. If every coverage is 1 there is nothing to plot: the figure is
    empty (``svrobs_empty``) and its note says so."""
    cols, meta = as_columns(records), spec_meta(spec)
    ctx = context(cols, meta)
    rows = figure_series("fig_coverage")
    systems = systems_of(cols) or ["(none)"]
    from .columns import sigmas_of

    sig: Sequence[float | None] = sigmas_of(cols) or [None]
    cells = [(system, mat) for system in systems for mat in ("A", "B")]
    level = 1 - meta.delta
    lines: dict[tuple[str, str, float | None], list[Line]] = {}
    for system, mat in cells:
        for s in sig:
            pm = select(cols, system=system, sigma_w=s) if s is not None else np.zeros(cols.n, bool)
            lines[(system, mat, s)] = series_lines(cols, meta, rows[f"coverage_{mat}"], pm, ctx)

    def values(mats: list[str]) -> FloatArray:
        ys = [ln.y[np.isfinite(ln.y)] for (_, m, _), v in lines.items() if m in mats for ln in v]
        return np.concatenate(ys) if ys else np.array([])

    def n_records(mats: list[str]) -> str:
        ok = np.zeros(cols.n, bool)
        for m in mats:
            ok |= np.isfinite(cols[f"coverage_{m}"])
        return f"{int(ok.sum()):,}"

    ones = [m for m in ("A", "B") if values([m]).size and (values([m]) == 1.0).all()]
    title = "Empirical coverage of the Lemma 2 entry intervals (mean share of entries inside)"
    if len(ones) == 2:
        return _empty_figure(
            "Every Lemma 2 interval contains its entry: the coverage of A and B is 1 in all "
            f"{n_records(ones)} records (every system, σ_w, N, estimator and γ), above "
            f"1 − δ = {fmt_num(level)}; no figure is drawn.",
            title,
            experiment,
            meta,
        )
    cells = [(system, mat) for system, mat in cells if mat not in ones]
    ys = values([m for m in ("A", "B") if m not in ones])
    fig, axes = new_figure(
        len(cells), len(sig), size("two", 4.2 * len(cells) + 2.5), sharex=True, sharey=True
    )
    for m in ones:
        note(
            fig,
            f"The coverage of {m} is 1 in all {n_records([m])} records (every system, σ_w, N, "
            f"estimator and γ), above 1 − δ = {fmt_num(level)}: its rows are left out.",
        )
    styles: Styles = {}
    for r, (system, mat) in enumerate(cells):
        for c, s in enumerate(sig):
            ax = axes[r, c]
            panel = f"{system}, σ_w={fmt_num(s)}: {mat}"
            items = [(series_name(ln.key), ln.x, ln.y) for ln in lines[(system, mat, s)]]
            if not items:
                pm = select(cols, system=system, sigma_w=s)
                no_data_panel(ax, no_data_reason(cols, pm, (f"coverage_{mat}",), meta))
                continue
            for name, *_ in items:
                styles.setdefault(name, series_style(len(styles)))
            if plot_merged(ax, items, styles, panel=panel, quantity=f"coverage_{mat}"):
                note(fig, MERGED_NOTE)
            ref_line(ax, level, ls="--", color="k")
            panel_title(ax, panel)
            if c == 0:
                ax.set_ylabel(f"coverage of {mat}_ij intervals")
            if r == len(cells) - 1:
                from .plotting import n0_axis

                n0_axis(ax, n0_ratio(cols))
            ax.grid(True)
    lo = float(ys.min()) if ys.size else level
    axes[0, 0].set_ylim(min(lo, level) - 0.02, 1.005)
    handles = [series_handle(n, st) for n, st in styles.items()]
    level_h = legend_line("k", "--", f"1 − δ = {fmt_num(level)}")
    grid_legend(fig, [handles[i : i + 3] for i in range(0, len(handles), 3)] + [[level_h]])
    figure_title(fig, title, experiment, meta)
    return fig


def _empty_figure(text: str, title: str, experiment: str | None, meta: Meta) -> Figure:
    """A figure with nothing to plot: no panels, the note as its only text; the
    report shows the note instead of an image (``svrobs_empty``)."""
    import textwrap

    fig, axes = new_figure(1, 1, size("two", 4))
    fig.delaxes(axes[0, 0])
    note(fig, text)
    fig.text(0.5, 0.3, "\n".join(textwrap.wrap(text, 100)), ha="center", va="center")
    mark(fig, svrobs_empty=True)
    figure_title(fig, title, experiment, meta)
    return fig


@styled
def fig_svr_ols_diff(
    records: Records, spec: Any = None, *, experiment: str | None = "E2"
) -> Figure:
    """max_ij |Ã_svr − Ã_ols| on the same data (mean over reps) vs N0, one colour
    and marker per γ, one line style per σ_w: where SVR and OLS really differ."""
    cols, meta = as_columns(records), spec_meta(spec)
    ctx = context(cols, meta)
    s = figure_series("fig_svr_ols_diff")["svr_ols_A"]
    panels = _panels(cols)
    fig, axes = new_figure(1, len(panels), size("two", 9.5), sharey=True)
    g_styles: Styles = {}
    s_styles: dict[str, Any] = {}  # σ_w name -> line style
    for c, (system, pm) in enumerate(panels):
        ax = axes[0, c]
        lines = series_lines(cols, meta, s, pm, ctx)
        if not lines:
            why = (
                "needs OLS and SVR estimates (A_hat) of the same repetitions"
                if cols.has("rmse_A", pm)
                else no_data_reason(cols, pm, ("A_hat",), meta)
            )
            no_data_panel(ax, why)
            continue
        for ln in lines:
            gname, sname = f"γ={fmt_num(ln.key['gamma'])}", f"σ_w={fmt_num(ln.key['sigma_w'])}"
            st = g_styles.setdefault(gname, series_style(len(g_styles), line=False))
            ls = s_styles.setdefault(sname, LINESTYLES[len(s_styles) % len(LINESTYLES)])
            draw(ax, ln, system, f"{gname} {sname}", s.field, ls=ls, **st)
        value_axis(ax)
        label_panel(ax, f"{s.label} (mean)", system, n0_ratio(cols, pm))
    handles = [series_handle(n, st) for n, st in g_styles.items()]
    handles += [legend_line(ls=ls, label=n) for n, ls in s_styles.items()]
    figure_legend(fig, handles, ncol=min(len(handles), 4))
    figure_title(
        fig, "SVR minus OLS: largest entry difference of Ã on the same data", experiment, meta
    )
    return fig
