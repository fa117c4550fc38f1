"""A report's figures drawn by helper processes (svrobs_lab.figure_pool): the page is
the one drawn in process, byte for byte, and a helper that fails, is killed, is
late, cannot be handed its figure or was not sent a field it reads costs only time."""

from __future__ import annotations

import logging
import multiprocessing as mp
import os
import signal
import threading
import time

import pytest

from svrobs_core.report import FigureJob, draw_png
from svrobs_core.report.build import FIGURE_FIELDS
from svrobs_core.report.plotting import new_figure
from svrobs_lab import figure_pool
from svrobs_lab.report_html import job_report_html
from tests.core.test_report import make_records, tiny_spec

HELPERS = 2


@pytest.fixture(scope="module")
def job():
    spec = tiny_spec()
    return spec, make_records(spec, seed=5)


@pytest.fixture
def pool():
    figure_pool._discard(figure_pool._pool)  # a pool of this test's own
    yield
    figure_pool._discard(figure_pool._pool)


def page(job, render):
    spec, recs = job
    return job_report_html(spec, recs, {"job_id": 7}, name="pool", render=render)


def alive(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as fh:
            return fh.read().split(")")[-1].split()[0] != "Z"
    except OSError:
        return False


def test_the_helpers_draw_the_page_drawn_in_process(job, pool):
    here = page(job, None)
    assert figure_pool.warm(HELPERS)
    pids = figure_pool.helper_pids()
    assert len(pids) == HELPERS and os.getpid() not in pids and all(map(alive, pids))
    drawn = page(job, figure_pool.figure_renderer(HELPERS))
    assert drawn == here
    assert "data:image/png;base64," in drawn
    assert figure_pool.helper_pids() == pids  # the same helpers, kept for the next report


def test_killed_helpers_cost_only_time(job, pool, caplog):
    here = page(job, None)
    assert figure_pool.warm(HELPERS)
    killed = figure_pool.helper_pids()
    for pid in killed:
        os.kill(pid, signal.SIGKILL)
    deadline = time.monotonic() + 10
    while any(map(alive, killed)) and time.monotonic() < deadline:
        time.sleep(0.05)
    with caplog.at_level(logging.WARNING, logger="svrobs_lab.figure_pool"):
        assert page(job, figure_pool.figure_renderer(HELPERS)) == here
    assert "drawn in process" in caplog.text or "could not be handed" in caplog.text
    # the next report has helpers of its own
    assert page(job, figure_pool.figure_renderer(HELPERS)) == here
    fresh = figure_pool.helper_pids()
    assert fresh and not set(fresh) & set(killed)


def test_a_late_helper_leaves_its_figure_to_this_process(job, pool, monkeypatch, caplog):
    here = page(job, None)
    assert figure_pool.warm(HELPERS)
    started = figure_pool.helper_pids()
    monkeypatch.setattr(figure_pool, "DRAW_TIMEOUT_SECONDS", 1e-4)  # no draw is this fast
    with caplog.at_level(logging.WARNING, logger="svrobs_lab.figure_pool"):
        assert page(job, figure_pool.figure_renderer(HELPERS)) == here
    assert "drawn in process" in caplog.text
    assert figure_pool._pool is None  # the late pool was stopped, its helpers killed
    deadline = time.monotonic() + 10
    while any(map(alive, started)) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert not any(map(alive, started))


def _small_figure(*_):
    fig, axes = new_figure(1, 1, (3.0, 2.0))
    axes[0, 0].plot([1, 2, 3], [3, 1, 2])
    return fig


def test_a_figure_that_cannot_be_pickled_is_drawn_here(pool, caplog):
    expected = draw_png(_small_figure())
    job = FigureJob(_small_figure, (lambda: None,))  # pickle refuses a lambda
    assert figure_pool.warm(HELPERS)
    pids = figure_pool.helper_pids()
    render = figure_pool.figure_renderer(HELPERS)
    assert render is not None
    with caplog.at_level(logging.WARNING, logger="svrobs_lab.figure_pool"):
        assert render(job).result() == expected
    assert "could not be sent to a helper" in caplog.text and "drawn in process" in caplog.text
    assert figure_pool.helper_pids() == pids  # the helpers are fine: kept


def test_a_figure_sent_too_few_fields_is_built_here_from_all(job, pool, monkeypatch, caplog):
    here = page(job, None)
    assert figure_pool.warm(HELPERS)
    pids = figure_pool.helper_pids()
    fields = {n: tuple(f for f in fs if f != "N") for n, fs in FIGURE_FIELDS.items()}
    monkeypatch.setattr("svrobs_core.report.build.FIGURE_FIELDS", fields)
    with caplog.at_level(logging.WARNING, logger="svrobs_lab.figure_pool"):
        assert page(job, figure_pool.figure_renderer(HELPERS)) == here
    assert "KeyError: 'N (not sent with the figure)'" in caplog.text
    assert "drawn in process" in caplog.text
    assert figure_pool.helper_pids() == pids  # the helpers are fine: kept


def _renderer_in_daemon(q):
    q.put(figure_pool.figure_renderer(HELPERS) is None)


def test_no_helpers_when_turned_off_or_in_a_daemon(monkeypatch):
    assert figure_pool.figure_renderer(0) is None
    monkeypatch.setattr(figure_pool, "_processes", 0)
    assert figure_pool.figure_renderer() is None  # not configured: drawn in process
    figure_pool.configure(HELPERS)
    assert figure_pool.figure_renderer() is not None
    assert not figure_pool.warm(0)
    ctx = mp.get_context("fork")
    q = ctx.Queue()
    p = ctx.Process(target=_renderer_in_daemon, args=(q,), daemon=True)
    p.start()
    assert q.get(timeout=30) is True  # a daemon (a Celery pool process) may have no children
    p.join(30)


def test_the_api_app_and_beat_set_the_helpers_from_the_settings(monkeypatch, tmp_path):
    from service.app import create_app
    from service.config import Settings, get_settings
    from worker import tick

    monkeypatch.setattr(figure_pool, "_processes", 0)
    db = f"sqlite:///{tmp_path / 'svrobs.db'}"
    create_app(Settings(DATABASE_URL=db, REPORT_RENDER_PROCESSES=3))
    assert figure_pool._processes == 3
    create_app(Settings(DATABASE_URL=db, REPORT_RENDER_PROCESSES=0))
    assert figure_pool.figure_renderer() is None
    # beat's report thread, from the process's settings
    monkeypatch.setenv("SVROBS_REPORT_RENDER_PROCESSES", "1")
    monkeypatch.setenv("SVROBS_VAR_DIR", str(tmp_path))
    get_settings.cache_clear()
    monkeypatch.setattr(tick, "build_reports", lambda *a, **k: [])
    monkeypatch.setattr(tick, "_report_thread", None)
    monkeypatch.setattr(tick, "_crash_record", None)
    monkeypatch.setattr(tick, "_stop_reports", threading.Event())
    try:
        assert tick.start_report_builds()
        assert figure_pool._processes == 1
    finally:
        tick._stop_reports.set()
        tick._report_thread.join(10)
        get_settings.cache_clear()


OWNER = """
import os, sys, time
from svrobs_lab import figure_pool
assert figure_pool.warm(2)
print(" ".join(map(str, figure_pool.helper_pids())), flush=True)
time.sleep(120)
"""


def marked(value: str) -> list[int]:
    """Live processes whose environment holds SVROBS_TEST_POOL_OWNER=value."""
    needle = f"SVROBS_TEST_POOL_OWNER={value}\0".encode()
    found = []
    for entry in os.scandir("/proc"):
        if entry.name.isdigit():
            try:
                with open(f"/proc/{entry.name}/environ", "rb") as fh:
                    if needle in fh.read():
                        found.append(int(entry.name))
            except OSError:
                continue
    return found


@pytest.mark.parametrize("stop", [signal.SIGKILL, signal.SIGTERM])
def test_the_helpers_end_with_the_process_that_owns_them(stop):
    """A killed owner leaves no helper, forkserver or resource tracker behind (a
    helper holds a write end of its own task queue, so it would wait forever)."""
    import subprocess
    import sys
    import uuid

    value = uuid.uuid4().hex
    env = dict(os.environ, SVROBS_TEST_POOL_OWNER=value)
    owner = subprocess.Popen(
        [sys.executable, "-c", OWNER], stdout=subprocess.PIPE, text=True, env=env
    )
    try:
        helpers = [int(p) for p in owner.stdout.readline().split()]
        assert len(helpers) == 2 and all(map(alive, helpers))
        assert len(marked(value)) >= 5  # owner, forkserver, resource tracker, 2 helpers
        owner.send_signal(stop)
        owner.wait(10)
        deadline = time.monotonic() + 10
        while marked(value) and time.monotonic() < deadline:
            time.sleep(0.1)
        assert not marked(value)
    finally:
        owner.kill()
        owner.wait()
        for pid in marked(value):
            os.kill(pid, signal.SIGKILL)


def test_the_api_app_stops_the_helpers_at_its_shutdown(tmp_path, monkeypatch):
    """uvicorn ends the API process by its stop signal after the app's shutdown, so
    the exit handlers that would free the pool do not run: the shutdown frees it."""
    import subprocess
    import sys

    from fastapi.testclient import TestClient

    from service.app import create_app
    from service.config import Settings

    monkeypatch.setattr(figure_pool, "_processes", 0)
    app = create_app(Settings(DATABASE_URL=f"sqlite:///{tmp_path / 'svrobs.db'}"))
    with TestClient(app):
        assert figure_pool.warm(HELPERS)
        pids = figure_pool.helper_pids()
    assert figure_pool._pool is None
    deadline = time.monotonic() + 10
    while any(map(alive, pids)) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert not any(map(alive, pids))
    # a process that closed its pool and then ends by SIGTERM leaks nothing its
    # resource tracker would have to clean up (and warn of, on the terminal)
    script = (
        "import os, signal\nfrom svrobs_lab import figure_pool\n"
        "assert figure_pool.warm(2)\nfigure_pool.close()\n"
        "os.kill(os.getpid(), signal.SIGTERM)\n"
    )
    done = subprocess.run(
        [sys.executable, "-c", script], capture_output=True, text=True, timeout=60
    )
    assert done.returncode == -signal.SIGTERM
    assert "leaked" not in done.stderr and "Traceback" not in done.stderr, done.stderr


def test_a_report_whose_helpers_died_lets_go_of_its_columns(job, pool):
    """The futures of a broken pool share one exception; its traceback must not keep
    the build's frames, and so its columns, until a gc pass."""
    import gc
    import weakref

    from svrobs_core.report.columns import Columns

    spec, recs = job
    page(job, None)  # this process's first draws (lazy imports) before the one watched
    assert figure_pool.warm(HELPERS)
    for pid in figure_pool.helper_pids():
        os.kill(pid, signal.SIGKILL)
    time.sleep(0.5)
    cols = Columns.from_records(recs)
    ref = weakref.ref(cols)
    gc.disable()
    try:
        job_report_html(
            spec, cols, {"job_id": 7}, name="pool", render=figure_pool.figure_renderer(HELPERS)
        )
        del cols
        assert ref() is None
    finally:
        gc.enable()
