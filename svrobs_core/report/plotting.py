"""Figure plumbing shared by every figure: a headless (Agg) Figure, titles,
"no data" panels and why, the N0 axis, legends, and rendering to PNG/SVG bytes."""

from __future__ import annotations

import io
import sys

import numpy as np

from .columns import STAGE_FIELDS, Columns, Meta


def _ensure_agg():
    import matplotlib

    if "matplotlib.pyplot" not in sys.modules:  # never switch a user's live pyplot backend
        matplotlib.use("Agg")


def new_figure(nrows: int, ncols: int, figsize, sharex=False, sharey=False):
    _ensure_agg()
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=figsize, layout="constrained")
    FigureCanvasAgg(fig)
    axes = fig.subplots(nrows, ncols, squeeze=False, sharex=sharex, sharey=sharey)
    return fig, axes


def figure_title(fig, what: str, experiment: str | None, meta: Meta):
    exp = experiment or "experiment"
    fig.suptitle(f"{what}\n{exp} · seed {meta.seed}", fontsize=11)


def no_data_panel(ax, msg: str):
    ax.text(
        0.5,
        0.5,
        "no data\n" + msg,
        ha="center",
        va="center",
        transform=ax.transAxes,
        fontsize=9,
        color="0.35",
        wrap=True,
        bbox=dict(boxstyle="round", fc="0.95", ec="0.7"),
    )
    # not set_xticks([]): that would clear the ticks of every axis shared with this one
    ax.tick_params(left=False, bottom=False, labelleft=False, labelbottom=False)


def n0_axis(ax, ratio: float | None):
    if ratio is not None and ratio != 1.0:
        ax.set_xlabel(f"sample length N0 = {ratio:g}·N  (N rollouts)")
    else:
        ax.set_xlabel("sample length N0")


def label_panel(ax, ylabel: str, title: str, ratio: float | None, *, xlabel=True, grid="major"):
    """A panel's y label, title, N0 axis (if ``xlabel``) and grid (``grid`` ticks)."""
    ax.set_ylabel(ylabel)
    ax.set_title(title, fontsize=10)
    if xlabel:
        n0_axis(ax, ratio)
    ax.grid(alpha=0.3, which=grid)


def no_data_reason(cols: Columns, mask, fields: tuple[str, ...], meta: Meta) -> str:
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


def figure_bytes(fig, fmt: str = "png", dpi: int = 110) -> bytes:
    """Render a Figure to PNG or SVG bytes in memory (deterministic metadata)."""
    buf = io.BytesIO()
    if fmt == "svg":
        import matplotlib

        with matplotlib.rc_context({"svg.hashsalt": "svrobs", "svg.fonttype": "none"}):
            fig.savefig(buf, format="svg", metadata={"Date": None})
    elif fmt == "png":
        fig.savefig(buf, format="png", dpi=dpi, metadata={"Software": None})
    else:
        raise ValueError(f"fmt must be 'png' or 'svg', got {fmt!r}")
    return buf.getvalue()


def figure_legend(fig, handles, ncol=4):
    if handles:
        fig.legend(
            handles=handles, loc="outside lower center", ncol=ncol, fontsize=8, frameon=False
        )


def legend_line(color="0.2", ls="-", label=""):
    from matplotlib.lines import Line2D

    return Line2D([], [], color=color, ls=ls, label=label)
