"""Child processes that leave nothing behind: own process group, parent-death signal,
SIGTERM then SIGKILL of the whole group, reaped; and a :class:`Supervisor` that
restarts a child that dies.

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
PR_GET_PDEATHSIG = 2


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


def parent_death_signal() -> int:
    """The signal this process gets when its parent dies (0: none, or not Linux)."""
    if _PRCTL is None:
        return 0
    import ctypes

    sig = ctypes.c_int(0)
    if _PRCTL(PR_GET_PDEATHSIG, ctypes.byref(sig), 0, 0, 0) != 0:
        return 0
    return sig.value


def guarded(argv: list[str], grace: float) -> list[str]:
    """``[python, -m, module, ...]`` run under :mod:`svrobs_cli.guard`: once this
    process (its parent) is gone, the child is SIGKILLed ``grace`` s later at most."""
    if argv[1:2] != ["-m"]:
        raise ValueError(f"not a `python -m module` command: {argv[:3]}")
    return [
        argv[0],
        "-m",
        "svrobs_cli.guard",
        "--parent",
        str(os.getpid()),
        "--grace",
        f"{grace:g}",
        *argv[1:],
    ]


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
    # a pid file the child writes (celery's --pidfile): removed before every start,
    # so one left by a killed child never stops the next (celery refuses a live pid)
    pidfile: Path | None = None
    proc: subprocess.Popen | None = field(default=None, repr=False)

    def start(self) -> Child:
        if self.pidfile is not None:
            self.pidfile.unlink(missing_ok=True)
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


def describe_exit(code: int | None) -> str:
    """``code 1`` / ``killed by SIGKILL`` for a Popen return code."""
    if code is not None and code < 0:
        try:
            return f"killed by {signal.Signals(-code).name}"
        except ValueError:
            return f"killed by signal {-code}"
    return f"code {code}"


@dataclass
class _Watch:
    started: float
    failures: int = 0  # exits in a row, each within STABLE_SECONDS of its start
    restart_at: float | None = None
    restarts: int = 0


class Supervisor:
    """Runs children and restarts one that exits, after an exponential backoff.

    The n-th exit in a row of a child that ran less than ``stable`` s waits
    ``first * 2**(n-1)`` s (at most ``longest``) before the restart; each exit and
    restart is logged through ``log``. An exited child's process group is killed
    before it is restarted (a prefork pool left behind by a SIGKILLed worker)."""

    def __init__(
        self,
        children: list[Child],
        *,
        log=print,
        first: float = 1.0,
        longest: float = 30.0,
        stable: float = 60.0,
        clock=time.monotonic,
    ):
        self.children = children
        self.log = log
        self.first, self.longest, self.stable = first, longest, stable
        self.clock = clock
        self._watch: dict[str, _Watch] = {}

    def start(self) -> None:
        for c in self.children:
            c.start()
            self._watch[c.name] = _Watch(started=self.clock())
            self.log(f"svrobs: started {c.name} (pid {c.pid})")

    def poll(self) -> None:
        """Note children that exited and restart those whose backoff is over."""
        now = self.clock()
        for c in self.children:
            w = self._watch[c.name]
            if w.restart_at is None:
                code = c.poll()
                if code is None:
                    continue
                c.kill_group()
                ran = now - w.started
                w.failures = w.failures + 1 if ran < self.stable else 1
                delay = min(self.longest, self.first * 2 ** (w.failures - 1))
                w.restart_at = now + delay
                self.log(
                    f"svrobs: {c.name} (pid {c.pid}) exited ({describe_exit(code)}) after "
                    f"{ran:.1f} s; restarting in {delay:g} s"
                )
            elif now >= w.restart_at:
                c.start()
                w.started, w.restart_at = now, None
                w.restarts += 1
                self.log(f"svrobs: restarted {c.name} (pid {c.pid}; restart {w.restarts})")

    def stop(self, grace: float) -> None:
        stop_all(self.children, grace=grace)
