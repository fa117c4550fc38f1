"""The report as one self-contained HTML page (``report.html``, ``GET /jobs/{id}/report``).

The core builds the :class:`~svrobs_core.report.Report` (findings, Table 2,
figure bytes); this module renders it, with the stylesheet ``report.css``
shipped beside it as package data.
"""

from __future__ import annotations

import base64
import html
import json
from functools import cache
from importlib.resources import files

from svrobs_core.report import Report, build_report, spec_json, table2_markdown
from svrobs_core.report.audit import audit_markdown
from svrobs_core.report.columns import fmt_num

# The layout of the page :func:`job_report_html` gives for a job's rows, stored with
# each stored report (``job_reports.layout``). Raise it whenever a change (here, in
# report.css or in svrobs_core.report) alters the page a job's rows give: a stored
# report of another layout is then built again from the job's rows, at its next
# request or by beat's report thread (a job whose rows were pruned keeps its own).
REPORT_LAYOUT = 2


def _table(name: str) -> str:
    """The start of a table. A table, like a spec's <pre>, scrolls sideways inside
    itself on a narrow screen (report.css), so it takes the focus (its overflow can
    be scrolled with the keyboard) and has a name (what a screen reader says there)."""
    return f"<table tabindex='0' aria-label='{html.escape(name, quote=True)}'>"


def _scrolled_pre(name: str, text: str) -> str:
    """Preformatted text that scrolls inside itself: a focusable, named region."""
    label = html.escape(name, quote=True)
    return f"<pre tabindex='0' role='region' aria-label='{label}'>{html.escape(text)}</pre>"


@cache
def report_css() -> str:
    """The page's stylesheet (``svrobs_lab/report.css``)."""
    return files(__package__).joinpath("report.css").read_text(encoding="utf-8")


_STATUS_CLASS = {
    "[holds]": "holds",
    "[does not hold]": "nothold",
    "[partly]": "partly",
    "[no data]": "nodata",
    "[info]": "",
}


def _html_finding(f: str) -> str:
    for tag, cls in _STATUS_CLASS.items():
        if f.startswith(tag):
            rest = html.escape(f[len(tag) :])
            return f'<li><span class="{cls}">{html.escape(tag)}</span>{rest}</li>'
    return f"<li>{html.escape(f)}</li>"


def _markdown_table(md: str, name: str) -> str:
    """A pipe table (header, rule, rows) as an HTML table named ``name``."""
    lines = [ln.strip().strip("|") for ln in md.strip().splitlines()]
    rows = [[c.strip() for c in ln.split(" | ")] for ln in lines[:1] + lines[2:]]
    out = [_table(name) + "<tr>" + "".join(f"<th>{html.escape(c)}</th>" for c in rows[0]) + "</tr>"]
    for r in rows[1:]:
        out.append("<tr>" + "".join(f"<td>{html.escape(c)}</td>" for c in r) + "</tr>")
    return "".join(out) + "</table>"


