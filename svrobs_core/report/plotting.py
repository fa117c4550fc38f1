"""Figure plumbing shared by every figure: a headless (Agg) Figure at print size,
lines that record what they plot (the figure's CSV), value axes (log for
positive data, symlog sized to the data where it changes sign), identical
curves drawn once, difference panels, legends, notes and the figure's CSV
(its PNG, SVG and PDF bytes: :mod:`.figure_files`).

Each Figure made by :func:`new_figure` carries ``svrobs_rows`` (every plotted
curve: panel, series, quantity, x, y, in drawing order) and ``svrobs_notes``
(sentences for the caption: what coincides, the largest gaps, panels left out
and why). These and the lines' ``svrobs_key`` / ``svrobs_ref`` are instance
attributes matplotlib does not declare, set with :func:`mark`.
"""

from __future__ import annotations

import csv
import io
import math
import sys
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

import numpy as np

from ..array_types import Array, FloatArray
from .columns import STAGE_FIELDS, Columns, Meta
from .style import NEUTRAL, REFERENCE

if TYPE_CHECKING:
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure
    from matplotlib.lines import Line2D

# A recorded curve: (panel, series, quantity, x, y).
Row = tuple[str, str, str, FloatArray, FloatArray]

SAME_TOL = 1e-12  # two curves within this (relative to their size) are "identical"


def mark(obj: object, **attrs: Any) -> None:
    """Set svrobs_* attributes on a matplotlib object (its instance dict)."""
    vars(obj).update(attrs)


def _ensure_agg() -> None:
    import matplotlib

    if "matplotlib.pyplot" not in sys.modules:  # never switch a user's live pyplot backend
        matplotlib.use("Agg")


def new_figure(
    nrows: int,
    ncols: int,
    figsize: tuple[float, float],
    sharex: bool = False,
    sharey: bool = False,
    **gridspec: Any,
) -> tuple[Figure, Array]:
    """A Figure (Agg canvas, constrained layout) and its axes grid (always 2-D)."""
    _ensure_agg()
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    from matplotlib.layout_engine import ConstrainedLayoutEngine

    fig = Figure(figsize=figsize, layout="constrained")
    engine = fig.get_layout_engine()
    assert isinstance(engine, ConstrainedLayoutEngine)  # layout="constrained"
    engine.set(h_pad=0.03, w_pad=0.03, hspace=0.03, wspace=0.03)
    FigureCanvasAgg(fig)
    axes = fig.subplots(
        nrows, ncols, squeeze=False, sharex=sharex, sharey=sharey, gridspec_kw=gridspec or None
    )
    mark(fig, svrobs_rows=[], svrobs_notes=[], svrobs_empty=False)
    return fig, axes


def figure_title(fig: Figure, what: str, experiment: str | None, meta: Meta) -> None:
    """Title (wrapped to the figure's width) and, below, experiment and seed."""
    import textwrap

    exp = experiment or "experiment"
    width = max(30, int(fig.get_figwidth() * 13))  # characters of 9 pt per line
    fig.suptitle("\n".join(textwrap.wrap(what, width)) + f"\n{exp} · seed {meta.seed}")


def notes_of(fig: Figure) -> list[str]:
    """The caption's sentences of a figure of :func:`new_figure`."""
    notes: list[str] = vars(fig)["svrobs_notes"]
    return notes


def note(fig: Figure, text: str) -> None:
    """A sentence for the figure's caption."""
    notes = notes_of(fig)
    if text and text not in notes:
        notes.append(text)


def no_data_panel(ax: Axes, msg: str) -> None:
    ax.text(
        0.5,
        0.5,
        "no data\n" + msg,
        ha="center",
        va="center",
        transform=ax.transAxes,
        color="0.3",
        wrap=True,
        bbox=dict(boxstyle="round", fc="0.95", ec="0.7"),
    )
    # not set_xticks([]): that would clear the ticks of every axis shared with this one
    ax.tick_params(left=False, bottom=False, labelleft=False, labelbottom=False)
    mark(ax.figure, svrobs_no_data=True)


