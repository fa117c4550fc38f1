"""The report as Markdown (``report.md``): experiments, findings, Table 2,
figures by file name, specs and provenance."""

from __future__ import annotations

import json
from typing import Any

from .audit import audit_markdown
from .build import Report
from .tables import table2_markdown


def spec_json(spec: Any) -> str:
    """A spec as JSON with one top-level field per line (valid JSON)."""
    if not isinstance(spec, dict):
        return json.dumps(spec)
    items = [f" {json.dumps(k)}: {json.dumps(v)}" for k, v in spec.items()]
    return "{\n" + ",\n".join(items) + "\n}"


def _md_escape(s: str) -> str:
    return s.replace("|", "\\|")


def render_markdown(report: Report, figure_files: dict[str, str] | None = None) -> str:
    """The report as Markdown; figures referenced by file name (``<name>.png``,
    with links to ``<name>.svg``, ``.pdf`` and the plotted data ``.csv``) unless
    ``figure_files`` maps names to paths. An empty figure is its note only."""
    L = [f"# {report.title}", ""]
    L.append(
        "Every number below comes from the records of this run (and, for the true "
        "system matrices, from its specs), except the columns marked *published*, which "
        "are the paper's own Table 2 values."
    )
    L.append("")
    L.append("| Experiment | What | Records |")
    L.append("|---|---|---|")
    for name, e in report.experiments.items():
        L.append(f"| {name} | {_md_escape(e['title'])} | {e['n_records']} |")
    L += ["", "## Findings: where the paper's claims hold here and where they do not", ""]
    for name, e in report.experiments.items():
        L.append(f"### {name}: {e['title']}")
        L.append("")
        for f in e["findings"]:
            L.append(f"- {f}")
        L.append("")
    L += ["## Table 2: RMSE, ours beside the paper's published values", ""]
    if report.table2:
        L.append(f"Source: experiment {report.table2_source}.")
        L.append("")
        L.append(table2_markdown(report.table2))
    else:
        L.append("No data for Table 2.")
        L.append("")
    if report.audit:
        L += ["## Beyond the paper: uncertainty sets that hold (bounds_method)", ""]
        L.append(
            "The same grid with the paper's intervals and with the sound sets of "
            "docs/uncertainty.md (experiments: "
            + ", ".join(f"{m}: {n}" for m, n in report.audit_sources.items())
            + "). Coverage is measured against the true system; 'all inside' is the share "
            "of records with every entry of A and of B in its interval at once, which is "
            "what a box claiming probability ≥ 1 − δ must reach."
        )
        L.append("")
        L += [f"- {f}" for f in report.audit_findings]
        L.append("")
        L.append(audit_markdown(report.audit, report.audit[0]["delta"]))
    L += ["## Figures", ""]
    for fg in report.figures:
        L.append(f"### {fg.title}")
        L.append("")
        if fg.empty:  # nothing to plot: the note says why
            L.append(f"{fg.full_caption} Data: experiment {fg.experiment}.")
            L.append("")
            continue
        png = (figure_files or {}).get(fg.name, f"{fg.name}.png")
        stem = png[:-4] if png.endswith(".png") else None
        links = f" [SVG]({stem}.svg) · [PDF]({stem}.pdf) · [data (CSV)]({stem}.csv)" if stem else ""
        L.append(f"![{fg.title}]({png})")
        L.append("")
        L.append(f"{fg.full_caption} Data: experiment {fg.experiment}." + links)
        L.append("")
    L += [f"- Not drawn: {title} ({why})." for title, why in report.figures_not_drawn]
    if report.figures_not_drawn:
        L.append("")
    L += ["## Specs", ""]
    for name, e in report.experiments.items():
        L.append(f"### {name}" + (f" (paper: {e['paper']})" if e.get("paper") else ""))
        L.append("")
        L.append("```json")
        L.append(spec_json(e["spec"]))
        L.append("```")
        L.append("")
    L += ["## Provenance", "", "| Key | Value |", "|---|---|"]
    for k, v in report.provenance.items():
        val = v if isinstance(v, str) else json.dumps(v)
        L.append(f"| {k} | {_md_escape(str(val))} |")
    L.append("")
    return "\n".join(L)
