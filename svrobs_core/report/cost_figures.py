"""The report's figures on the observer cost: Figs. 4 and 5 of the paper and the
share of certified gains. Same conventions as :mod:`.figures`."""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any, TypeAlias

import numpy as np

from ..paper import STABLE
from .columns import Columns, as_columns, fmt_num, n0_ratio, select, spec_meta, systems_of
from .figures import _diff_panel, _panels, draw, series_name
from .plotting import (
    MERGED_NOTE,
    figure_legend,
    figure_title,
    fmt_gap,
    grid_legend,
    label_panel,
    legend_line,
    log_axis,
    new_figure,
    no_data_panel,
    no_data_reason,
    note,
    plot_band,
    plot_merged,
    series_handle,
    value_axis,
)
from .series import context, figure_series, series_lines
from .style import NEUTRAL, series_style, size, styled

Records: TypeAlias = Columns | Iterable[dict[str, Any]]


def _pick_system(cols: Columns, prefer: str | None, field_: str) -> str | None:
    systems = systems_of(cols)
    if prefer in systems:
        return prefer
    for s in systems:
        if cols.has(field_, select(cols, system=s)):
            return s
    return systems[0] if systems else None


def _count(n: int) -> str:
    return f"{n:,}"


@styled
def fig4(
    records: Records,
    spec: Any = None,
    *,
    experiment: str | None = "E3",
    system: str | None = STABLE,
) -> Any:
    """Fig. 4 (one column): ΔJ = J_b − J vs N0 for each γ on S, mean over the
    repetitions with the 5-95 % band; below, each γ's mean minus that of γ_ref;
    the share of repetitions with ΔJ < 0 as a third panel only if there is one."""
    cols, meta = as_columns(records), spec_meta(spec)
    system = _pick_system(cols, system, "delta_J")
    ctx = context(cols, meta, system_S=system)
    rows = figure_series("fig4")
    s, sn = rows["delta_J"], rows["share_neg"]
    pm = np.ones(cols.n, bool)
    lines = series_lines(cols, meta, s, pm, ctx)
    dJ = cols["delta_J"]
    m = select(cols, system=system, estimator="svr") if system else np.zeros(cols.n, bool)
    ok = m & np.isfinite(dJ)
    n_neg, n_all = int(np.sum(dJ[ok] < 0)), int(ok.sum())
    share = n_neg > 0
    ratio = n0_ratio(cols, m)
    nr = 3 if share else 2
    fig, axes = new_figure(
        nr,
        1,
        size("one", 15 if share else 11.5),
        sharex=True,
        height_ratios=[2, 1, 1][:nr],
    )
    ax, axd = axes[0, 0], axes[1, 0]
    title = f"Fig. 4: ΔJ = J_b − J vs sample length for each γ on {system}"
    if not lines:
        no_data_panel(ax, no_data_reason(cols, m, ("delta_J", "J_bound", "J_exact"), meta))
        for a in axes[1:, 0]:
            a.set_visible(False)
        figure_title(fig, title, experiment, meta)
        return fig
    styles: dict[str, dict[str, Any]] = {}
    drawn: dict[Any, Any] = {}
    for i, ln in enumerate(lines):
        name = series_name(ln.key)
        st = styles.setdefault(name, series_style(i))
        band = dict(band=s.band, color=st["color"], ls=st["ls"])
        assert ln.lo is not None and ln.hi is not None  # the delta_J row has a band
        plot_band(ax, ln.x, ln.lo, ln.hi, panel="delta_J", series=name, **band)
        draw(ax, ln, "delta_J", name, "mean", **st)
        drawn[name] = ln
    value_axis(ax)
    _band_note(fig, lines, s.band)
    label_panel(
        ax, "ΔJ (mean, 5-95 % band)", f"{system}: bound minus exact cost", ratio, xlabel=False
    )
    ref_name = next(iter(drawn))  # the smallest γ
    if len(drawn) > 1:
        others = [(n, ln) for n, ln in drawn.items() if n != ref_name]
        big = _diff_panel(
            axd,
            fig,
            "difference",
            others,
            (ref_name, drawn[ref_name]),
            styles,
            f"mean delta_J minus {ref_name}",
        )
        label_panel(axd, f"ΔJ − ΔJ({ref_name})", None, ratio, xlabel=nr == 2)
        note(
            fig,
            f"The middle panel shows each γ's mean ΔJ minus that of {ref_name}; the "
            f"largest gap is {fmt_gap(big[0])} ({big[1]}, N0={big[2]:g}).",
        )
    else:
        axd.set_visible(False)
    if share:
        ax3 = axes[2, 0]
        items = [(series_name(ln.key), ln.x, ln.y) for ln in series_lines(cols, meta, sn, pm, ctx)]
        if plot_merged(ax3, items, styles, panel="share_negative", quantity="share"):
            note(fig, MERGED_NOTE)
        ax3.set_ylim(-0.02, 1.02)
        label_panel(ax3, "share with ΔJ < 0", f"{system}: where Theorem 3's bound fails", ratio)
    note(
        fig,
        f"ΔJ < 0 in {_count(n_neg)} of {_count(n_all)} cells"
        + ("" if share else " (so no panel for the share of ΔJ < 0)")
        + ".",
    )
    from matplotlib.patches import Patch

    handles: list[Any] = [series_handle(n, st) for n, st in styles.items()]
    handles.append(Patch(color=NEUTRAL, alpha=0.3, lw=0, label="5-95 % of the repetitions"))
    figure_legend(fig, handles, ncol=2)
    figure_title(fig, title, experiment, meta)
    return fig


