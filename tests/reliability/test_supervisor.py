"""The supervisor's restarts and the guard's bound, with real processes.

- :class:`svrobs_cli.processes.Supervisor` (on a clock the test moves) restarts a
  child that exits after 1, 2, 4, ... s, back to 1 s once a run lasted a minute, and
  kills what the exited child left in its process group first.
- :mod:`svrobs_cli.guard`: a child that ignores SIGTERM and hangs in a lock wait
  (what an orphaned worker did) is gone, with the process it started, ``grace`` s
  after its parent is SIGKILLed; the same child started without the guard is not.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

from svrobs_cli.processes import Child, Supervisor

ROOT = Path(__file__).resolve().parents[2]


def _alive(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as fh:
            return fh.read().rsplit(")", 1)[-1].split()[0] != "Z"
    except OSError:
        return False


class Clock:
    def __init__(self):
        self.now = 0.0

    def __call__(self) -> float:
        return self.now


def test_restarts_back_off_and_reset_after_a_stable_run(tmp_path):
    lines: list[str] = []
    clock = Clock()
    child = Child("flaky", [sys.executable, "-c", "import sys; sys.exit(3)"], dict(os.environ))
    sup = Supervisor([child], log=lines.append, first=1.0, longest=4.0, stable=60.0, clock=clock)
    sup.start()
    restarts_at = []
    for _ in range(5):
        child.proc.wait(30)
        sup.poll()  # sees the exit, schedules the restart
        pid = child.pid
        waited = 0.0
        while child.pid == pid:
            clock.now += 0.25
            waited += 0.25
            sup.poll()
        restarts_at.append(waited)
    assert restarts_at == [1.0, 2.0, 4.0, 4.0, 4.0]  # doubling, capped at `longest`
    assert "flaky (pid" in lines[1] and "exited (code 3)" in lines[1]
    assert lines[-1].endswith("restart 5)")

    child.proc.wait(30)
    clock.now += 61.0  # this run lasted over `stable` seconds: the next delay is the first
    sup.poll()
    assert lines[-1].endswith("restarting in 1 s"), lines[-1]
    sup.stop(grace=5)


def test_an_exited_childs_group_is_killed_before_the_restart(tmp_path):
    pidfile = tmp_path / "grandchild"
    code = (
        "import subprocess, sys\n"
        "p = subprocess.Popen([sys.executable, '-c', 'import time; time.sleep(300)'])\n"
        f"open({str(pidfile)!r}, 'w').write(str(p.pid))\n"
        "sys.exit(1)\n"
    )
    child = Child("leaver", [sys.executable, "-c", code], dict(os.environ))
    sup = Supervisor([child], log=lambda _line: None, clock=Clock())
    sup.start()
    child.proc.wait(30)
    grandchild = int(pidfile.read_text())
    assert _alive(grandchild)  # left behind in the child's process group
    sup.poll()
    deadline = time.monotonic() + 10
    while _alive(grandchild) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert not _alive(grandchild)
    sup.stop(grace=5)


HANG = """
import signal, subprocess, sys, threading
signal.signal(signal.SIGTERM, signal.SIG_IGN)
helper = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(300)"])
print(helper.pid, flush=True)
lock = threading.Lock()
lock.acquire()
lock.acquire()  # waits forever (a futex wait)
"""

# a parent that starts the hanging module as serve starts its children (own group,
# parent-death SIGTERM), with or without the guard, prints the child's pid and sleeps
PARENT = """
import os, sys, time
from pathlib import Path
from svrobs_cli.processes import Child, guarded
argv = [sys.executable, "-m", "hang"]
if sys.argv[1] == "guarded":
    argv = guarded(argv, 2.0)
