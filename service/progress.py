"""The CLI's progress bar, :func:`svrobs_cli.progress.progress_bar`, under the name
``service.reports.reproduce`` imports."""

from svrobs_cli.progress import progress_bar

__all__ = ["progress_bar"]
