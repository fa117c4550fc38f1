"""A report's figures drawn as PNG in helper processes while the build goes on
(docs/performance.md#figures-drawn-beside-the-build).

matplotlib draws in Python, holding the GIL: threads cannot share a report's
drawing, and building and drawing its five figures is most of a build. A process
that builds reports keeps a small pool of helpers
(``SVROBS_REPORT_RENDER_PROCESSES``, 0: none), started by a forkserver that has
matplotlib imported, at its first report. Each figure's job (its function and the
few columns it reads: ``svrobs_core.report.FigureJob``) is handed to the pool as
soon as its experiment is read (``build_report``'s ``render`` hook) and built and
drawn there, byte for byte the PNG this process would draw, while this process
computes the findings and tables.

A helper that fails (killed, out of memory, a job that cannot be pickled or that
reads a field it was not sent) or takes longer than ``DRAW_TIMEOUT_SECONDS`` costs
nothing but time: the figure is built and drawn here instead (and a pool with a
helper gone or late is replaced at the next report). A process that
may not have children (a daemon, such as a Celery pool process) draws its own.
"""

from __future__ import annotations

import logging
import multiprocessing as mp
import os
import pickle
import signal
import threading
from concurrent.futures import BrokenExecutor, Future, ProcessPoolExecutor
from multiprocessing.connection import Connection
from typing import TYPE_CHECKING, Any

from svrobs_core.report import Drawn, FigureJob, draw_png

if TYPE_CHECKING:
    from collections.abc import Callable

log = logging.getLogger(__name__)

# A figure not back from its helper by then is drawn in this process.
DRAW_TIMEOUT_SECONDS = 60.0
# What the forkserver imports once, so that a new helper starts drawing at once.
PRELOAD = ["matplotlib.figure", "matplotlib.backends.backend_agg", "svrobs_core.report"]

_lock = threading.Lock()
_pool: ProcessPoolExecutor | None = None
_size = 0
_processes = 0  # this process's setting: configure()
# The pipe by which the helpers see this process end: they hold its read end, only
# this process its write end (see _watch_owner).
_lifeline: tuple[int, int] | None = None


class DrawnFigure:
    """A figure's :class:`Drawn` as ``ReportFigure.set_drawn`` takes it: from its
    helper, or built and drawn here (by ``draw``) when the helper failed. ``timed``:
    a result not back within ``DRAW_TIMEOUT_SECONDS`` counts as failed (False: waited
    for, as in a pool whose figures queue behind other work)."""

    def __init__(
        self,
        job: FigureJob,
        future: Future[Any] | None,
        pool: ProcessPoolExecutor | None,
        *,
        draw: Callable[[FigureJob], Drawn] = draw_png,
        timed: bool = True,
    ):
        self._job, self._future, self._pool = job, future, pool
        self._draw, self._timed = draw, timed

    def result(self) -> Drawn:
        future, self._future = self._future, None
        if future is not None:
            try:
                out: Drawn = future.result(timeout=DRAW_TIMEOUT_SECONDS if self._timed else None)
                return out
            except Exception as exc:  # noqa: BLE001 - any failure: draw it here
                why = f"{type(exc).__name__}: {exc}"
                log.warning("a report figure's helper failed (%s): drawn in process", why)
                if isinstance(exc, (BrokenExecutor, TimeoutError)):  # gone or stuck
                    _discard(self._pool)  # new helpers at the next report
                # a broken pool's futures share one exception, whose traceback would
                # keep this frame (and the columns) until the next gc pass
                exc.__traceback__ = None
            future = None
        return self._draw(self._job)


def configure(processes: int) -> None:
    """How many helpers this process's reports use: set by each front end that builds
    reports (the API app, beat) from ``SVROBS_REPORT_RENDER_PROCESSES``; 0 until then."""
    global _processes
    _processes = max(0, int(processes))


def figure_renderer(processes: int | None = None) -> Callable[[FigureJob], DrawnFigure] | None:
    """``build_report``'s ``render`` hook drawing on this process's pool of
    ``processes`` helpers (default: as configured); None (draw in process) for 0 or
    in a daemon process."""
    processes = _processes if processes is None else processes
    if processes <= 0 or mp.current_process().daemon:
        return None

    def render(job: FigureJob) -> DrawnFigure:
        pool = _get(processes)
        if pool is None:
            return DrawnFigure(job, None, None)
        try:  # here, so that the pool never holds the job's whole columns
            wire = pickle.dumps(job, protocol=pickle.HIGHEST_PROTOCOL)
        except Exception as exc:  # noqa: BLE001 - e.g. a lambda among its arguments
            why = f"{type(exc).__name__}: {exc}"
            log.warning("a report figure could not be sent to a helper (%s): drawn in process", why)
            return DrawnFigure(job, None, None)
        try:
            return DrawnFigure(job, pool.submit(_draw_sent, wire), pool)
        except Exception as exc:  # noqa: BLE001 - a broken or stopped pool: draw here
            why = f"{type(exc).__name__}: {exc}"  # not the exception: its frames hold the job
            log.warning("report figures could not be handed to helpers (%s)", why)
            _discard(pool)
            return DrawnFigure(job, None, None)

    return render


