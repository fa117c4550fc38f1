"""Pid files of the workers ``svrobs serve`` runs on this host, read by ``/readyz``.

``svrobs serve`` starts each worker with ``celery worker --pidfile
<WORKER_PID_DIR>/<name>.pid`` (Celery writes the file when the worker starts and
removes it when the worker stops) and sets ``SVROBS_WORKER_PID_DIR`` for the API,
whose ``/readyz`` then answers 503 while no worker is alive: a worker killed and
not yet restarted leaves its file behind with a pid that is gone.
"""

from __future__ import annotations

import os
from pathlib import Path


def pidfile(pid_dir: str | os.PathLike, name: str) -> Path:
    return Path(pid_dir) / f"{name}.pid"


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # someone else's process: not one of ours
        return False
    try:  # an exited child its parent has not reaped yet is not running
        with open(f"/proc/{pid}/stat") as fh:
            return fh.read().rsplit(")", 1)[-1].split()[0] != "Z"
    except OSError:
        return True  # no /proc: kill(pid, 0) said it exists


def live_workers(pid_dir: str | os.PathLike) -> dict[str, int]:
    """``{worker name: pid}`` of the pid files in ``pid_dir`` whose process is alive."""
    found: dict[str, int] = {}
    try:
        paths = sorted(Path(pid_dir).glob("*.pid"))
    except OSError:
        return found
    for path in paths:
        try:
            pid = int(path.read_text().strip() or 0)
        except (OSError, ValueError):
            continue
        if pid > 0 and _alive(pid):
            found[path.stem] = pid
    return found


def check_workers(pid_dir: str | os.PathLike) -> None:
    """Raise unless at least one worker of ``pid_dir`` is alive."""
    if not live_workers(pid_dir):
        raise RuntimeError(f"no worker is running (pid files in {pid_dir})")
