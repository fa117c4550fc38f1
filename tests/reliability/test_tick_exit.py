"""A beat (or any tick process) that exits while a report build runs in its
background thread waits for the build (bounded), so the interpreter never stops the
thread inside a native call: that aborted the process with "terminate called
without an active exception" (pybind11's GIL release in matplotlib's drawing)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def run_script(script: str, arg, *, timeout: float) -> subprocess.CompletedProcess:
    """``script`` in a new interpreter of this checkout, with ``arg`` as argv[1]."""
    return subprocess.run(
        [sys.executable, "-c", script, str(arg)],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=timeout,
    )


DRAWING = """
import sys, time
import worker.tick as tick

def drawing_build(limit=2, scope=None):  # a report's figures: native drawing for a while
    import io
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    t0 = time.monotonic()
    while time.monotonic() - t0 < SECONDS:
        fig, ax = plt.subplots()
        ax.plot(range(20000))
        fig.savefig(io.BytesIO(), format="png")
        plt.close(fig)
    open(sys.argv[1], "w").write("built")
    return [1]

"""

SCRIPT = (
    DRAWING.replace("SECONDS", "1.0")
    + """
tick.build_reports = drawing_build
assert tick.start_report_builds()
assert not tick.start_report_builds()  # one build at a time
print("exiting")
"""
)


def test_exit_waits_for_the_report_build_in_flight(tmp_path):
    done = tmp_path / "built"
    p = run_script(SCRIPT, done, timeout=120)
    assert p.returncode == 0, p.stderr[-2000:]
    assert "terminate called" not in p.stderr
    assert done.read_text() == "built"  # the build finished before the process ended


ABANDON = (
    DRAWING.replace("SECONDS", "120.0")
    + """
tick.REPORT_EXIT_WAIT_SECONDS = 0.5  # a build far longer than the wait at exit
tick.build_reports = drawing_build
assert tick.start_report_builds()
time.sleep(0.5)  # the build is drawing
print("exiting")
"""
)


def test_exit_abandons_a_build_longer_than_the_wait(tmp_path):
    """A build still running when the wait at exit ends is abandoned: the process
    ends at once with status 0 (nothing of the build is stored), never aborted."""
    done = tmp_path / "built"
    # far below the build's 120 s: the process did not wait for it
    p = run_script(ABANDON, done, timeout=60)
    assert p.returncode == 0, p.stderr[-2000:]
    assert "terminate called" not in p.stderr
    assert "abandoned at exit" in p.stderr
    assert p.stdout.strip() == "exiting" and not done.exists()


ABANDON_MARKED = (
    DRAWING.replace("SECONDS", "120.0")
    + """
from pathlib import Path
from service.report_crashes import CrashRecord

tick.REPORT_EXIT_WAIT_SECONDS = 0.5
tick._crash_record = CrashRecord(Path(sys.argv[1]).with_name("record.json"))

def marked_build(limit=2, scope=None):  # a build marked in flight, as build_reports marks it
    with tick._crash_record.in_flight(5):
        return drawing_build(limit, scope)

tick.build_reports = marked_build
assert tick.start_report_builds()
time.sleep(0.5)
assert '"in_flight": 5' in tick._crash_record.path.read_text()
print("exiting")
"""
)


def test_a_build_abandoned_at_exit_is_not_counted_as_a_crash(tmp_path):
    """The in-flight mark of a build abandoned at exit is cleared: only a build that
    ends the process counts against its job (service.report_crashes)."""
    from service.report_crashes import CrashRecord

    p = run_script(ABANDON_MARKED, tmp_path / "built", timeout=60)
    assert p.returncode == 0 and "abandoned at exit" in p.stderr, p.stderr[-2000:]
    assert CrashRecord(tmp_path / "record.json").recover() is None


def test_a_tick_run_by_a_worker_starts_no_report_thread(monkeypatch):
    """Reports are built in beat's process: a worker that runs the tick task (beat
    without the tick scheduler) does not start a report thread in its pool process."""
    import worker.tasks as tasks
    import worker.tick as tick

    started = []
    monkeypatch.setattr(tick, "start_report_builds", lambda: started.append(1) or True)
    for part in ("create_due_jobs", "relay", "prune_expired"):
        monkeypatch.setattr(tick, part, lambda *a, **k: [])
    tasks.tick()
    assert started == []
    tick.run_tick()  # beat's own call does start it
    assert started == [1]


def test_wait_is_bounded(monkeypatch):
    import threading

    import worker.tick as tick

    monkeypatch.setattr(tick, "_stop_reports", threading.Event())  # this process's stays clear
    release = threading.Event()
    t = threading.Thread(target=release.wait, daemon=True)
    t.start()
    old, tick._report_thread = tick._report_thread, t
    try:
        assert tick.wait_for_report_builds(timeout=0.1) is False
        release.set()
        assert tick.wait_for_report_builds(timeout=5) is True
    finally:
        tick._report_thread = old


def test_the_report_thread_polls_until_stopped(monkeypatch, tmp_path):
    """Beat's report thread builds again every REPORT_POLL_SECONDS (not once per
    tick), survives a failing build, and ends when the process stops it."""
    import threading

    import worker.tick as tick
    from service.config import get_settings

    calls = []
    third = threading.Event()

    def counting_build(limit=2, scope=None):
        calls.append(1)
        if len(calls) == 1:
            raise RuntimeError("a build that fails: retried at the next poll")
        if len(calls) == 3:
            third.set()
        return []

    monkeypatch.setenv("SVROBS_REPORT_POLL_SECONDS", "0.05")
    monkeypatch.setenv("SVROBS_VAR_DIR", str(tmp_path))
    monkeypatch.setattr(tick, "_crash_record", None)
    get_settings.cache_clear()
    monkeypatch.setattr(tick, "build_reports", counting_build)
    monkeypatch.setattr(tick, "_report_thread", None)
    monkeypatch.setattr(tick, "_stop_reports", threading.Event())
    monkeypatch.setattr(tick.atexit, "register", lambda fn: None)
    try:
        assert tick.start_report_builds()
        assert not tick.start_report_builds()  # one thread per process
        assert third.wait(30)  # polled again after the failure, with no tick in between
        assert tick.wait_for_report_builds(timeout=30)
        assert not tick._report_thread.is_alive()
        n = len(calls)
        threading.Event().wait(0.2)  # four polls' time
        assert len(calls) == n  # nothing builds after the stop
        assert tick._crash_record.path.parent == tmp_path  # in the state folder
    finally:
        get_settings.cache_clear()


def test_beat_starts_the_report_thread_with_its_schedule(monkeypatch, tmp_path):
    """The report thread runs from beat's start, not from its first tick."""
    import worker.tick as tick
    from worker.beat import TickScheduler
    from worker.celery_app import celery_app

    started = []
    monkeypatch.setattr(tick, "start_report_builds", lambda: started.append(1) or True)
    scheduler = TickScheduler(app=celery_app, schedule_filename=str(tmp_path / "schedule"))
    try:
        assert started == [1]
        assert "svrobs.tick" in {e.task for e in scheduler.schedule.values()}
    finally:
        scheduler.close()
