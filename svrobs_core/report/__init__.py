"""Tables, figures, findings and the Markdown report, from records (docs/spec.md#record-fields).

Pure: records (or :class:`Columns` built from them) in; rows, strings,
matplotlib ``Figure`` objects and bytes out. Nothing here writes files or
touches the network. Figures are rendered headless with the Agg canvas. The
HTML page is rendered by the service (``svrobs_lab.report_html``).

Every number shown comes from the records (and the spec that produced them).
The only typed-in numbers are the paper's *published* values of
``svrobs_core.paper`` (``PUBLISHED_TABLE2``, ``PUBLISHED_CLAIMS``), shown
beside ours and labelled as published.

Modules, in the order a report is made:

* ``columns``: :class:`Columns` (the records as arrays), spec metadata,
  selection, grouping and formatting helpers.
* ``tables``: ``table2(records, gamma=None)``, ``table2_markdown``, ``table2_csv``.
* ``derived``: per-record quantities, ``first_stable_certified``, ``cost_ratio_of_means``.
* ``style``: the one figure style (print sizes, fonts ≥ 8 pt, Okabe-Ito palette,
  line styles and markers), ``figure_style()``.
* ``series``: ``FIGURE_SERIES``, what each figure plots (field, statistic,
  grouping, band, difference reference), shared with the dashboard's charts:
  ``summary_lines(groups, row, summary_context(groups, spec))`` gives a row's
  curves from stored summaries, the same as the figures draw from the records.
* ``plotting``: figure plumbing, ``figure_bytes(fig, fmt="png" | "svg" | "pdf")``,
  ``figure_csv(fig)`` (the plotted data).
* ``figures``: ``fig_rmse``, ``fig_coverage``, ``fig_svr_ols_diff``;
  ``entry_figures``: ``fig2``, ``fig3``; ``cost_figures``: ``fig4``, ``fig5``,
  ``fig_certified``;
  each ``f(records, spec=None, *, experiment=...) -> matplotlib.figure.Figure``;
  ``audit``: the uncertainty-set audit (rows, findings, ``fig_bounds_audit``).
* ``findings``: ``findings(records, spec) -> list[str]``.
* ``report_figure``: ``ReportFigure`` (a figure of the report and its files),
  ``FigureJob`` (a figure function and its arguments, to build here or in another
  process), ``draw_png`` / ``draw_files`` (build and draw a job -> ``Drawn``).
* ``column_wire``: how ``Columns`` travel to another process (narrowed, codes packed).
* ``build``: ``build_report(experiments, provenance=...)``, ``ReportBuilder``, ``Report``.
* ``markdown``: ``render_markdown(report)``, ``spec_json(spec)``.
"""

from ..records import COLUMN_MATRIX_FIELDS, REPORT_FIELDS, SCALAR_FIELDS, TEXT_FIELDS
from .audit import fig_bounds_audit
from .build import (
    FIGURE_PLAN,
    Report,
    ReportBuilder,
    build_report,
)
from .columns import STAGE_FIELDS, Columns, as_columns
from .cost_figures import fig4, fig5, fig_certified
from .derived import cost_ratio_of_means, first_stable_certified, svr_ols_diff
from .entry_figures import fig2, fig3
from .figure_files import figure_bytes
from .figures import fig_coverage, fig_rmse, fig_svr_ols_diff
from .findings import findings
from .markdown import render_markdown, spec_json
from .plotting import figure_csv
from .report_figure import Drawn, FigureJob, ReportFigure, draw_files, draw_png
from .series import (
    FIGURE_SERIES,
    FigureSeries,
    figure_series,
    figure_series_json,
    summary_context,
    summary_lines,
)
from .style import figure_style
from .tables import TABLE2_COLUMNS, table2, table2_csv, table2_markdown

__all__ = [
    "COLUMN_MATRIX_FIELDS",
    "FIGURE_PLAN",
    "FIGURE_SERIES",
    "FigureSeries",
    "REPORT_FIELDS",
    "SCALAR_FIELDS",
    "STAGE_FIELDS",
    "TABLE2_COLUMNS",
    "TEXT_FIELDS",
    "Columns",
    "Drawn",
    "FigureJob",
    "Report",
    "ReportBuilder",
    "ReportFigure",
    "as_columns",
    "build_report",
    "cost_ratio_of_means",
    "draw_files",
    "draw_png",
    "fig2",
    "fig3",
    "fig4",
    "fig5",
    "fig_bounds_audit",
    "fig_certified",
    "fig_coverage",
    "fig_rmse",
    "fig_svr_ols_diff",
    "figure_bytes",
    "figure_csv",
    "figure_series",
    "figure_series_json",
    "figure_style",
    "findings",
    "first_stable_certified",
    "render_markdown",
    "spec_json",
    "summary_context",
    "summary_lines",
    "svr_ols_diff",
    "table2",
    "table2_csv",
    "table2_markdown",
]
