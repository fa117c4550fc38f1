"""The running unit's watch (``worker.tasks._Watch``): a cancel stops the unit's
computation, including a cancel that lands between the watch's status check and
its heartbeat (the heartbeat then finds the unit no longer running; the watch must
keep checking rather than give up, or the unit would run to its end); a deleted unit
counts as cancelled; in a pool process, a computation that does not stop at the
interrupt (one long native call) ends its process."""

from __future__ import annotations

import multiprocessing
import signal
import time

import pytest

from service.db import jobs
from service.db.job_delete import delete_job
from service.db.models import Job, WorkUnit
from tests.reliability.test_retries import _unit, tasks  # noqa: F401 - the fixture


def _compute_until_cancelled(tasks, uid, lease, seconds=8.0):  # noqa: F811
    """Python-level steps, as the core's stages are; -> seconds until UnitCancelled."""
    t0 = time.monotonic()
    with pytest.raises(tasks.UnitCancelled):
        with tasks._Watch(uid, lease, check=0.05):
            while time.monotonic() - t0 < seconds:
                time.sleep(0.01)
    return time.monotonic() - t0


def test_cancel_stops_the_computation(tasks, monkeypatch):  # noqa: F811
    uid = _unit()
    with tasks.session_scope() as s:
        tasks.units.start_unit(s, uid, "w", 360, max_attempts=0)
    real = tasks.units.unit_status
    calls = []

    def status(session, unit_id):  # the real read, and "cancelled" from the third check
        calls.append(real(session, unit_id))
        return "cancelled" if len(calls) >= 3 else calls[-1]

    monkeypatch.setattr(tasks.units, "unit_status", status)
    took = _compute_until_cancelled(tasks, uid, lease=360)
    assert calls == ["running"] * 3 and took < 8.0


def test_cancel_between_check_and_heartbeat_still_stops_it(tasks, monkeypatch):  # noqa: F811
    """The first heartbeat (lease 3 s: one per second) meets the unit cancelled just
    after the check said running."""
    uid = _unit()
    with tasks.session_scope() as s:
        tasks.units.start_unit(s, uid, "w", 3, max_attempts=0)
    beats = []

    def status(session, unit_id):
        return "cancelled" if beats else "running"

    def heartbeat(session, unit_id, lease):
        beats.append(unit_id)
        return False  # cancelled meanwhile: no longer running

    monkeypatch.setattr(tasks.units, "unit_status", status)
    monkeypatch.setattr(tasks.units, "heartbeat_unit", heartbeat)
    took = _compute_until_cancelled(tasks, uid, lease=3)
    assert beats and took < 8.0


def test_a_deleted_unit_counts_as_cancelled(tasks):  # noqa: F811
    """Cancel then delete: the unit's row is gone; the watch stops the computation."""
    uid = _unit()
    with tasks.session_scope() as s:
        tasks.units.start_unit(s, uid, "w", 360, max_attempts=0)
        job = s.get(Job, s.get(WorkUnit, uid).job_id)
        jobs.cancel_job(s, job)
        delete_job(s, job)
    with tasks.session_scope(write=False) as s:
        assert tasks.units.unit_status(s, uid) is None
    assert _compute_until_cancelled(tasks, uid, lease=360) < 8.0


def _swallowing_child(tasks, uid: int, out) -> None:  # noqa: F811
    """A pool process whose computation swallows the interrupt (as a native call that
    does not return to Python would ignore it): only ending the process stops it."""
    tasks.dispose_all()  # the parent's connections stay the parent's
    out.put("started")
    with tasks._Watch(uid, 360, check=0.05, kill=True):
        t0 = time.monotonic()
        while time.monotonic() - t0 < 30:
            try:
                time.sleep(0.01)
            except tasks.UnitCancelled:
                out.put("interrupted")
    out.put("ran to its end")


def test_a_computation_that_ignores_the_interrupt_ends_its_process(tasks):  # noqa: F811
    uid = _unit()
    with tasks.session_scope() as s:
        tasks.units.start_unit(s, uid, "w", 360, max_attempts=0)
    ctx = multiprocessing.get_context("fork")
    out = ctx.Queue()
    child = ctx.Process(target=_swallowing_child, args=(tasks, uid, out))
    child.start()
    try:
        assert out.get(timeout=30) == "started"
        with tasks.session_scope() as s:
            jobs.cancel_job(s, s.get(Job, s.get(WorkUnit, uid).job_id))
        child.join(timeout=30)
        assert child.exitcode == -signal.SIGKILL
        seen = []
        while not out.empty():
            seen.append(out.get())
        assert seen == ["interrupted"]  # the signal came first, then the kill
    finally:
        if child.is_alive():
            child.kill()
            child.join()
