"""One ``svrobs serve`` per state folder (SVROBS_VAR_DIR, ``./var``).

Two ``serve`` processes on one folder would share the workers' pid files
(``var/run/worker1.pid``, read by ``/readyz``), beat's schedule file and the
filesystem broker's folders: the second one's stop removes the first one's worker
pid file, and the first one's ``/readyz`` answers 503 while its worker runs. So
``serve`` holds ``serve.lock`` in the folder locked (flock) while it runs, with its
pid and URL written in it, and a second ``serve`` on the folder is one line naming
them, before it starts anything. The lock goes with the process that holds it (a
SIGKILLed ``serve`` leaves no stale lock); the file stays.
"""

from __future__ import annotations

import fcntl
import os
from pathlib import Path

from svrobs_cli.errors import CliError

FILE_NAME = "serve.lock"


def lock_file(state: Path) -> Path:
    """The lock file of the state folder ``state``."""
    return Path(state).resolve() / FILE_NAME


def already_serving(state: Path, holder: str) -> CliError:
    """The one-line error naming the ``serve`` that holds the folder
    (``holder``: ``"<pid> <url>"`` as it wrote them, or ``""``)."""
    pid, _, url = holder.strip().partition(" ")
    who = f"pid {pid}, {url}" if pid.isdigit() and url else "another process"
    return CliError(
        f"svrobs serve already runs on the state folder {Path(state).resolve()} ({who}); "
        "use that one, or stop it (Ctrl-C in its terminal) before starting another"
    )


def _holder(fd: int) -> str:
    return os.pread(fd, 256, 0).decode("utf-8", "replace")


def running_serve(state: Path) -> str | None:
    """``"<pid> <url>"`` of the ``serve`` that holds ``state``'s lock (``""`` if it has
    not written them yet), or None when none does. Creates nothing."""
    try:
        fd = os.open(lock_file(state), os.O_RDONLY)
    except OSError:
        return None
    try:
        fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
    except BlockingIOError:
        return _holder(fd)
    finally:
        os.close(fd)  # also releases a shared lock just taken
    return None


def hold_serve_lock(state: Path, url: str) -> int:
    """Lock ``state`` for this process and write our pid and URL in the lock file;
    returns the fd (closing it, or this process ending, releases the lock; children
    do not inherit it). Raises :func:`already_serving`'s error when another process
    holds it (two starts at once: one of them gets it)."""
    fd = os.open(lock_file(state), os.O_RDWR | os.O_CREAT, 0o644)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        holder = _holder(fd)
        os.close(fd)
        raise already_serving(state, holder) from None
    os.ftruncate(fd, 0)
    os.pwrite(fd, f"{os.getpid()} {url}\n".encode(), 0)
    return fd
