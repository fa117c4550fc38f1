"""The report page renderer, :mod:`svrobs_lab.report_html`, under the name
``service.reports.reproduce`` imports."""

from svrobs_lab.report_html import job_report_html, render_html, report_css

__all__ = ["job_report_html", "render_html", "report_css"]
