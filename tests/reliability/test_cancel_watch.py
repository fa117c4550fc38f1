"""The running unit's watch (``worker.tasks._Watch``): a cancel stops the unit's
computation, including a cancel that lands between the watch's status check and
its heartbeat (the heartbeat then finds the unit no longer running; the watch must
keep checking rather than give up, or the unit would run to its end)."""

from __future__ import annotations

import time

import pytest

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
        tasks.units.start_unit(s, uid, "w", 360)
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
        tasks.units.start_unit(s, uid, "w", 3)
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
