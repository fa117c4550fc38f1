"""Stop signals that arrive before ``svrobs serve`` has set its own handlers.

Python's default SIGINT raises KeyboardInterrupt wherever the process is; during the
imports before ``serve`` runs, a library's bare ``except:`` can swallow it, and the
stack would then start as if no one had asked it to stop. :func:`record_early`, set
first thing by the entry point, keeps SIGINT and SIGTERM in :data:`RECEIVED`, which
``serve`` reads once its handlers are set (docs/performance.md#restarts-and-stops).
Every other command ends on SIGTERM as on Ctrl-C (:func:`exit_on_sigterm`): what it
was writing is removed, not left as a temporary file.
"""

from __future__ import annotations

import signal

RECEIVED: list[int] = []


def _record(signum: int, _frame: object) -> None:
    RECEIVED.append(signum)


def record_early() -> None:
    """Keep SIGINT and SIGTERM in :data:`RECEIVED` until a handler replaces this one."""
    for s in (signal.SIGINT, signal.SIGTERM):
        signal.signal(s, _record)


def _terminated(signum: int, _frame: object) -> None:
    raise SystemExit(128 + signum)


def exit_on_sigterm() -> None:
    """SIGTERM raises SystemExit(143) where the process is, so that cleanup (a file
    written through :func:`svrobs_client.files.write_atomic`) runs, as for Ctrl-C."""
    signal.signal(signal.SIGTERM, _terminated)
