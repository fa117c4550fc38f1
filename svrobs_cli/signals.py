"""Stop signals that arrive before ``svrobs serve`` has set its own handlers.

Python's default SIGINT raises KeyboardInterrupt wherever the process is; during the
imports before ``serve`` runs, a library's bare ``except:`` can swallow it, and the
stack would then start as if no one had asked it to stop. :func:`record_early`, set
first thing by the entry point, keeps SIGINT and SIGTERM in :data:`RECEIVED`, which
``serve`` reads once its handlers are set (docs/performance.md#restarts-and-stops).
The commands that talk to the API end on SIGTERM by unwinding, as on Ctrl-C
(:func:`exit_on_sigterm`): what they were writing is removed, not left as a temporary
file. The commands that compute in worker processes (:data:`COMPUTING`) keep the
default, which ends them at once (unwinding would wait for the units running).
"""

from __future__ import annotations

import os
import signal

RECEIVED: list[int] = []
COMPUTING = ("reproduce", "run-local")  # the core in this process and its workers


def _record(signum: int, _frame: object) -> None:
    RECEIVED.append(signum)


def record_early() -> None:
    """Keep SIGINT and SIGTERM in :data:`RECEIVED` until a handler replaces this one."""
    for s in (signal.SIGINT, signal.SIGTERM):
        signal.signal(s, _record)


_OWNER: list[int] = []  # the process that set the handler (not a child forked later)


def _terminated(signum: int, _frame: object) -> None:
    if os.getpid() not in _OWNER:  # a forked child: the default, at once
        signal.signal(signum, signal.SIG_DFL)
        os.kill(os.getpid(), signum)
        return
    raise SystemExit(128 + signum)


def exit_on_sigterm() -> None:
    """SIGTERM raises SystemExit(143) where this process is, so that cleanup (a file
    written through :func:`svrobs_client.files.write_atomic`) runs, as for Ctrl-C."""
    _OWNER[:] = [os.getpid()]
    signal.signal(signal.SIGTERM, _terminated)