def _band_note(fig: Any, lines: list[Any], band: tuple[Any, ...] | None) -> None:
    """Say how wide the band is when it is too narrow to see beside the mean."""
    rel = [
        np.nanmax((ln.hi - ln.lo) / np.abs(ln.y))
        for ln in lines
        if ln.hi is not None and np.isfinite((ln.hi - ln.lo) / np.abs(ln.y)).any()
    ]
    if rel and max(rel) < 0.03:
        assert band is not None  # the lines have a band
        lo, hi = (round(100 * b) for b in band)
        note(
            fig,
            f"The {lo}-{hi} % band over the repetitions is drawn but is narrower than the "
            f"lines: at most {100 * max(rel):.2g} % of the mean.",
        )


@styled
def fig5(records: Records, spec: Any = None, *, experiment: str | None = "E4") -> Any:
    """Fig. 5: cost ratio r = |mean J_γ − mean J_ref| / mean J_ref vs N0, S and U
    (solid); the mean of the per-repetition ``cost_ratio`` dashed; below, each γ's
    r minus that of the smallest γ."""
    cols, meta = as_columns(records), spec_meta(spec)
    ctx = context(cols, meta)
    rows = figure_series("fig5")
    panels = _panels(cols)
    fig, axes = new_figure(2, len(panels), size("two", 12), sharex=True, height_ratios=[2, 1])
    styles: dict[str, dict[str, Any]] = {}
    gaps: list[Any] = []
    for c, (system, pm) in enumerate(panels):
        ax, axd = axes[0, c], axes[1, c]
        lines = series_lines(cols, meta, rows["ratio"], pm, ctx)
        if not lines:
            why = (
                no_data_reason(cols, pm, ("J_exact",), meta)
                if not cols.has("J_exact", pm)
                else f"no J at the reference γ_ref={fmt_num(ctx['gamma_ref'])}"
            )
            no_data_panel(ax, why)
            axd.set_visible(False)
            continue
        drawn = {}
        for ln in lines:
            name = series_name(ln.key)
            st = styles.setdefault(name, series_style(len(styles), line=False))
            draw(ax, ln, system, name, "ratio_of_means", ls="-", **st)
            drawn[name] = ln
        for ln in series_lines(cols, meta, rows["ratio_rep"], pm, ctx):
            name = series_name(ln.key)
            if name in styles:
                st = dict(ls="--", lw=0.8, color=styles[name]["color"], alpha=0.8)
                draw(ax, ln, system, name, "cost_ratio mean", **st)
        value_axis(ax)
        ylabel = f"r  (γ_ref = {fmt_num(ctx['gamma_ref'])})"
        label_panel(ax, ylabel, system, n0_ratio(cols, pm), xlabel=False)
        names = list(drawn)
        if len(names) < 2:
            axd.set_visible(False)
            continue
        big = _diff_panel(
            axd,
            fig,
            f"{system} difference",
            [(n, drawn[n]) for n in names[1:]],
            (names[0], drawn[names[0]]),
            styles,
            f"ratio_of_means minus {names[0]}",
        )
        label_panel(axd, f"r − r({names[0]})", None, n0_ratio(cols, pm))
        gaps.append((big[0], f"{system}, {big[1]}, N0={big[2]:g}", names[0]))
    kinds = [
        legend_line(ls="-", label="r of the mean exact costs"),
        legend_line(ls="--", lw=0.8, label="mean of per-repetition cost_ratio"),
    ]
    grid_legend(fig, [[series_handle(n, st) for n, st in styles.items()], kinds])
    if gaps:
        g = max(gaps, key=lambda t: t[0])
        note(
            fig,
            f"The lower panels show each γ's r minus that of {g[2]}; the largest gap is "
            f"{fmt_gap(g[0])} ({g[1]}).",
        )
    figure_title(
        fig,
        f"Fig. 5: observer cost ratio vs sample length (reference γ={fmt_num(ctx['gamma_ref'])})",
        experiment,
        meta,
    )
    return fig


