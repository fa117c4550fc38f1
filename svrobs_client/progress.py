"""Progress bars for :meth:`Client.wait`: rich in a terminal, ``tqdm.auto`` (widgets)
or rich in a Jupyter notebook, nothing when stderr is not a terminal. Both libraries
are optional; without them the client waits silently."""

from __future__ import annotations

import sys
from typing import Any, Protocol


class Bar(Protocol):
    def update(self, done: int, total: int, status: str) -> None: ...
    def close(self) -> None: ...


class NoBar:
    def update(self, done: int, total: int, status: str) -> None:
        pass

    def close(self) -> None:
        pass


class RichBar:
    """A rich progress bar (renders in a terminal and, through IPython, in Jupyter)."""

    def __init__(self, job_id: int, total: int, status: str, *, console: Any = None):
        from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

        self._bar = Progress(
            TextColumn("job {task.fields[job]} {task.fields[status]}"),
            BarColumn(),
            TextColumn("{task.completed}/{task.total} units"),
            TimeElapsedColumn(),
            console=console,
        )
        self._bar.start()
        self._task = self._bar.add_task("job", total=total or 1, job=job_id, status=status)

    def update(self, done: int, total: int, status: str) -> None:
        self._bar.update(self._task, completed=done, total=total or 1, status=status)

    def close(self) -> None:
        self._bar.stop()


class TqdmBar:
    """A ``tqdm.auto`` bar: an ipywidgets bar in a notebook, text in a terminal."""

    def __init__(self, job_id: int, total: int, status: str, *, file: Any = None):
        from tqdm.auto import tqdm

        self._job = job_id
        self._bar = tqdm(total=total or 1, desc=f"job {job_id} {status}", unit="unit", file=file)

    def update(self, done: int, total: int, status: str) -> None:
        self._bar.total = total or 1
        self._bar.n = done
        self._bar.set_description(f"job {self._job} {status}", refresh=False)
        self._bar.refresh()

    def close(self) -> None:
        self._bar.close()


def in_notebook() -> bool:
    """True inside a Jupyter kernel (IPython already imported, a ZMQ shell)."""
    ipython = sys.modules.get("IPython")
    if ipython is None:
        return False
    shell = getattr(ipython, "get_ipython", lambda: None)()
    return type(shell).__name__ == "ZMQInteractiveShell"


def _importable(name: str) -> bool:
    import importlib.util

    return importlib.util.find_spec(name) is not None


def make_bar(job_id: int, total: int, status: str, *, enabled: bool = True) -> Bar:
    """The bar that fits where the code runs (see the module docstring)."""
    if not enabled:
        return NoBar()
    if in_notebook():
        kinds = ("tqdm", "rich")
    elif sys.stderr is not None and sys.stderr.isatty():
        kinds = ("rich", "tqdm")
    else:
        return NoBar()
    for kind in kinds:
        if kind == "tqdm" and _importable("tqdm"):
            return TqdmBar(job_id, total, status)
        if kind == "rich" and _importable("rich"):
            from rich.console import Console

            return RichBar(job_id, total, status, console=Console(stderr=True))
    return NoBar()