def n0_axis(ax: Axes, ratio: float | None) -> None:
    if ratio is not None and ratio != 1.0:
        ax.set_xlabel(f"sample length N0 = {ratio:g}·N")
    else:
        ax.set_xlabel("sample length N0")


def panel_title(ax: Axes, title: str) -> None:
    """A panel's title, placed once at the top of its axes (``y=1``): no panel has top
    ticks or an offset text to move it clear of (docs/performance.md#figure-files)."""
    ax.set_title(title, y=1.0)


def label_panel(
    ax: Axes, ylabel: str, title: str | None, ratio: float | None, *, xlabel: bool = True
) -> None:
    """A panel's y label, title, N0 axis (if ``xlabel``) and grid."""
    ax.set_ylabel(ylabel)
    if title:
        panel_title(ax, title)
    if xlabel:
        n0_axis(ax, ratio)
    ax.grid(True, which="major")


def no_data_reason(cols: Columns, mask: Array | None, fields: tuple[str, ...], meta: Meta) -> str:
    """Why a panel has no data: the stage did not run, or its fields are null."""
    need = [s for s, fs in STAGE_FIELDS.items() if any(f in fs for f in fields)]
    missing = [s for s in need if meta.stages and s not in meta.stages]
    if missing:
        return f"stage(s) {', '.join(missing)} not in the spec that ran"
    if cols.n == 0 or (mask is not None and not np.any(mask)):
        return "no records for this selection"
    notes = [v for v in cols["notes"][mask] if v] if mask is not None else []
    text = f"fields {', '.join(fields)} are null in every record"
    if notes:
        text += f"\n(notes: {notes[0][:80]})"
    return text


# ---------------------------------------------------------------------------
# recorded lines, bands and reference lines
# ---------------------------------------------------------------------------


