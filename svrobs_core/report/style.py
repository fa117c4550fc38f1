"""The one figure style of the report: print sizes, fonts, palette, line styles.

Figures are drawn at their print size (one column 8.5 cm, two columns 17.5 cm
wide), so a font size here is the size on paper; no text is below
``MIN_FONT_PT``. Colours are the Okabe-Ito palette (safe for the common colour
vision deficiencies); each series also gets its own line style and marker,
so that a figure printed in grey keeps its series apart.

The style is applied with :func:`figure_style`, a ``matplotlib.rc_context``:
nothing here changes matplotlib's global state.
"""

from __future__ import annotations

from collections.abc import Callable
from contextlib import AbstractContextManager
from typing import Any, ParamSpec, TypeVar, cast

P = ParamSpec("P")
R = TypeVar("R")

CM = 1 / 2.54  # inches per cm
ONE_COLUMN_CM = 8.5
TWO_COLUMN_CM = 17.5
MIN_FONT_PT = 8.0

# Okabe & Ito (2008), "Color Universal Design"; yellow (#F0E442) left out (too light on white)
PALETTE = ("#0072B2", "#D55E00", "#009E73", "#CC79A7", "#E69F00", "#56B4E9", "#000000")
LINESTYLES = ("-", "--", "-.", ":", (0, (5, 1.5, 1, 1.5, 1, 1.5)), (0, (8, 2)))
MARKERS = ("o", "s", "^", "D", "v", "P", "X")
# legend entries that explain a line style only (not a series) are drawn in this colour
NEUTRAL = "#404040"
REFERENCE = "#7f7f7f"  # reference lines (0, 1 − δ)

RC = {
    "font.family": "DejaVu Sans",
    "font.size": 8.0,
    "axes.titlesize": 8.5,
    "axes.labelsize": 8.0,
    "xtick.labelsize": 8.0,
    "ytick.labelsize": 8.0,
    "legend.fontsize": 8.0,
    "legend.title_fontsize": 8.0,
    "figure.titlesize": 9.0,
    "axes.linewidth": 0.6,
    "axes.titlepad": 3.0,
    "xtick.major.width": 0.6,
    "ytick.major.width": 0.6,
    "xtick.major.size": 3.0,
    "ytick.major.size": 3.0,
    "lines.linewidth": 1.2,
    "lines.markersize": 4.0,
    "grid.linewidth": 0.4,
    "grid.alpha": 0.4,
    "legend.frameon": False,
    "legend.handlelength": 2.8,
    "legend.columnspacing": 1.2,
    "axes.formatter.use_mathtext": True,
    "mathtext.default": "regular",
    "pdf.fonttype": 42,  # TrueType, embedded: the text stays text in the PDF
    "ps.fonttype": 42,
    "svg.fonttype": "none",
    "svg.hashsalt": "svrobs",
    "figure.dpi": 100,
}


def figure_style() -> AbstractContextManager[None]:
    """Context manager: the report's rcParams while a figure is built or saved."""
    import matplotlib

    ctx: AbstractContextManager[None] = matplotlib.rc_context(cast(Any, RC))
    return ctx


def styled(fn: Callable[P, R]) -> Callable[P, R]:
    """Decorator: build the figure inside :func:`figure_style`."""
    import functools

    @functools.wraps(fn)
    def wrapper(*args: P.args, **kwargs: P.kwargs) -> R:
        with figure_style():
            return fn(*args, **kwargs)

    return wrapper


def size(width: str = "two", height_cm: float = 8.0) -> tuple[float, float]:
    """Figure size in inches: ``width`` "one" (8.5 cm) or "two" (17.5 cm) columns."""
    w = {"one": ONE_COLUMN_CM, "two": TWO_COLUMN_CM}[width]
    return (w * CM, height_cm * CM)


def series_style(i: int, *, line: bool = True, markevery: Any = None) -> dict[str, Any]:
    """Colour, line style and marker of series ``i`` (each cycles on its own)."""
    st = {
        "color": PALETTE[i % len(PALETTE)],
        "marker": MARKERS[i % len(MARKERS)],
        "markersize": 3.5,
        "markerfacecolor": "white" if i % 2 else PALETTE[i % len(PALETTE)],
        "markeredgewidth": 0.9,
    }
    if line:
        st["ls"] = LINESTYLES[i % len(LINESTYLES)]
    if markevery is not None:
        st["markevery"] = markevery
    return st