def render_html(report: Report, figure_src: dict[str, str] | None = None) -> str:
    """The report as one HTML page; figures embedded as base64 PNG unless
    ``figure_src`` maps figure names to URLs."""
    e = html.escape
    H = [
        "<!DOCTYPE html>",
        "<html lang='en'><head><meta charset='utf-8'>"
        "<meta name='viewport' content='width=device-width, initial-scale=1'>",
        f"<title>{e(report.title)}</title><style>\n{report_css()}</style></head><body>",
        f"<h1>{e(report.title)}</h1>",
        "<p>Every number below comes from the records of this run (and, for the true system "
        "matrices, from its specs), except the cells marked <span class='pub'>published</span>, "
        "which are the paper's own Table 2 values.</p>",
        _table("Experiments") + "<tr><th>Experiment</th><th>What</th><th>Records</th></tr>",
    ]
    for name, x in report.experiments.items():
        H.append(f"<tr><td>{e(name)}</td><td>{e(x['title'])}</td><td>{x['n_records']}</td></tr>")
    H.append("</table>")
    H.append("<h2>Findings: where the paper's claims hold here and where they do not</h2>")
    for name, x in report.experiments.items():
        H.append(f"<h3>{e(name)}: {e(x['title'])}</h3><ul>")
        H += [_html_finding(f) for f in x["findings"]]
        H.append("</ul>")
    H.append("<h2>Table 2: RMSE, ours beside the paper's published values</h2>")
    if report.table2:
        H.append(f"<p>Source: experiment {e(str(report.table2_source))}.</p>")
        H.append(
            _table("Table 2") + "<tr><th>System</th><th>σ_w</th><th>Matrix</th><th>OLS (ours)</th>"
            "<th>SVR (ours)</th><th class='pub'>OLS (paper, published)</th>"
            "<th class='pub'>\"Ours\" SVR (paper, published)</th><th>OLS ours/paper</th>"
            "<th>SVR ours/paper</th><th>SVR − OLS (ours)</th></tr>"
        )
        for r in report.table2:
            H.append(
                f"<tr><td>{e(r['system'])}</td><td>{fmt_num(r['sigma_w'])}</td><td>{r['matrix']}</td>"
                f"<td>{fmt_num(r['ols'])}</td><td>{fmt_num(r['svr'])}</td>"
                f"<td class='pub'>{fmt_num(r['paper_ols'])}</td>"
                f"<td class='pub'>{fmt_num(r['paper_ours'])}</td>"
                f"<td>{fmt_num(r['ratio_ols'], 3)}</td><td>{fmt_num(r['ratio_svr'], 3)}</td>"
                f"<td>{fmt_num(r['svr_minus_ols'], 3)}</td></tr>"
            )
        H.append("</table>")
        note = table2_markdown(report.table2).strip().splitlines()[-1]
        H.append(f"<p>{e(note)}</p>")
    else:
        H.append("<p>No data for Table 2.</p>")
    if report.audit:
        H.append("<h2>Beyond the paper: uncertainty sets that hold (bounds_method)</h2><ul>")
        H += [_html_finding(f) for f in report.audit_findings]
        H.append("</ul>")
        audit = audit_markdown(report.audit, report.audit[0]["delta"])
        H.append(_markdown_table(audit, "Uncertainty sets"))
    H.append("<h2>Figures</h2>")
    for fg in report.figures:
        H.append(f"<h3>{e(fg.title)}</h3>")
        if not fg.empty:  # an empty figure is its note only
            src = (figure_src or {}).get(fg.name)
            if src is None:
                src = "data:image/png;base64," + base64.b64encode(fg.png()).decode("ascii")
            H.append(f"<img alt='{e(fg.title)}' src='{e(src)}'>")
        H.append(f"<p>{e(fg.full_caption)} Data: experiment {e(fg.experiment)}.</p>")
    H += [f"<p>Not drawn: {e(title)} ({e(why)}).</p>" for title, why in report.figures_not_drawn]
    H.append("<h2>Specs</h2>")
    for name, x in report.experiments.items():
        H.append(f"<h3>{e(name)}</h3>" + _scrolled_pre(f"Spec of {name}", spec_json(x["spec"])))
    H.append(f"<h2>Provenance</h2>{_table('Provenance')}<tr><th>Key</th><th>Value</th></tr>")
    for k, v in report.provenance.items():
        val = v if isinstance(v, str) else json.dumps(v)
        H.append(f"<tr><td>{e(str(k))}</td><td style='text-align:left'>{e(str(val))}</td></tr>")
    H.append("</table></body></html>")
    return "\n".join(H)


def job_report_html(
    spec: dict, records, provenance: dict | None = None, name: str = "job", *, render=None
) -> str:
    """One job's spec and records -> a self-contained HTML report (for the REST route).
    ``render``: :func:`~svrobs_core.report.build_report`'s hook (e.g. the figures drawn
    by helper processes: :mod:`svrobs_lab.figure_pool`)."""
    rep = build_report(
        {name: {"spec": spec, "records": records, "title": f"Job {name}"}},
        provenance=provenance,
        title=f"svrobs report: {name}",
        render=render,
    )
    return render_html(rep)
