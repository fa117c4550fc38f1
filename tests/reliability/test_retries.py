"""Only transient failures are retried.

A unit whose computation raises MemoryError or a ValueError/SpecError of the core
fails at once (attempt 1) with the reason, and its job with it; a database or broker
that is unreachable (OperationalError, a connection invalidated, a redis/kombu
connection error) propagates to the Celery task, which hands the unit back and
retries it. The real-process counterpart (a worker really running out of memory)
is tests/integration/test_trust.py::test_permanent_failure_fails_at_once.
"""

from __future__ import annotations

import kombu.exceptions
import pytest
import redis.exceptions
import sqlalchemy.exc
from sqlalchemy import select

import svrobs_lab.units
from service.config import get_settings
from service.db import accounts, jobs
from service.db.migrate import upgrade
from service.db.models import Job, Team, WorkUnit
from service.db.session import dispose_all, session_scope
from svrobs_core.errors import DimensionError, SpecError
from tests.service.svc_helpers import TINY_SPEC as SPEC


@pytest.fixture
def tasks(tmp_path, monkeypatch):
    """worker.tasks on a fresh SQLite database (the in-memory broker)."""
    url = f"sqlite:///{tmp_path / 'w.db'}"
    monkeypatch.setenv("SVROBS_DATABASE_URL", url)
    monkeypatch.setenv("SVROBS_BROKER_URL", "memory://")
    get_settings.cache_clear()
    upgrade(url)
    with session_scope(url) as s:
        accounts.create_team(s, "lab")
    import worker.tasks as tasks

    monkeypatch.setattr(tasks, "_dispatch_team", lambda unit_id: None)  # no broker here
    yield tasks
    dispose_all()
    get_settings.cache_clear()


def _unit() -> int:
    with session_scope(get_settings().DATABASE_URL) as s:
        team = s.scalar(select(Team).where(Team.name == "lab"))
        job, _ = jobs.create_job(s, team_id=team.id, user_id=None, spec=SPEC)
        s.flush()
        (uid,) = jobs.unit_ids_of_job(s, job.id)
    return uid


def _state(uid):
    with session_scope(get_settings().DATABASE_URL, write=False) as s:
        u = s.get(WorkUnit, uid)
        j = s.get(Job, u.job_id)
        return u.status, u.attempts, u.error, j.status, j.error


def _raising(exc):
    def run(spec, unit):
        raise exc

    return run


@pytest.mark.parametrize(
    "exc",
    [
        MemoryError("Unable to allocate 29.8 GiB"),
        ValueError("SVD did not converge"),
        SpecError("systems[0].sigma_v", "must be > 0"),
        DimensionError("A", "must be square"),
        RuntimeError("a bug"),
    ],
    ids=lambda e: type(e).__name__,
)
def test_permanent_failures_fail_the_unit_at_once(tasks, monkeypatch, exc):
    uid = _unit()
    monkeypatch.setattr(svrobs_lab.units, "run_unit_result", _raising(exc))
    out = tasks.execute_unit(uid, "w")
    status, attempts, error, job_status, job_error = _state(uid)
    assert out["status"] == "failed"
    assert (status, attempts, job_status) == ("failed", 1, "failed")
    assert error.startswith(type(exc).__name__) and str(exc) in error
    assert type(exc).__name__ in job_error


def _invalidated() -> sqlalchemy.exc.DBAPIError:
    err = sqlalchemy.exc.DBAPIError("SELECT 1", {}, Exception("server closed the connection"))
    err.connection_invalidated = True
    return err


@pytest.mark.parametrize(
    "exc",
    [
        sqlalchemy.exc.OperationalError("COMMIT", {}, Exception("database is locked")),
        _invalidated(),
        redis.exceptions.ConnectionError("Connection refused"),
        kombu.exceptions.OperationalError("broker down"),
    ],
    ids=lambda e: type(e).__name__,
)
def test_transient_failures_are_retried(tasks, monkeypatch, exc):
    """The error propagates out of execute_unit (the unit is not failed); the task
    releases the unit and asks Celery to retry it."""
    assert tasks.is_transient(exc)
    uid = _unit()
    real_complete = tasks.units.complete_unit

    def complete_fails(session, unit_id, records):
        raise exc

    monkeypatch.setattr(tasks.units, "complete_unit", complete_fails)
    with pytest.raises(type(exc)):
        tasks.execute_unit(uid, "w")
    assert _state(uid)[0] == "running"  # not failed: the task decides
    retried = []

    def fake_retry(exc=None, countdown=None, **kw):
        retried.append((type(exc), countdown))
        return RuntimeError("retry scheduled")

    monkeypatch.setattr(tasks.run_unit, "retry", fake_retry)
    with pytest.raises(RuntimeError, match="retry scheduled"):
        tasks.run_unit.run(uid)
    assert retried and retried[0][0] is type(exc)
    status, _, error, job_status, _ = _state(uid)
    assert (status, job_status) == ("pending", "running") and error.startswith("transient:")
    # the next attempt succeeds
    monkeypatch.setattr(tasks.units, "complete_unit", real_complete)
    assert tasks.execute_unit(uid, "w")["status"] == "done"
    assert _state(uid)[3] == "succeeded"


def test_integrity_and_programming_errors_are_not_transient(tasks):
    for exc in (
        sqlalchemy.exc.IntegrityError("INSERT", {}, Exception("duplicate key")),
        sqlalchemy.exc.ProgrammingError("SELECT", {}, Exception("no such column")),
        sqlalchemy.exc.DBAPIError("SELECT", {}, Exception("not a disconnect")),
    ):
        assert not tasks.is_transient(exc)
