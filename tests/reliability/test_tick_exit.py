"""A beat (or any tick process) that exits while a report build runs in its
background thread waits for the build (bounded), so the interpreter never stops the
thread inside a native call: that aborted the process with "terminate called
without an active exception" (pybind11's GIL release in matplotlib's drawing)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]

SCRIPT = """
import sys, time
import worker.tick as tick

def slow_build(limit=2, scope=None):  # a report's figures: native drawing for ~1 s
    import io
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    t0 = time.monotonic()
    while time.monotonic() - t0 < 1.0:
        fig, ax = plt.subplots()
        ax.plot(range(20000))
        fig.savefig(io.BytesIO(), format="png")
        plt.close(fig)
    open(sys.argv[1], "w").write("built")
    return [1]

tick.build_reports = slow_build
assert tick.start_report_builds()
assert not tick.start_report_builds()  # one build at a time
print("exiting")
"""


def test_exit_waits_for_the_report_build_in_flight(tmp_path):
    done = tmp_path / "built"
    p = subprocess.run(
        [sys.executable, "-c", SCRIPT, str(done)],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert p.returncode == 0, p.stderr[-2000:]
    assert "terminate called" not in p.stderr
    assert done.read_text() == "built"  # the build finished before the process ended


def test_wait_is_bounded():
    import threading

    import worker.tick as tick

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
