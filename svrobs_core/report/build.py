"""The whole report: which figure is drawn from which experiment, findings per
experiment and Table 2, assembled into a :class:`Report` (all at once with
:func:`build_report`, or as experiments arrive with :class:`ReportBuilder`)."""

from __future__ import annotations

from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from ..paper import EXPERIMENTS, PRESET_NAME
from .audit import audit_findings, audit_rows, audit_sources, fig_bounds_audit
from .columns import Columns, as_columns, spec_meta
from .cost_figures import fig4, fig5, fig_certified
from .entry_figures import fig2, fig3
from .figure_files import figure_bytes
from .figures import fig_coverage, fig_rmse, fig_svr_ols_diff
from .findings import findings
from .plotting import figure_csv
from .tables import table2

if TYPE_CHECKING:
    from matplotlib.figure import Figure

# a figure function: (records, spec, *, experiment=) -> Figure
FigureFn = Callable[..., Any]


@dataclass
class ReportFigure:
    """One figure of the report: its caption (the plan's text plus the figure's
    own notes: what coincides, the largest gaps, what is left out), the
    Figure, and its PNG / SVG / PDF / CSV. An *empty* figure (nothing to plot,
    e.g. every coverage is 1) has only its notes: no image is written."""

    name: str
    title: str
    caption: str
    experiment: str
    figure: Figure
    _png: bytes | None = None
    _svg: bytes | None = None
    _pdf: bytes | None = None

    @property
    def notes(self) -> list[str]:
        return list(getattr(self.figure, "svrobs_notes", []))

    @property
    def empty(self) -> bool:
        return bool(getattr(self.figure, "svrobs_empty", False))

    @property
    def full_caption(self) -> str:
        return " ".join([self.caption, *self.notes]).strip()

    def png(self) -> bytes:
        if self._png is None:
            self._png = figure_bytes(self.figure, "png")
            # the constrained layout is computed by that first draw; keep it fixed
            # with no layout engine at all, so the SVG and PDF (and any later
            # render) skip savefig's dry draw (an engine, even matplotlib's
            # placeholder for "none", asks for one) and the layout pass
            import matplotlib

            off: Any = {"figure.autolayout": False, "figure.constrained_layout.use": False}
            with matplotlib.rc_context(off):  # None would otherwise mean the rc's engine
                self.figure.set_layout_engine(None)
        return self._png

    def svg(self) -> bytes:
        if self._svg is None:
            self.png()
            self._svg = figure_bytes(self.figure, "svg")
        return self._svg

    def pdf(self) -> bytes:
        if self._pdf is None:
            self.png()
            self._pdf = figure_bytes(self.figure, "pdf")
        return self._pdf

    def csv(self) -> str:
        """The plotted data (:func:`~.plotting.figure_csv`)."""
        return figure_csv(self.figure)

    def set_rendered(self, png: bytes, svg: bytes | None = None, pdf: bytes | None = None) -> None:
        """Bytes rendered elsewhere (e.g. :func:`render_figure` in another process);
        a file given as None is drawn here when asked for."""
        self._png, self._svg, self._pdf = png, svg, pdf


def render_png(fig: Figure) -> tuple[bytes, None, None]:
    """``(PNG, None, None)`` of a Figure, as ``ReportFigure.png()`` gives it (for a
    report page, whose only file is the PNG; picklable, as :func:`render_figure`)."""
    rf = ReportFigure("", "", "", "", fig)
    return (b"" if rf.empty else rf.png()), None, None


def render_figure(fig: Figure) -> tuple[bytes, bytes, bytes]:
    """(PNG, SVG, PDF) of a Figure, as ``ReportFigure.png()``/``svg()``/``pdf()``
    give them (picklable: figures can be rendered in worker processes)."""
    rf = ReportFigure("", "", "", "", fig)
    if rf.empty:
        return b"", b"", b""
    return rf.png(), rf.svg(), rf.pdf()


@dataclass
class Report:
    title: str
    experiments: dict[str, dict[str, Any]]  # name -> {title, spec, n_records, findings, notes}
    table2: list[dict[str, Any]]
    table2_source: str | None
    figures: list[ReportFigure]
    provenance: dict[str, Any]
    # the uncertainty-set audit: rows of audit.audit_rows, its findings,
    # and bounds_method -> the experiment it was computed from
    audit: list[dict[str, Any]] = field(default_factory=list)
    audit_findings: list[str] = field(default_factory=list)
    audit_sources: dict[str, str] = field(default_factory=dict)
    # (title, why) of each planned figure no experiment of the report has the data for
    figures_not_drawn: list[tuple[str, str]] = field(default_factory=list)


