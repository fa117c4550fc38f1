"""The whole report: which figure is drawn from which experiment, findings per
experiment and Table 2, assembled into a :class:`Report` (all at once with
:func:`build_report`, or as experiments arrive with :class:`ReportBuilder`)."""

from __future__ import annotations

from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from typing import Any

from ..paper import EXPERIMENTS, PRESET_NAME
from .audit import audit_findings, audit_rows, audit_sources, fig_bounds_audit
from .columns import Columns, as_columns, spec_meta
from .cost_figures import fig4, fig5, fig_certified
from .entry_figures import fig2, fig3
from .figures import fig_coverage, fig_rmse, fig_svr_ols_diff
from .findings import findings
from .report_figure import FigureFn, FigureJob, ReportFigure
from .tables import table2


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


# The fields each figure reads (of its Columns), on any of its branches: all that is
# sent with it to a helper process (:class:`~.report_figure.FigureJob`). Reading
# another field there is a KeyError, and the figure is then built from all the
# fields in the building process; tests/core/test_report_figure.py checks every
# figure on records of several shapes.
# Every figure reads the cells' key, and their notes where a panel has no data.
_KEY = ("system", "sigma_w", "N", "N0", "estimator", "gamma", "rep", "notes")
_BOXES = ("A_hat", "B_hat", "eps_A", "eps_B", "r_A", "r_B", "stable_certified", "rmse_A")
FIGURE_FIELDS: dict[str, tuple[str, ...]] = {
    "fig_rmse": (*_KEY, "rmse_A", "rmse_B"),
    "fig2": (*_KEY, *_BOXES),
    "fig3": (*_KEY, *_BOXES),
    "fig4": (*_KEY, "delta_J", "J_bound", "J_exact"),
    "fig5": (*_KEY, "J_exact", "cost_ratio"),
    "fig_coverage": (*_KEY, "coverage_A", "coverage_B"),
    "fig_certified": (*_KEY, "certified", "rho_true", "stable_certified"),
    "fig_svr_ols_diff": (*_KEY, "A_hat", "rmse_A"),
    "fig_bounds_audit": (*_KEY, "coverage_A", "coverage_B", "r_A", "r_B"),
}


# The order in which the figures are handed to ``render``: the slowest to draw first,
# so that the last to finish is a short one (docs/performance.md#figures-drawn-beside-the-build).
# On the 625,050-cell job of bench/report_build.py the coverage figure takes 0.45-0.6 s
# (12 panels), fig_rmse 0.3 s, fig5 0.2 s, the others 0.15 s; on the reduced preset
# fig2 and fig3 take 0.25 s. The figures not named follow in the plan's order.
DRAW_FIRST = ("fig_coverage", "fig2", "fig3", "fig_rmse", "fig5")


_FIRST = {name: k for k, name in enumerate(DRAW_FIRST)}
# the plan's indices in that order
DRAW_ORDER = sorted(
    range(len(FIGURE_PLAN)), key=lambda i: _FIRST.get(FIGURE_PLAN[i][0], len(_FIRST))
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
    *,
    provenance: dict[str, Any] | None = None,
    title: str | None = None,
    render: Callable[[FigureJob], Any] | None = None,
) -> Report:
    """``experiments``: name -> {"spec": dict, "records": list|Columns, optional
    "title", "notes" (list[str], e.g. stages that could not run)}.

    ``render``: optional ``job -> future`` (e.g. ``pool.submit(draw_files, job)``);
    each figure's :class:`~.report_figure.FigureJob` is handed to it as soon as its
    experiment is there, so that the figure is built and drawn elsewhere while the
    rest is computed; the futures' :class:`~.report_figure.Drawn` are collected at
    the end. Without it each figure is built and drawn here at its first use."""
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
        render: Callable[[FigureJob], Any] | None = None,
    ) -> None:
        self.names = list(names)
        self.provenance = provenance
        self.title = title
        self.render = render
        self.experiments: dict[str, dict[str, Any]] = {}
        self.cols: dict[str, Columns] = {}
        self.exps: dict[str, dict[str, Any]] = {}
        self.figs: dict[int, tuple[ReportFigure, Any]] = {}
        self.not_drawn: dict[int, tuple[str, str]] = {}  # plan index -> (figure title, why)

    def _source(self, prefer: Sequence[str], needs: Sequence[str], final: bool) -> str | None:
        for name in prefer:
            if name in self.names:
                return name
        if not final:
            return None  # decided on the data, once every experiment is there
        ordered = {n: self.experiments[n] for n in self.names if n in self.experiments}
        return _choose_source(ordered, self.cols, prefer, needs)

    def _figures(self, final: bool) -> None:
        for i in DRAW_ORDER:
            name, fn, prefer, needs, ftitle, caption = FIGURE_PLAN[i]
            if i in self.figs:
                continue
            src = self._source(prefer, needs, final)
            if src is None or src not in self.experiments:
                if final:
                    self.not_drawn[i] = (ftitle, f"no experiment here has {', '.join(needs)}")
                continue
            job = FigureJob(
                fn,
                (self.cols[src], self.experiments[src].get("spec")),
                {"experiment": _exp_label(src, self.provenance)},
                FIGURE_FIELDS.get(name),
            )
            fut = self.render(job) if self.render is not None else None
            self.figs[i] = (ReportFigure(name, ftitle, caption, src, job), fut)

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
                fg.set_drawn(fut.result())
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
            figures_not_drawn=[self.not_drawn[i] for i in sorted(self.not_drawn)],
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
        job = FigureJob(
            fig_bounds_audit,
            (cols, meta.delta),
            {"experiment": _exp_label(label, self.provenance), "seed": meta.seed},
            FIGURE_FIELDS["fig_bounds_audit"],
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
            job,
        )
        fut = None if self.render is None else self.render(job)
        return rows, audit_findings(rows, meta.delta), dict(sources), (fg, fut)


def _topics(name: str) -> bool:
    return "findings" in EXPERIMENTS.get(name, {})


def _exp_label(name: str, provenance: dict[str, Any] | None) -> str:
    preset = (provenance or {}).get("preset")
    return f"{preset} / {name}" if preset else name
