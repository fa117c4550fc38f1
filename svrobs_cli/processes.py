"""Child processes that leave nothing behind: own process group, parent-death signal,
SIGTERM then SIGKILL of the whole group, reaped.

Used by ``svrobs serve`` and by the test helpers that start real servers
(``tests/integration``), so every process the project starts is stopped the same way.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

PR_SET_PDEATHSIG = 1


def _load_prctl():
    """libc's prctl, resolved once in the parent (the child must not dlopen after fork)."""
    if not sys.platform.startswith("linux"):
        return None
    try:
        import ctypes

        return ctypes.CDLL(None, use_errno=True).prctl
    except (OSError, AttributeError):
        return None


_PRCTL = _load_prctl()


def deathsig(sig: int = signal.SIGTERM):
    """A ``preexec_fn``: the child gets ``sig`` when this process dies (even by SIGKILL),
    so a killed parent leaves no orphans. None where prctl is not available."""
    if _PRCTL is None:
        return None

    def preexec() -> None:  # pragma: no cover - runs in the child, between fork and exec
        _PRCTL(PR_SET_PDEATHSIG, int(sig))

    return preexec


def kill_group(proc: subprocess.Popen | None, wait: float = 10.0) -> None:
    """SIGKILL ``proc``'s process group (a prefork pool, a postmaster's backends) and
    reap ``proc``."""
    if proc is None:
        return
    try:
        os.killpg(proc.pid, signal.SIGKILL)
    except (ProcessLookupError, PermissionError):
        pass
    try:
        proc.wait(wait)
    except subprocess.TimeoutExpired:  # pragma: no cover
        pass


@dataclass
class Child:
    """One supervised child process in its own process group."""

    name: str
    argv: list[str]
    env: dict
    log: Path | None = None
    cwd: Path | None = None  # default: the caller's working directory
    proc: subprocess.Popen | None = field(default=None, repr=False)

    def start(self) -> Child:
        out = open(self.log, "ab") if self.log else None
        self.proc = subprocess.Popen(
            self.argv,
            env=self.env,
            cwd=str(self.cwd or os.getcwd()),
            stdin=subprocess.DEVNULL,
            stdout=out,
            stderr=subprocess.STDOUT if out else None,
            start_new_session=True,
            preexec_fn=deathsig(signal.SIGTERM),  # noqa: PLW1509
        )
        if out:
            out.close()
        return self

    @property
    def pid(self) -> int | None:
        return self.proc.pid if self.proc else None

    def poll(self) -> int | None:
        return self.proc.poll() if self.proc else 0

    def signal(self, sig: int, group: bool = False) -> None:
        if self.proc is None or self.proc.poll() is not None:
            return
        try:
            if group:
                os.killpg(self.proc.pid, sig)
            else:
                self.proc.send_signal(sig)
        except ProcessLookupError:
            pass

    def stop(self, grace: float = 10.0) -> int | None:
        """SIGTERM, wait ``grace`` s, then SIGKILL the whole group; reap."""
        if self.proc is None:
            return None
        self.signal(signal.SIGTERM)
        try:
            self.proc.wait(grace)
        except subprocess.TimeoutExpired:
            pass
        self.kill_group()
        return self.proc.returncode

    def kill_group(self) -> None:
        """SIGKILL the child's process group (the prefork pool too) and reap."""
        kill_group(self.proc)


def stop_all(children: list[Child], grace: float = 10.0) -> None:
    """SIGTERM every child at once, wait up to ``grace`` s in total, SIGKILL the rest."""
    for c in children:
        c.signal(signal.SIGTERM)
    deadline = time.monotonic() + grace
    for c in children:
        if c.proc is None:
            continue
        try:
            c.proc.wait(max(0.0, deadline - time.monotonic()))
        except subprocess.TimeoutExpired:
            pass
    for c in children:
        c.kill_group()  # also sweeps leftover grandchildren of exited children