# name, function, preferred experiments, fields it needs, title, caption
FIGURE_PLAN: tuple[tuple[str, FigureFn, tuple[str, ...], tuple[str, ...], str, str], ...] = (
    (
        "fig_rmse",
        fig_rmse,
        ("E1",),
        ("rmse_A",),
        "RMSE per sample length (Table 2 curves)",
        "Mean RMSE of Ã and B̃ over repetitions at each N, OLS (solid, filled markers) and SVR "
        "(dashed, open markers), one colour and marker per σ_w; below each, SVR − OLS.",
    ),
    (
        "fig2",
        fig2,
        ("E1", "E2"),
        ("A_hat", "r_A"),
        "Fig. 2: estimation error and Lemma 2 interval ends, γ = 0.05",
        "Solid (error): max_ij |ΔX_ij| with ΔX = X − X̃; dashed (upper end): max_ij (γX̃_ij + r_X); "
        "dash-dot (−(lower end)): −min_ij (γX̃_ij − r_X), i.e. the envelope of the Lemma 2 "
        "intervals, the lower end negated to share the log axis; dotted: ε_X of Corollary 1. "
        "Means over repetitions, one colour and marker per σ_w.",
    ),
    (
        "fig3",
        fig3,
        ("E2",),
        ("A_hat", "r_A"),
        "Fig. 3: the same for the four γ",
        "As Fig. 2, one colour and marker per γ, at σ_w = 1; below each row, each γ's error "
        "minus that of the smallest γ.",
    ),
    (
        "fig4",
        fig4,
        ("E3", "E4"),
        ("delta_J",),
        "Fig. 4: ΔJ = J_b − J on S",
        "Top: mean ΔJ over repetitions with the band from the 5 % to the 95 % quantile; "
        "middle: each γ's mean minus that of the smallest γ; a bottom panel with the share of "
        "repetitions where Theorem 3's bound is below the exact cost (ΔJ < 0) when there are any.",
    ),
    (
        "fig5",
        fig5,
        ("E4", "E3"),
        ("J_exact",),
        "Fig. 5: cost ratio",
        "r = |mean J_γ − mean J_ref| / mean J_ref with J the exact finite-horizon cost (solid) "
        "and the mean of the per-repetition cost_ratio (dashed); below, each γ's r minus that "
        "of the smallest γ.",
    ),
    (
        "fig_coverage",
        fig_coverage,
        ("E2", "E1"),
        ("coverage_A",),
        "Beyond the paper: empirical coverage of the Lemma 2 intervals",
        "Mean share of the entries of A (B) inside their Lemma 2 interval, with the 1 − δ line.",
    ),
    (
        "fig_certified",
        fig_certified,
        ("E4", "E3"),
        ("certified",),
        "Beyond the paper: share of certified observer gains",
        "Share of repetitions with g(L) < 1 (solid) and with ρ(A − LC) < 1 for the true A "
        "(dashed).",
    ),
    (
        "fig_svr_ols_diff",
        fig_svr_ols_diff,
        ("E2", "E1"),
        ("A_hat",),
        "Beyond the paper: SVR minus OLS on the same data",
        "Mean over repetitions of max_ij |Ã_SVR − Ã_OLS|, per γ and σ_w: where SVR and OLS "
        "really differ.",
    ),
)


def _records_of(exp: dict[str, Any]) -> Columns:
    return as_columns(exp["records"])


def _choose_source(
    experiments: dict[str, dict[str, Any]],
    cols: dict[str, Columns],
    prefer: Sequence[str],
    needs: Sequence[str],
) -> str | None:
    """The first of ``prefer``, then of the others, whose records have every field of
    ``needs``; None when none has (the figure or table is not drawn, and says so)."""
    ordered = [n for n in prefer if n in experiments] + [n for n in experiments if n not in prefer]
    return next((n for n in ordered if all(cols[n].has(f) for f in needs)), None)


def build_report(
    experiments: dict[str, dict[str, Any]],
    provenance: dict[str, Any] | None = None,
    title: str | None = None,
    *,
    render: Callable[[object], Any] | None = None,
) -> Report:
    """``experiments``: name -> {"spec": dict, "records": list|Columns, optional
    "title", "notes" (list[str], e.g. stages that could not run)}.

    ``render``: optional ``fig -> future`` (e.g. ``pool.submit(render_figure, fig)``);
    each figure is handed to it as soon as it is built, so that rendering runs
    elsewhere while the rest is computed; the futures' ``(png, svg)`` are
    collected at the end."""
    builder = ReportBuilder(list(experiments), provenance, title, render=render)
    for name, e in experiments.items():
        builder.add(name, e)
    return builder.finish()


