"""One figure of a report: how it is built (:class:`FigureJob`), its files, and the
functions that build and draw it in another process
(docs/performance.md#figures-drawn-beside-the-build).

A :class:`FigureJob` is a figure function and its arguments. Pickled, every
:class:`~.columns.Columns` among the arguments keeps only the fields the figure
reads, so a helper process is sent a few columns, not all of a job's rows; it
builds the figure there and returns a :class:`Drawn`: the files and what the
report's text needs of the figure (its notes, whether it is empty).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, NamedTuple

from .columns import Columns
from .figure_files import figure_bytes
from .plotting import figure_csv

if TYPE_CHECKING:
    from matplotlib.figure import Figure

# a figure function: (records, spec, *, experiment=) -> Figure
FigureFn = Callable[..., Any]


@dataclass
class FigureJob:
    """``fn(*args, **kwargs)``, a Figure. ``fields``: what the figure reads of its
    Columns arguments (a Columns, or a dict of them), which are all that is
    pickled of them; None: every field."""

    fn: FigureFn
    args: tuple[Any, ...]
    kwargs: dict[str, Any] = field(default_factory=dict)
    fields: tuple[str, ...] | None = None

    def figure(self) -> Figure:
        fig: Figure = self.fn(*self.args, **self.kwargs)
        return fig

    def __getstate__(self) -> dict[str, Any]:
        return {**self.__dict__, "args": tuple(self._narrow(a) for a in self.args)}

    def _narrow(self, a: Any) -> Any:
        if self.fields is None:
            return a
        if isinstance(a, Columns):
            return a.only(self.fields)
        if isinstance(a, dict) and a and all(isinstance(v, Columns) for v in a.values()):
            return {k: v.only(self.fields) for k, v in a.items()}
        return a


class Drawn(NamedTuple):
    """A figure drawn elsewhere: its files (None: not drawn) and what the report's
    text reads of it."""

    png: bytes
    svg: bytes | None
    pdf: bytes | None
    csv: str | None
    notes: list[str]
    empty: bool


@dataclass
class ReportFigure:
    """One figure of the report: its caption (the plan's text plus the figure's
    own notes: what coincides, the largest gaps, what is left out), the
    Figure (or the job that builds it, at first use), and its PNG / SVG / PDF /
    CSV. An *empty* figure (nothing to plot, e.g. every coverage is 1) has only
    its notes: no image is written."""

    name: str
    title: str
    caption: str
    experiment: str
    source: Figure | FigureJob
    _drawn: Drawn | None = None
    _figure: Figure | None = None
    _png: bytes | None = None
    _svg: bytes | None = None
    _pdf: bytes | None = None
    _laid_out: bool = False

    @property
    def figure(self) -> Figure:
        if self._figure is None:
            src = self.source
            self._figure = src.figure() if isinstance(src, FigureJob) else src
        return self._figure

    @property
    def notes(self) -> list[str]:
        if self._drawn is not None:
            return list(self._drawn.notes)
        return list(getattr(self.figure, "svrobs_notes", []))

    @property
    def empty(self) -> bool:
        if self._drawn is not None:
            return self._drawn.empty
        return bool(getattr(self.figure, "svrobs_empty", False))

    @property
    def full_caption(self) -> str:
        return " ".join([self.caption, *self.notes]).strip()

    def png(self) -> bytes:
        if self._png is None:
            self._png = self._draw("png")
        return self._png

    def svg(self) -> bytes:
        if self._svg is None:
            self._svg = self._draw("svg")
        return self._svg

    def pdf(self) -> bytes:
        if self._pdf is None:
            self._pdf = self._draw("pdf")
        return self._pdf

    def csv(self) -> str:
        """The plotted data (:func:`~.plotting.figure_csv`)."""
        if self._drawn is not None and self._drawn.csv is not None:
            return self._drawn.csv
        return figure_csv(self.figure)

    def set_drawn(self, drawn: Drawn) -> None:
        """Files drawn elsewhere (:func:`draw_png`, :func:`draw_files`); a file given
        as None is drawn here when asked for."""
        self._drawn = drawn
        self._png, self._svg, self._pdf = drawn.png, drawn.svg, drawn.pdf

    def _draw(self, fmt: str) -> bytes:
        """The figure's first draw is a PNG: the constrained layout is computed by it
        and then kept fixed, with no layout engine at all, so the SVG and PDF (and
        any later render) skip savefig's dry draw (an engine, even matplotlib's
        placeholder for "none", asks for one) and the layout pass."""
        fig = self.figure
        if not self._laid_out:
            png = figure_bytes(fig, "png")
            import matplotlib

            off: Any = {"figure.autolayout": False, "figure.constrained_layout.use": False}
            with matplotlib.rc_context(off):  # None would otherwise mean the rc's engine
                fig.set_layout_engine(None)
            self._laid_out = True
            if fmt == "png":
                return png
            self._png = png if self._png is None else self._png
        return figure_bytes(fig, fmt)


def draw_png(job: FigureJob | Figure) -> Drawn:
    """The figure's PNG, as ``ReportFigure.png()`` draws it, for a report page
    (picklable: run in a helper process)."""
    rf = ReportFigure("", "", "", "", job)
    return Drawn(b"" if rf.empty else rf.png(), None, None, None, rf.notes, rf.empty)


def draw_files(job: FigureJob | Figure) -> Drawn:
    """The figure's PNG, SVG, PDF and CSV, as ``ReportFigure`` draws them, for the
    reproduction's files (picklable: run in a worker process)."""
    rf = ReportFigure("", "", "", "", job)
    if rf.empty:  # nothing to draw: no image files (a ReportFigure draws them if asked)
        return Drawn(b"", None, None, rf.csv(), rf.notes, True)
    return Drawn(rf.png(), rf.svg(), rf.pdf(), rf.csv(), rf.notes, False)