def plot_line(
    ax: Axes,
    x: Any,
    y: Any,
    *,
    panel: str,
    series: str,
    quantity: str,
    label: str | None = None,
    **style: Any,
) -> Line2D:
    """``ax.plot`` that records (panel, series, quantity, x, y) for the figure's CSV."""
    x = np.asarray(x, float)
    y = np.asarray(y, float)
    if "marker" in style and "markevery" not in style and len(x) > 10:
        # about 8 markers per line, each series of the panel shifted by one point
        # so that coinciding series still show every series' markers
        order = ax.__dict__.setdefault("_svrobs_series", {})
        k = order.setdefault(series, len(order))
        step = max(2, len(x) // 8)
        style["markevery"] = (k % step, step)
    (ln,) = ax.plot(x, y, label=label if label else "_nolegend_", **style)
    mark(ln, svrobs_key=(panel, series, quantity))
    rows: list[Row] = vars(ax.figure)["svrobs_rows"]
    rows.append((panel, series, quantity, x, y))
    return ln


def plot_band(
    ax: Axes,
    x: Any,
    lo: FloatArray,
    hi: FloatArray,
    *,
    panel: str,
    series: str,
    band: tuple[float, float],
    color: Any,
    ls: Any = "-",
) -> None:
    """A band drawn as a fill with both edges as thin lines in the series' line
    style (both recorded)."""
    qlo, qhi = (f"q{round(100 * b):02d}" for b in band)
    ok = np.isfinite(lo) & np.isfinite(hi)
    ax.fill_between(np.asarray(x)[ok], lo[ok], hi[ok], color=color, alpha=0.18, lw=0)
    for q, v in ((qlo, lo), (qhi, hi)):
        plot_line(
            ax, x, v, panel=panel, series=series, quantity=q, color=color, lw=0.5, ls=ls, alpha=0.7
        )


def ref_line(ax: Axes, y: float, **style: Any) -> Line2D:
    """A horizontal reference line (0, 1 − δ), not data: not in the CSV."""
    style.setdefault("color", REFERENCE)
    style.setdefault("lw", 0.8)
    ln = ax.axhline(y, **style)
    mark(ln, svrobs_ref=True)
    return ln


def legend_line(
    color: Any = NEUTRAL, ls: Any = "-", label: str = "", marker: str | None = None, **kw: Any
) -> Line2D:
    """A legend proxy: a series (its colour and marker) or a quantity (its line
    style, in the neutral colour)."""
    from matplotlib.lines import Line2D

    return Line2D([], [], color=color, ls=ls, marker=marker, label=label, **kw)


def series_handle(label: str, style: dict[str, Any]) -> Line2D:
    """Legend proxy of a series: colour and marker, solid line."""
    keep = ("color", "marker", "markersize", "markerfacecolor", "markeredgewidth")
    return legend_line(ls="-", label=label, **{k: style[k] for k in keep if k in style})


def figure_legend(fig: Figure, handles: list[Any], ncol: int = 4) -> None:
    if handles:
        fig.legend(handles=handles, loc="outside lower center", ncol=ncol)


def grid_legend(fig: Figure, rows: list[list[Any]]) -> None:
    """A figure legend laid out row by row (``rows`` of handles; matplotlib
    fills a legend column by column, so the rows are interleaved and padded
    with blank entries, which carry no label)."""
    rows = [r for r in rows if r]
    if not rows:
        return
    ncol = max(len(r) for r in rows)
    blank = legend_line(label="", alpha=0.0)
    cells = [r + [blank] * (ncol - len(r)) for r in rows]
    fig.legend(
        handles=[cells[i][j] for j in range(ncol) for i in range(len(cells))],
        loc="outside lower center",
        ncol=ncol,
    )


# ---------------------------------------------------------------------------
# value axes
# ---------------------------------------------------------------------------


def _panel_values(ax: Axes) -> FloatArray:
    vals = [ln.get_ydata() for ln in ax.lines if hasattr(ln, "svrobs_key")]
    if not vals:
        return np.array([])
    v = np.concatenate([np.asarray(a, float) for a in vals])
    finite: FloatArray = v[np.isfinite(v)]
    return finite


def _decade(v: float) -> bool:
    e = math.log10(abs(v))
    return abs(e - round(e)) < 1e-9


def tick_labels(ticks: Sequence[float]) -> list[str]:
    """One format for all ticks of an axis: plain numbers when every tick is within
    [0.001, 10⁴), else powers of ten (10ᵏ, or m×10ᵏ)."""
    nz = [abs(t) for t in ticks if t != 0]
    plain = all(1e-3 <= t < 1e4 for t in nz)
    out: list[str] = []
    for t in ticks:
        if t == 0:
            out.append("0")
        elif plain:
            out.append(f"{t:.4g}")
        else:
            e = math.floor(math.log10(abs(t)) + 1e-9)
            m = t / 10**e
            sign = "−" if t < 0 else ""
            out.append(f"{sign}$10^{{{e}}}$" if _decade(t) else f"${m:.2g}\\times10^{{{e}}}$")
    return out


def _fixed_ticks(ax: Axes, ticks: list[float], which: str = "y") -> None:
    from matplotlib.ticker import FixedFormatter, FixedLocator, NullLocator

    axis = ax.yaxis if which == "y" else ax.xaxis
    axis.set_major_locator(FixedLocator(ticks))
    axis.set_major_formatter(FixedFormatter(tick_labels(ticks)))
    axis.set_minor_locator(NullLocator())


def log_axis(ax: Axes, lo: float, hi: float, which: str = "y") -> None:
    """Log y (or x) axis over [lo, hi] (padded) with at least three labelled ticks:
    decades (or 1-2-5 steps) over a wide range, evenly stepped values over a
    range of less than about one decade."""
    from matplotlib.ticker import MaxNLocator

    if hi <= lo:
        lo, hi = lo / 1.5, hi * 1.5
    pad = (hi / lo) ** 0.06
    lo, hi = lo / pad, hi * pad
    (ax.set_yscale if which == "y" else ax.set_xscale)("log")
    (ax.set_ylim if which == "y" else ax.set_xlim)(lo, hi)
    inside: list[float] = []
    if hi / lo > 3:
        e0, e1 = math.floor(math.log10(lo)) - 1, math.ceil(math.log10(hi)) + 1
        found: list[list[float]] = []
        for subs in ((1.0,), (1.0, 3.0), (1.0, 2.0, 5.0), (1.0, 2.0, 3.0, 5.0, 7.0)):
            ticks = [m * 10.0**e for e in range(e0, e1 + 1) for m in subs]
            found.append([t for t in ticks if lo <= t <= hi])
        # the coarsest set with 4 to 8 ticks, else the coarsest with at least 3
        coarse = next((t for t in found if 4 <= len(t) <= 8), None)
        inside = coarse or next((t for t in found if len(t) >= 3), found[-1])
        if len(inside) > 7:  # many decades: every other one
            inside = inside[:: math.ceil(len(inside) / 6)]
    if len(inside) < 3:
        for nbins in (4, 6, 9):
            vals = MaxNLocator(nbins=nbins, steps=[1, 2, 2.5, 5, 10]).tick_values(lo, hi)
            inside = [float(t) for t in vals if lo <= t <= hi and t > 0]
            if len(inside) >= 3:
                break
    _fixed_ticks(ax, inside, which)


def symlog_axis(ax: Axes, v: FloatArray) -> None:
    """Symlog y axis for values of both signs. The linear region ends at the decade
    below the 10 % quantile of the nonzero |values| (sized to the data); ticks at
    0 and at the largest decade each side reaches."""
    nz = np.abs(v[v != 0])
    lt = 10.0 ** math.floor(math.log10(float(np.quantile(nz, 0.1))))
    ax.set_yscale("symlog", linthresh=lt, linscale=0.8)
    top, bot = float(v.max()), float(-v.min())
    ax.set_ylim(-max(bot, lt) * 1.6, max(top, lt) * 1.6)
    ticks = [0.0]
    for sign, reach in ((1, top), (-1, bot)):
        dec = [lt * 10.0**k for k in range(1, 30) if lt * 10.0**k <= reach * 1.0001]
        ticks.append(sign * (dec[-1] if dec else lt))  # one per side: labels never crowd
    _fixed_ticks(ax, sorted(ticks))


def value_axis(ax: Axes, scale: str = "auto") -> str:
    """Scale of a panel's y axis from its recorded data: ``log`` when every value
    is positive, ``symlog`` (sized to the data) when values change sign, else
    linear. Returns the scale used."""
    v = _panel_values(ax)
    if scale == "linear" or v.size == 0:
        return "linear"
    if (v > 0).all():
        log_axis(ax, float(v.min()), float(v.max()))
        return "log"
    if (v < 0).any() and (v > 0).any():
        symlog_axis(ax, v)
        return "symlog"
    return "linear"


# ---------------------------------------------------------------------------
# identical curves and differences
# ---------------------------------------------------------------------------


def same_curve(a: Any, b: Any) -> bool:
    """Two curves equal within SAME_TOL (relative to their size); NaN equals NaN."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    if a.shape != b.shape or not np.array_equal(np.isnan(a), np.isnan(b)):
        return False
    ok = np.isfinite(a)
    if not ok.any():
        return True
    scale = max(1.0, float(np.abs(a[ok]).max()))
    return bool(np.abs(a[ok] - b[ok]).max() <= SAME_TOL * scale)


def merge_identical(items: list[tuple[Any, ...]]) -> list[tuple[list[Any], tuple[Any, ...]]]:
    """Group ``(name, x, y, ...)`` items whose (x, y) are identical: [(names, first item)]."""
    groups: list[tuple[list[Any], tuple[Any, ...]]] = []
    for it in items:
        for names, first in groups:
            if same_curve(first[1], it[1]) and same_curve(first[2], it[2]):
                names.append(it[0])
                break
        else:
            groups.append(([it[0]], it))
    return groups


def plot_merged(
    ax: Axes,
    items: list[tuple[Any, ...]],
    styles: dict[str, dict[str, Any]],
    *,
    panel: str,
    quantity: str,
    **over: Any,
) -> bool:
    """Draw ``(name, x, y)`` items in their ``styles``; identical ones share one line
    (the first one's colour and line style) on which each shows its own markers in
    turn. Returns True if any were identical."""
    merged = False
    for names, (_, x, y) in merge_identical(items):
        if len(names) == 1:
            st = {**styles[names[0]], **over}
            plot_line(ax, x, y, panel=panel, series=names[0], quantity=quantity, **st)
            continue
        merged = True
        base = {k: v for k, v in {**styles[names[0]], **over}.items() if "marker" not in k}
        label = joined(names) + " (identical)"
        plot_line(ax, x, y, panel=panel, series=label, quantity=quantity, **base)
        k = len(names)
        step = max(k, len(x) // 8)
        for j, n in enumerate(names):
            st = {kk: v for kk, v in styles[n].items() if kk != "ls"}
            st["markevery"] = (j * max(1, step // k), step)
            plot_line(ax, x, y, panel=panel, series=n, quantity=quantity, ls="none", **st)
    return merged


MERGED_NOTE = (
    "Identical curves (within 1e-12) share one line, drawn in the style of the first, "
    "on which each one's markers appear in turn."
)


def joined(names: list[str]) -> str:
    return names[0] if len(names) == 1 else ", ".join(names[:-1]) + " and " + names[-1]


def differences(
    lines: list[tuple[str, Any, Any]], ref: tuple[str, Any, Any]
) -> tuple[list[tuple[str, FloatArray, FloatArray]], tuple[Any, ...]]:
    """``lines``: (name, x, y); ``ref``: (name, x, y). -> [(name, x, y − y_ref)] on the
    x values both have, and (largest |y − y_ref|, its line, its x, largest
    |y − y_ref| / |y_ref| of any point)."""
    at = dict(zip(np.asarray(ref[1]).tolist(), np.asarray(ref[2]).tolist()))
    out: list[tuple[str, FloatArray, FloatArray]] = []
    big: tuple[float, Any, Any] = (0.0, None, None)
    rel = 0.0
    for name, x, y in lines:
        xs = [xv for xv in np.asarray(x).tolist() if xv in at]
        yv = dict(zip(np.asarray(x).tolist(), np.asarray(y).tolist()))
        d = np.array([yv[xv] - at[xv] for xv in xs], float)
        out.append((name, np.array(xs, float), d))
        if np.isfinite(d).any():
            i = int(np.nanargmax(np.abs(d)))
            if abs(d[i]) > big[0]:
                big = (float(abs(d[i])), name, xs[i])
            with np.errstate(divide="ignore", invalid="ignore"):
                r = np.abs(d) / np.abs(np.array([at[xv] for xv in xs], float))
            if np.isfinite(r).any():
                rel = max(rel, float(np.nanmax(np.where(np.isfinite(r), r, np.nan))))
    return out, (*big, rel)


def overlap_text(what: str, rel: float, ref: str) -> str:
    """Say that curves lie on top of each other when no point differs by 3 % or
    more from the reference curve ``ref``, else by how much they differ."""
    if rel < 0.03:
        return f"{what} lie on top of each other at this scale (no point differs by 3 % from {ref})"
    return f"{what} differ by up to {100 * rel:.2g} % of {ref}"


def fmt_gap(v: float) -> str:
    return f"{v:.2g}"


# ---------------------------------------------------------------------------
# output: CSV of the plotted data, PNG / SVG / PDF bytes
# ---------------------------------------------------------------------------

CSV_COLUMNS = ("panel", "series", "quantity", "N0", "value")


def figure_csv(fig: Figure) -> str:
    """Every plotted curve of ``fig``, one row per point (long format; values at
    full precision, empty where the curve has a gap)."""
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(CSV_COLUMNS)
    for panel, series, quantity, x, y in getattr(fig, "svrobs_rows", []):
        for xv, yv in zip(x.tolist(), y.tolist()):
            w.writerow(
                (panel, series, quantity, repr(xv), "" if not math.isfinite(yv) else repr(yv))
            )
    return buf.getvalue()