class ReportBuilder:
    """:func:`build_report` in steps, for experiments whose records arrive one
    group at a time: ``add(name, experiment)`` computes that experiment's
    findings and the figures drawn from it (their source is decided from the
    experiment names given up front, as :func:`build_report` decides it);
    ``finish()`` returns the :class:`Report`, the same as :func:`build_report`
    on all experiments."""

    def __init__(
        self,
        names: Iterable[str],
        provenance: dict[str, Any] | None = None,
        title: str | None = None,
        *,
        render: Callable[[object], Any] | None = None,
    ) -> None:
        self.names = list(names)
        self.provenance = provenance
        self.title = title
        self.render = render
        self.experiments: dict[str, dict[str, Any]] = {}
        self.cols: dict[str, Columns] = {}
        self.exps: dict[str, dict[str, Any]] = {}
        self.figs: dict[int, tuple[ReportFigure, Any]] = {}
        self.not_drawn: list[tuple[str, str]] = []  # (figure title, why)

    def _source(self, prefer: Sequence[str], needs: Sequence[str], final: bool) -> str | None:
        for name in prefer:
            if name in self.names:
                return name
        if not final:
            return None  # decided on the data, once every experiment is there
        ordered = {n: self.experiments[n] for n in self.names if n in self.experiments}
        return _choose_source(ordered, self.cols, prefer, needs)

    def _figures(self, final: bool) -> None:
        for i, (name, fn, prefer, needs, ftitle, caption) in enumerate(FIGURE_PLAN):
            if i in self.figs:
                continue
            src = self._source(prefer, needs, final)
            if src is None or src not in self.experiments:
                if final:
                    self.not_drawn.append((ftitle, f"no experiment here has {', '.join(needs)}"))
                continue
            fig = fn(
                self.cols[src],
                self.experiments[src].get("spec"),
                experiment=_exp_label(src, self.provenance),
            )
            fut = self.render(fig) if self.render is not None else None
            self.figs[i] = (ReportFigure(name, ftitle, caption, src, fig), fut)

    def add(self, name: str, e: dict[str, Any]) -> None:
        self.experiments[name] = e
        self.cols[name] = _records_of(e)
        self._figures(final=False)
        self.exps[name] = {
            "title": e.get("title") or EXPERIMENTS.get(name, {}).get("title", name),
            "paper": EXPERIMENTS.get(name, {}).get("paper"),
            "spec": e.get("spec"),
            "n_records": len(self.cols[name]),
            "notes": list(e.get("notes") or []),
            "findings": [f"[no data] {n}" for n in (e.get("notes") or [])]
            + findings(
                self.cols[name],
                e.get("spec"),
                **({"topics": EXPERIMENTS[name]["findings"]} if _topics(name) else {}),
            ),
        }

    def finish(self) -> Report:
        self._figures(final=True)
        experiments = {n: self.experiments[n] for n in self.names if n in self.experiments}
        # the audit's figure first: it renders while the others are awaited
        audit, a_findings, a_sources, a_fig = self._audit(experiments)
        t_src = _choose_source(experiments, self.cols, ("E1",), ("rmse_A",))
        rows = table2(self.cols[t_src], spec=experiments[t_src].get("spec")) if t_src else []
        figs: list[ReportFigure] = []
        for fg, fut in [self.figs[i] for i in sorted(self.figs)] + ([a_fig] if a_fig else []):
            if fut is not None:
                fg.set_rendered(*fut.result())
            figs.append(fg)
        return Report(
            title=self.title or f"Reproduction of the paper's Section 6 ({PRESET_NAME})",
            experiments={n: self.exps[n] for n in experiments},
            table2=rows,
            table2_source=t_src,
            figures=figs,
            provenance=dict(self.provenance or {}),
            audit=audit,
            audit_findings=a_findings,
            audit_sources=a_sources,
            figures_not_drawn=list(self.not_drawn),
        )

    def _audit(
        self, experiments: dict[str, dict[str, Any]]
    ) -> tuple[list[dict[str, Any]], list[str], dict[str, str], tuple[ReportFigure, Any] | None]:
        """The uncertainty-set audit when two or more bounds_methods ran: its rows,
        findings, sources and figure (with its render's future, if rendered elsewhere)."""
        sources = audit_sources(experiments, self.cols)
        if len(sources) < 2:
            return [], [], {}, None
        cols = {m: self.cols[n] for m, n in sources.items()}
        meta = spec_meta(experiments[next(iter(sources.values()))].get("spec"))
        rows = audit_rows(cols, meta.delta)
        label = " + ".join(f"{n} ({m})" for m, n in sources.items())
        fig = fig_bounds_audit(
            cols, meta.delta, experiment=_exp_label(label, self.provenance), seed=meta.seed
        )
        caption = (
            "Top: share of records with every entry of A and of B inside the method's box "
            "(linear axis), with the 1 − δ line; bottom: mean largest radius r_A (log axis). "
            "σ_w = 1; one colour and marker per bounds_method; SVR at the table's γ solid "
            "with small filled markers, OLS dashed with large open markers. The paper's box "
            "is centred at (1+γ)Ã, the others at the estimate."
        )
        fg = ReportFigure(
            "fig_bounds_audit",
            "Beyond the paper: coverage and width of the uncertainty sets per bounds_method",
            caption,
            " + ".join(sources.values()),
            fig,
        )
        fut = None if self.render is None else self.render(fig)
        return rows, audit_findings(rows, meta.delta), dict(sources), (fg, fut)


def _topics(name: str) -> bool:
    return "findings" in EXPERIMENTS.get(name, {})


def _exp_label(name: str, provenance: dict[str, Any] | None) -> str:
    preset = (provenance or {}).get("preset")
    return f"{preset} / {name}" if preset else name
