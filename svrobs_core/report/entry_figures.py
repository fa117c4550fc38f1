"""The report's Figs. 2 and 3 of the paper: per system and matrix the entry
error, the Lemma 2 interval ends and ε of each line; Fig. 3 adds each γ's error
minus that of the smallest γ and the first N0 with stable_certified in at least
half of the repetitions (docs/science.md#92-how-the-tables-and-figures-aggregate).

The shared figure plumbing is :mod:`~svrobs_core.report.figures` and
:mod:`~svrobs_core.report.plotting`.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np

from ..array_types import Array
from .columns import Columns, Meta, as_columns, fmt_num, n0_ratio, spec_meta, systems_of
from .derived import first_stable_certified
from .figures import Records, Styles, _diff_panel, _panels, draw, series_name
from .plotting import (
    figure_legend,
    figure_title,
    fmt_gap,
    grid_legend,
    joined,
    label_panel,
    legend_line,
    mark,
    new_figure,
    no_data_panel,
    no_data_reason,
    note,
    overlap_text,
    series_handle,
    value_axis,
)
from .series import Line, context, figure_series, series_lines
from .style import series_style, size, styled

if TYPE_CHECKING:
    from matplotlib.figure import Figure


QUANTITY_LS = {"err": "-", "hi": "--", "lo": "-.", "eps": ":"}
QUANTITY_LEGEND = (  # the caption gives the formulas
    ("err", "error"),
    ("hi", "upper end"),
    ("lo", "−(lower end)"),
    ("eps", "ε_X"),
)


def _entry_figure(
    fig_name: str,
    records: Records,
    spec: Any,
    experiment: str | None,
    ctx_over: dict[str, Any],
    title: str,
    height_cm: float,
) -> tuple[Figure, Columns, Meta, dict[str, Any], Styles, Array, list[tuple[Any, ...]]]:
    """Shared body of fig2/fig3: per system (columns) and matrix (rows) the entry
    error, the interval ends and ε of each line; fig3 adds difference rows."""
    cols, meta = as_columns(records), spec_meta(spec)
    ctx = context(cols, meta, **ctx_over)
    rows = figure_series(fig_name)
    with_diff = rows["err_A"].diff_to is not None
    panels = _panels(cols)
    nr, hr = (4, [2, 1, 2, 1]) if with_diff else (2, [1, 1])
    fig, axes = new_figure(nr, len(panels), size("two", height_cm), sharex=True, height_ratios=hr)
    ratio = n0_ratio(cols)
    styles: Styles = {}
    gaps: list[tuple[Any, ...]] = []
    for c, (system, pm) in enumerate(panels):
        for r, mat in enumerate(("A", "B")):
            ax = axes[(2 if with_diff else 1) * r, c]
            panel = f"{system}: {mat}"
            drawn: dict[str, Line] = {}
            for q in ("err", "hi", "lo", "eps"):
                s = rows[f"{q}_{mat}"]
                for ln in series_lines(cols, meta, s, pm, ctx):
                    name = series_name(ln.key)
                    st = styles.setdefault(name, series_style(len(styles), line=False))
                    draw(ax, ln, panel, name, s.field, ls=QUANTITY_LS[q], **st)
                    if q == "err":
                        drawn[name] = ln
            if not drawn and not ax.lines:
                fields = (f"{mat}_hat", f"r_{mat}", f"eps_{mat}")
                no_data_panel(ax, no_data_reason(cols, pm, fields, meta))
                if with_diff:
                    axes[2 * r + 1, c].set_visible(False)
                continue
            value_axis(ax)
            label_panel(
                ax, f"{mat}: error and bounds", panel, ratio, xlabel=not with_diff and r == 1
            )
            if with_diff:
                axd = axes[2 * r + 1, c]
                if len(drawn) < 2:
                    axd.set_visible(False)
                    continue
                ref_name = next(iter(drawn))  # the smallest γ
                others = [(n, ln) for n, ln in drawn.items() if n != ref_name]
                big = _diff_panel(
                    axd,
                    fig,
                    panel,
                    others,
                    (ref_name, drawn[ref_name]),
                    styles,
                    f"entry_error_{mat} minus {ref_name}",
                )
                label_panel(axd, f"minus {ref_name}", None, ratio, xlabel=r == 1)
                gaps.append((big[0], f"{panel}, {big[1]}, N0={big[2]:g}", ref_name, big[3]))
    quantities = [legend_line(ls=QUANTITY_LS[k], label=lab) for k, lab in QUANTITY_LEGEND]
    grid_legend(fig, [[series_handle(n, st) for n, st in styles.items()], quantities])
    figure_title(fig, title, experiment, meta)
    return fig, cols, meta, ctx, styles, axes, gaps


@styled
def fig2(
    records: Records,
    spec: Any = None,
    *,
    experiment: str | None = "E1",
    gamma: float | None = None,
) -> Figure:
    """Fig. 2: SVR (γ = 0.05) estimation error and Lemma 2 interval ends vs N0,
    S and U, one colour and marker per σ_w; ε_A, ε_B of Corollary 1 dotted."""
    g = gamma if gamma is not None else None
    cols = as_columns(records)
    ctx_g = context(cols, spec_meta(spec), table=g)["table"]
    fig, *_ = _entry_figure(
        "fig2",
        cols,
        spec,
        experiment,
        {"table": g},
        f"Fig. 2: SVR (γ={fmt_num(ctx_g)}) estimation error and Lemma 2 interval ends vs "
        "sample length, for each σ_w",
        13,
    )
    return fig


@styled
def fig3(
    records: Records,
    spec: Any = None,
    *,
    experiment: str | None = "E2",
    sigma_w: float | None = None,
) -> Figure:
    """Fig. 3: as Fig. 2 for the four γ at one σ_w (default 1), each γ's error
    minus that of γ_ref below; the first N0 at which stable_certified holds in
    ≥ half the reps (vertical lines, if any, and in the caption)."""
    cols = as_columns(records)
    sw = context(cols, spec_meta(spec), sigma_ref=sigma_w)["sigma_ref"]
    fig, cols, meta, ctx, styles, axes, gaps = _entry_figure(
        "fig3",
        cols,
        spec,
        experiment,
        {"sigma_ref": sigma_w},
        f"Fig. 3: SVR estimation error and Lemma 2 interval ends for each γ (σ_w={fmt_num(sw)})",
        17,
    )
    if gaps:
        g = max(gaps, key=lambda t: t[0])
        note(
            fig,
            overlap_text(
                f"The error curves of the {len(styles)} γ", max(t[3] for t in gaps), gaps[0][2]
            )
            + f"; the difference rows show each γ's error minus that of {g[2]}; the "
            f"largest gap is {fmt_gap(g[0])} ({g[1]}).",
        )
    _certified_marks(fig, cols, meta, ctx, styles, axes)
    return fig


def _certified_marks(
    fig: Figure, cols: Columns, meta: Meta, ctx: dict[str, Any], styles: Styles, axes: Array
) -> None:
    """Vertical lines at the first N0 with stable_certified in ≥ half the reps; the
    caption says where (or that it never happens in the grid)."""
    sw = ctx["sigma_ref"]
    first = first_stable_certified(cols) if sw is not None else {}
    hits: list[str] = []
    never: list[str] = []
    n0_max: Any = None
    for c, system in enumerate(systems_of(cols)):
        for name in styles:
            g = float(name.split("=")[1]) if name.startswith("γ=") else None
            key = next(
                (
                    k
                    for k in first
                    if k[0] == system
                    and k[2] == "svr"
                    and k[1] is not None
                    and np.isclose(k[1], sw)
                    and k[3] is not None
                    and g is not None
                    and np.isclose(k[3], g)
                ),
                None,
            )
            if key is None:
                continue
            hit = first[key]
            n0_max = hit["N0_max"]
            if hit["N0"] is None:
                never.append(f"{system} {name}")
                continue
            hits.append(f"{system} {name}: N0={hit['N0']}")
            ln = axes[0, c].axvline(hit["N0"], color=styles[name]["color"], ls=(0, (1, 2)), lw=1.6)
            mark(ln, svrobs_ref=True)
    if hits:
        handles = list(fig.legends[0].legend_handles) if fig.legends else []
        fig.legends.clear()
        handles.append(
            legend_line(
                ls=(0, (1, 2)), lw=1.6, label="first N0 with stable_certified in ≥ half the reps"
            )
        )
        figure_legend(fig, handles, ncol=max(1, min(4, len(styles))))
    if not first:
        return
    if not hits:
        text = (
            "stable_certified holds in at least half of the repetitions at no N0 of the grid "
            f"(N0 ≤ {n0_max}), for no γ on any system, so no vertical line is drawn"
        )
    else:
        text = "The dotted vertical lines mark the first N0 at which stable_certified holds in "
        text += "at least half of the repetitions: " + "; ".join(hits)
        if never:
            text += f"; never (N0 ≤ {n0_max}) for {joined(never)}"
    note(fig, text + ".")
