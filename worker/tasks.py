"""Thin Celery tasks: the DB says what to run, the core runs it, the DB stores it.

``svrobs.run_unit(unit_id)``:

1. ``units.start_unit`` claims the unit (status, lease, attempt counter) in one
   transaction and returns ``(spec, unit payload)``, or ``None`` when there is
   nothing to do (already done or cancelled; a duplicate delivery of a unit that
   is still running claims it again, which only costs an attempt: the results
   are upserted on the cell key);
2. ``svrobs_core.run_unit_result`` computes the records as columns (pure, no I/O);
3. ``units.complete_unit`` upserts them on the cell key and updates progress;
   the job finishes when the DB says every unit is done.

A redelivered or duplicated message is therefore harmless. Transient DB or
broker errors retry the task with exponential backoff (acks_late: the message
is acknowledged only after the task returned, and rejected - so redelivered -
if the worker process is lost). Any other error is recorded with
``units.fail_unit``; it is final once the unit was attempted
``MAX_UNIT_ATTEMPTS`` times, otherwise the task is retried.
"""

from __future__ import annotations

import logging
import os
import socket
import threading
import time
import traceback

from billiard.exceptions import TimeLimitExceeded, WorkerLostError
from celery.exceptions import Retry
from celery.signals import worker_process_init
from celery.worker.request import Request

from service.db import units
from service.db.models import WorkUnit
from service.db.session import dispose_all, session_scope
from svrobs_core import parse_spec
from svrobs_core.runner import run_unit_result
from worker.celery_app import celery_app, settings

# (imported here, in the worker's main process, so that every pool child forks
# with numpy, scipy and the core already loaded)

log = logging.getLogger(__name__)


def _transient_errors() -> tuple[type[BaseException], ...]:
    import kombu.exceptions
    import sqlalchemy.exc

    errs: list[type[BaseException]] = [
        sqlalchemy.exc.OperationalError,  # connection lost, DB restarting, SQLITE_BUSY
        sqlalchemy.exc.InterfaceError,
        sqlalchemy.exc.DisconnectionError,
        kombu.exceptions.OperationalError,  # broker unreachable
        ConnectionError,
        TimeoutError,
    ]
    try:
        import redis.exceptions

        errs += [redis.exceptions.ConnectionError, redis.exceptions.TimeoutError]
    except ImportError:  # pragma: no cover
        pass
    return tuple(errs)


TRANSIENT = _transient_errors()
MAX_RETRIES = 8


def max_attempts() -> int:
    return settings.MAX_UNIT_ATTEMPTS


def lease_seconds() -> int:
    return settings.UNIT_LEASE_SECONDS


@worker_process_init.connect
def _fresh_connections_after_fork(**_kw):
    """Pool children must not share the parent's DB sockets."""
    dispose_all()


def _attempts(unit_id: int) -> int:
    with session_scope(write=False) as s:
        unit = s.get(WorkUnit, unit_id)
        return int(unit.attempts) if unit is not None else 0


def _test_crash_hook(unit_id: int) -> None:
    """TEST-ONLY fault injection, off by default: with ``SVROBS_TEST_CRASH_UNIT=<unit id>``
    in the worker's environment, running that unit kills the worker process (as a
    segfaulting extension would). ``tests/faults`` uses it to check that a unit which
    keeps killing its worker is failed after MAX_UNIT_ATTEMPTS attempts."""
    if settings.TEST_CRASH_UNIT == unit_id:
        os._exit(1)


def execute_unit(unit_id: int, worker_name: str | None = None) -> dict:
    """Claim, compute and store one work unit (the task body, callable without Celery).

    Raises :class:`UnitFailed` (not final) for a failure that should be retried.
    """
    worker_name = worker_name or f"{socket.gethostname()}:{os.getpid()}"
    t0 = time.perf_counter()
    with session_scope() as s:
        claimed = units.start_unit(s, unit_id, worker_name, lease_seconds())
    if claimed is None:
        return {"unit": unit_id, "status": "skipped"}
    spec_dict, payload = claimed
    t1 = time.perf_counter()
    try:
        with _Heartbeat(unit_id, lease_seconds()):
            _test_crash_hook(unit_id)
            records = run_unit_result(parse_spec(spec_dict), payload)
    except Exception as exc:
        attempts = _attempts(unit_id)
        final = bool(max_attempts()) and attempts >= max_attempts()
        error = f"{type(exc).__name__}: {exc}"
        log.error(
            "unit %s failed (attempt %d/%d, final=%s): %s\n%s",
            unit_id,
            attempts,
            max_attempts(),
            final,
            error,
            traceback.format_exc(),
        )
        with session_scope() as s:
            units.fail_unit(s, unit_id, error, final)
        if final:
            return {"unit": unit_id, "status": "failed", "error": error}
        raise UnitFailed(error) from exc
    t2 = time.perf_counter()
    with session_scope() as s:
        units.complete_unit(s, unit_id, records)
    t3 = time.perf_counter()
    # logged by Celery ("succeeded in ...: {...}"): where a unit's time goes
    return {
        "unit": unit_id,
        "status": "done",
        "records": len(records),
        "claim_s": round(t1 - t0, 4),
        "compute_s": round(t2 - t1, 4),
        "store_s": round(t3 - t2, 4),
    }