@styled
def fig_certified(records: Records, spec: Any = None, *, experiment: str | None = "E4") -> Any:
    """Share of repetitions whose observer gain L is certified (g(L) < 1), and
    the share with ρ(A − LC) < 1 for the true A, vs N0 per γ (identical lines
    drawn once; a share that is 1 everywhere is a caption note, not a line)."""
    cols, meta = as_columns(records), spec_meta(spec)
    ctx = context(cols, meta)
    rows = figure_series("fig_certified")
    panels = _panels(cols)
    fig, axes = new_figure(1, len(panels), size("two", 8.5), sharey=True)
    all_ones = {}
    for key in ("certified", "stable_true"):
        ys = [ln.y for _, pm in panels for ln in series_lines(cols, meta, rows[key], pm, ctx)]
        all_ones[key] = bool(ys) and all(np.all(y[np.isfinite(y)] == 1.0) for y in ys)
    styles: dict[str, dict[str, Any]] = {}
    for c, (system, pm) in enumerate(panels):
        ax = axes[0, c]
        if not cols.has("certified", pm):
            no_data_panel(ax, no_data_reason(cols, pm, ("certified", "g_L"), meta))
            continue
        for key, ls, lw in (("certified", "-", 1.2), ("stable_true", "--", 0.9)):
            if all_ones[key] and key == "stable_true":
                continue
            items = [
                (series_name(ln.key), ln.x, ln.y)
                for ln in series_lines(cols, meta, rows[key], pm, ctx)
            ]
            for name, *_ in items:
                styles.setdefault(name, series_style(len(styles), line=False))
            if plot_merged(ax, items, styles, panel=system, quantity=rows[key].field, ls=ls, lw=lw):
                note(fig, MERGED_NOTE)
        ax.set_ylim(-0.03, 1.03)
        x = cols["N0"][pm]
        if np.isfinite(x).any() and np.nanmin(x) > 0 and np.nanmax(x) / np.nanmin(x) > 10:
            log_axis(ax, float(np.nanmin(x)), float(np.nanmax(x)), "x")  # the jump is early
        label_panel(ax, "share of repetitions", system, n0_ratio(cols, pm))
    if all_ones["stable_true"]:
        n = int(np.isfinite(cols["rho_true"]).sum())
        note(
            fig,
            f"ρ(A − LC) < 1 for the true A in every repetition with a gain ({_count(n)} "
            "of them), for every γ: not drawn.",
        )
    kinds = [legend_line(ls="-", label="certified: g(L) < 1")]
    if not all_ones["stable_true"]:
        kinds.append(legend_line(ls="--", lw=0.9, label="ρ(A − LC) < 1 for the true A"))
    grid_legend(fig, [[series_handle(n, st) for n, st in styles.items()], kinds])
    figure_title(fig, "Share of certified observer gains vs sample length", experiment, meta)
    return fig
