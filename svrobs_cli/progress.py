"""The one progress bar of in-process runs (``svrobs run-local``, ``svrobs reproduce``)."""

from __future__ import annotations

from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TimeElapsedColumn


def progress_bar(console: Console, *, quiet: bool) -> Progress:
    """A rich bar with description, count and elapsed time; inert when ``quiet``."""
    return Progress(
        "[progress.description]{task.description}",
        BarColumn(),
        MofNCompleteColumn(),
        TimeElapsedColumn(),
        console=console,
        disable=quiet,
        transient=False,
    )