def _draw_sent(wire: bytes) -> Drawn:
    """In a helper: the pickled job built and drawn."""
    job: FigureJob = pickle.loads(wire)
    return draw_png(job)


def warm(processes: int) -> bool:
    """Start this process's helpers now and have each draw a small figure (fonts and
    mathtext loaded), rather than at the first report; False when there are none."""
    if figure_renderer(processes) is None:
        return False
    pool = _get(processes)
    if pool is None:
        return False
    try:
        for f in [pool.submit(_draw_sample) for _ in range(processes)]:
            f.result(timeout=DRAW_TIMEOUT_SECONDS)
    except Exception as exc:  # noqa: BLE001 - the first report draws in process instead
        log.warning("report figure helpers did not start (%s)", exc)
        _discard(pool)
        return False
    return True


def _draw_sample() -> int:
    """In a helper: one panel in the report's style, with a log axis' mathtext labels."""
    from svrobs_core.report.plotting import new_figure, panel_title
    from svrobs_core.report.style import figure_style

    with figure_style():
        fig, axes = new_figure(1, 1, (3.0, 2.0))
        axes[0, 0].loglog([1, 10, 100], [1e-3, 1e-2, 1e-1])
        panel_title(axes[0, 0], "γ σ_w")
    return len(draw_png(fig).png)


def close() -> None:
    """Stop this process's helpers, letting a draw in progress finish, and free the
    pool (its queues' semaphores). For an orderly stop of a process that may end
    without running its exit handlers: uvicorn ends the API process by the signal
    that stopped it, once its shutdown is done."""
    global _pool
    with _lock:
        pool, _pool = _pool, None
    if pool is not None:
        pool.shutdown(wait=True, cancel_futures=True)


def helper_pids() -> list[int]:
    """The process ids of this process's helpers (none before its first report)."""
    with _lock:
        procs = getattr(_pool, "_processes", None) or {}
        return list(procs)


def _get(processes: int) -> ProcessPoolExecutor | None:
    global _pool, _size
    with _lock:
        if _pool is not None and _size == processes:
            return _pool
        old, _pool = _pool, None
        if old is not None:
            old.shutdown(wait=False, cancel_futures=True)
        try:
            ctx = _context()
            # the pool's own copy of the read end (closed with the pool, when collected)
            lifeline = Connection(os.dup(_open_lifeline()), writable=False)
            _pool = ProcessPoolExecutor(
                max_workers=processes,
                mp_context=ctx,
                initializer=_helper_start,
                initargs=(lifeline,),
            )
            _size = processes
        except (OSError, ValueError) as exc:
            log.warning("no helper processes for report figures (%s)", exc)
        return _pool


def _open_lifeline() -> int:
    """The read end of this process's lifeline (made once, kept open)."""
    global _lifeline
    if _lifeline is None:
        _lifeline = os.pipe()
    return _lifeline[0]


def _helper_start(lifeline: Connection) -> None:
    """In a helper: a terminal's Ctrl-C (SIGINT to the process group) is for the
    process that owns the pool, which stops its helpers as it exits; and when that
    process ends any other way (SIGKILL), the helper ends too. A pool's helpers
    would otherwise wait for work forever, as each holds a write end of its own
    task queue, and keep their forkserver (and its resource tracker) alive."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    threading.Thread(target=_watch_owner, args=(lifeline,), daemon=True).start()


def _watch_owner(lifeline: Connection) -> None:
    try:
        lifeline.recv_bytes()  # nothing is ever sent: returns only at the owner's end
    except (EOFError, OSError):
        pass
    os._exit(0)


def _context() -> Any:
    if "forkserver" not in mp.get_all_start_methods():
        return mp.get_context("spawn")
    ctx = mp.get_context("forkserver")
    ctx.set_forkserver_preload(PRELOAD)
    return ctx


def _discard(pool: ProcessPoolExecutor | None) -> None:
    """Stop ``pool`` (if it is still this process's); the next report starts another."""
    global _pool
    with _lock:
        if pool is None or pool is not _pool:
            return
        _pool = None
    helpers = list((getattr(pool, "_processes", None) or {}).values())  # before the shutdown
    pool.shutdown(wait=False, cancel_futures=True)
    for p in helpers:  # a helper stuck in a draw would otherwise be waited for
        if p.is_alive():
            p.kill()


def _forget() -> None:
    """In a forked child: the parent's pool is not its own (nor its lock's state), and
    its copy of the parent's lifeline must not keep the parent's helpers alive."""
    global _pool, _lock, _lifeline
    _pool, _lock = None, threading.Lock()
    if _lifeline is not None:
        for fd in _lifeline:
            os.close(fd)
        _lifeline = None


if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_forget)