class _Heartbeat:
    """Extend the unit's lease every lease/3 seconds while it runs (a daemon thread).

    The lease is what lets the relay re-queue a unit whose worker vanished
    without the broker redelivering it; the heartbeat keeps a long unit that
    is still alive from being re-queued. A stuck computation is bounded by
    the Celery time limit, which kills the process (and so the heartbeat).
    """

    def __init__(self, unit_id: int, lease: int):
        self.unit_id = unit_id
        self.lease = lease
        self.interval = max(1.0, min(300.0, lease / 3))
        self._stop = threading.Event()
        self._thread = threading.Thread(
            target=self._run, daemon=True, name=f"svrobs-heartbeat-{unit_id}"
        )

    def __enter__(self):
        self._thread.start()
        return self

    def __exit__(self, *exc):
        self._stop.set()
        self._thread.join(timeout=5)
        return False

    def _run(self):
        while not self._stop.wait(self.interval):
            try:
                with session_scope() as s:
                    if not units.heartbeat_unit(s, self.unit_id, self.lease):
                        return  # no longer running (cancelled job, failed, re-claimed)
            except Exception as exc:  # noqa: BLE001 - the DB may be restarting
                log.warning("unit %s: heartbeat failed: %s", self.unit_id, exc)


class UnitFailed(Exception):
    """A unit's computation failed and may succeed on another attempt."""


class UnitRequest(Request):
    """A ``run_unit`` message as the worker's main process sees it. When the pool
    process running the unit is lost (killed, crashed, hard time limit), the main
    process records why on the unit before the message is requeued, so that a
    unit failed after MAX_UNIT_ATTEMPTS says what killed its worker each time."""

    def on_failure(self, exc_info, send_failed_event=True, return_ok=False):
        try:
            exc = getattr(exc_info, "exception", None)
            exc = getattr(exc, "exc", exc)  # billiard's ExceptionWithTraceback
            if isinstance(exc, (WorkerLostError, TimeLimitExceeded)):
                why = str(exc).split(" Job:")[0]  # billiard appends its own job counter
                _note_lost(int(self.args[0]), f"{type(exc).__name__}: {why}")
        except Exception as err:  # noqa: BLE001 - best effort: never break the requeue
            log.warning("could not record a lost worker on the unit: %s", err)
        return super().on_failure(
            exc_info, send_failed_event=send_failed_event, return_ok=return_ok
        )


def _note_lost(unit_id: int, why: str) -> None:
    """In the main process: a throw-away engine, so that no pooled connection is
    inherited by the pool processes forked later (their after-fork dispose would
    close it under the main process)."""
    from sqlalchemy.orm import Session

    from service.db.session import create_db_engine

    engine = create_db_engine(settings.DATABASE_URL)
    try:
        with Session(engine) as s, s.begin():
            units.note_unit_error(s, unit_id, why)
    finally:
        engine.dispose()


@celery_app.task(
    name="svrobs.run_unit",
    bind=True,
    acks_late=True,
    reject_on_worker_lost=True,
    ignore_result=True,
    max_retries=MAX_RETRIES,
    Request=UnitRequest,
)
def run_unit(self, unit_id: int):
    try:
        return execute_unit(int(unit_id), worker_name=self.request.hostname)
    except Retry:
        raise
    except UnitFailed as exc:
        raise self.retry(
            exc=exc, countdown=_backoff(self.request.retries), max_retries=None
        ) from exc
    except TRANSIENT as exc:
        log.warning(
            "unit %s: transient error, retry %d: %s", unit_id, self.request.retries + 1, exc
        )
        _release(unit_id, f"transient: {type(exc).__name__}: {exc}")
        raise self.retry(exc=exc, countdown=_backoff(self.request.retries)) from exc


def _release(unit_id: int, error: str) -> None:
    """Best effort: hand the unit back (non-final failure) so the retry can claim it."""
    try:
        with session_scope() as s:
            units.fail_unit(s, unit_id, error, False)
    except Exception:  # noqa: BLE001 - the DB may still be down; the lease expires anyway
        pass


def _backoff(retries: int, base: float = 1.0, cap: float = 120.0) -> float:
    import random

    return min(cap, base * 2**retries) * (0.5 + random.random() / 2)


@celery_app.task(name="svrobs.tick", ignore_result=True)
def tick():
    """Normally run inside beat (worker.beat.TickScheduler); a worker can run it too."""
    from worker.tick import run_tick

    return run_tick(celery=celery_app)