child = Child("hang", argv, dict(os.environ), log=Path(sys.argv[2])).start()
print(child.pid, flush=True)
time.sleep(300)
"""


def _start_parent(folder: Path, mode: str) -> tuple[subprocess.Popen, int, int]:
    folder.mkdir()
    (folder / "hang.py").write_text(HANG)
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(folder), str(ROOT)])}
    out = folder / "child.out"
    parent = subprocess.Popen(
        [sys.executable, "-c", PARENT, mode, str(out)],
        cwd=ROOT,
        env=env,
        stdout=subprocess.PIPE,
        text=True,
        start_new_session=True,
    )
    child = int(parent.stdout.readline())
    deadline = time.monotonic() + 60
    while not out.exists() or not out.read_text().strip():
        assert time.monotonic() < deadline, "the hanging child did not start"
        time.sleep(0.05)
    helper = int(out.read_text().split()[0])
    return parent, child, helper


def test_the_guard_kills_a_hung_child_after_its_parent_dies(tmp_path):
    guarded = _start_parent(tmp_path / "guarded", "guarded")
    bare = _start_parent(tmp_path / "bare", "bare")
    try:
        for parent, _child, _helper in (guarded, bare):
            os.kill(parent.pid, signal.SIGKILL)
            parent.wait(10)
        deadline = time.monotonic() + 15
        while (_alive(guarded[1]) or _alive(guarded[2])) and time.monotonic() < deadline:
            time.sleep(0.1)
        assert not _alive(guarded[1]) and not _alive(guarded[2])
        # the same hung child without the guard ignores the parent-death SIGTERM
        assert _alive(bare[1]) and _alive(bare[2])
        assert "still running after 2 s" in (tmp_path / "guarded" / "child.out").read_text()
    finally:
        for pid in (*guarded[1:], *bare[1:]):
            try:
                os.kill(pid, signal.SIGKILL)
            except ProcessLookupError:
                pass


def test_a_stop_during_the_migration_starts_nothing(tmp_path, monkeypatch, capsys):
    """SIGINT while ``svrobs serve`` migrates, with the KeyboardInterrupt it would
    raise swallowed as a finalizer running at that moment would: the migration ends,
    no process starts, the new admin key is still printed, the handlers are restored."""
    from service.config import Settings
    from svrobs_cli import serve as serve_mod

    def migrate(_settings):
        try:
            os.kill(os.getpid(), signal.SIGINT)
            time.sleep(0.05)  # the handler has run by now
        except KeyboardInterrupt:  # what a finalizer does with it
            pass

    def start(_self):
        raise AssertionError("the stack started after the stop")

    monkeypatch.setattr(serve_mod, "check_port", lambda _host, _port: None)
    monkeypatch.setattr(serve_mod, "migrate", migrate)
    monkeypatch.setattr(serve_mod, "bootstrap_admin", lambda _s: "svr_new_key")
    monkeypatch.setattr(Supervisor, "start", start)
    before = signal.getsignal(signal.SIGINT)
    settings = Settings(DATABASE_URL=f"sqlite:///{tmp_path / 'x.db'}", VAR_DIR=str(tmp_path))
    assert serve_mod.serve(settings, grace=0.1) == 0
    assert signal.getsignal(signal.SIGINT) is before
    out = capsys.readouterr().out
    assert "svrobs: stopping" in out and "admin API key (shown once): svr_new_key" in out


def test_a_stop_during_the_imports_of_serve_starts_nothing(tmp_path):
    """``svrobs serve`` keeps a SIGINT that arrives before its handlers are set (here
    sent right after the entry point's first line) and starts nothing: exit 0, no
    process started, nothing migrated."""
    code = (
        "import os, signal, sys\n"
        "sys.argv = ['svrobs', 'serve', '--port', '1']\n"
        "from svrobs_cli.signals import record_early\n"
        "record_early()\n"
        "os.kill(os.getpid(), signal.SIGINT)  # before svrobs_cli.app is imported\n"
        "from svrobs_cli.__main__ import main\n"
        "main()\n"
    )
    env = {k: v for k, v in os.environ.items() if not k.startswith("SVROBS_")}
    env.update(SVROBS_DATABASE_URL=f"sqlite:///{tmp_path / 'x.db'}", SVROBS_VAR_DIR=str(tmp_path))
    done = subprocess.run(
        [sys.executable, "-c", code], cwd=ROOT, env=env, capture_output=True, text=True, timeout=120
    )
    assert done.returncode == 0, done.stderr
    assert "svrobs: stopping" in done.stdout and "started" not in done.stdout + done.stderr
    assert not (tmp_path / "x.db").exists()


def test_a_stop_clears_beats_report_build_mark(tmp_path, monkeypatch):
    """A report build cut short by the operator's stop (here two Ctrl-Cs while beat's
    build is marked in flight) is not a crash: ``svrobs serve`` clears the mark after
    stopping its processes and keeps the jobs' counts (service.report_crashes)."""
    from service.config import Settings
    from service.report_crashes import FILE_NAME, CrashRecord
    from svrobs_cli import serve as serve_mod

    record = CrashRecord(tmp_path / FILE_NAME)
    record.crashes = {3: 1}
    building = record.in_flight(9)  # held: the build never ends in this process

    def start(_self):  # beat marks a build in flight; then the operator presses Ctrl-C twice
        building.__enter__()
        os.kill(os.getpid(), signal.SIGINT)
        os.kill(os.getpid(), signal.SIGINT)

    monkeypatch.setattr(serve_mod, "check_port", lambda _host, _port: None)
    monkeypatch.setattr(serve_mod, "migrate", lambda _s: None)
    monkeypatch.setattr(serve_mod, "bootstrap_admin", lambda _s: None)
    monkeypatch.setattr(serve_mod, "_children", lambda *a, **k: [])
    monkeypatch.setattr(Supervisor, "start", start)
    settings = Settings(DATABASE_URL=f"sqlite:///{tmp_path / 'x.db'}", VAR_DIR=str(tmp_path))
    assert serve_mod.serve(settings, grace=0.1) == 0
    assert building.gen.gi_frame is not None  # the mark was not cleared by the build
    after = CrashRecord(tmp_path / FILE_NAME)
    assert after.recover() is None and after.crashes == {3: 1}
