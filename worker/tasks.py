"""Thin Celery tasks: the DB says what to run, the core runs it, the DB stores it.

``svrobs.run_unit(unit_id)``:

1. ``units.start_unit`` claims the unit (status, lease, attempt counter) in one
   transaction and returns ``(spec, unit payload)``, or ``None`` when there is
   nothing to do (already done or cancelled; a duplicate delivery of a unit that
   is still running claims it again, which only costs an attempt: the results
   are upserted on the cell key);
2. ``svrobs_lab.units.compute_unit`` computes the records as columns (the core's
   ``run_unit_result``, or for a dataset job ``run_measured_unit`` on the arrays
   read from the database);
3. ``units.complete_unit`` upserts them on the cell key and updates progress;
   the job finishes when the DB says every unit is done. A dataset job's
   validation is stored after its first unit (``svrobs_lab.units.after_unit``).

A redelivered or duplicated message is therefore harmless; one whose argument is
not a unit id (``is_unit_id``) is logged and dropped. Only transient
errors (the DB or the broker unreachable: ``is_transient``) retry the task, with
exponential backoff (acks_late: the message is acknowledged only after the task
returned, and rejected - so redelivered - if the worker process is lost; a unit
that keeps killing its worker is failed after ``MAX_UNIT_ATTEMPTS`` starts). Any
other error (MemoryError, a ValueError of the core...) would fail again: it fails
the unit and its job at once, with the reason (``units.fail_unit``). A unit
cancelled (or deleted) while it runs stops within about ``CANCEL_CHECK_SECONDS``
(``_Watch``), even inside a long solver call: its pool process is then ended.
"""

from __future__ import annotations

import logging
import os
import signal
import socket
import threading
import time
import traceback

from billiard.exceptions import TimeLimitExceeded, WorkerLostError
from celery import current_app, shared_task
from celery.exceptions import Retry
from celery.signals import worker_process_init
from celery.worker.request import Request

from service.config import get_settings
from service.db import units
from service.db.session import dispose_all
from svrobs_lab.auth import MAX_ID
from svrobs_lab.units import after_unit, compute_unit
from worker.tick import run_tick, session_scope

settings = get_settings()

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


def lease_seconds() -> int:
    return settings.UNIT_LEASE_SECONDS


_IN_POOL_CHILD = False  # set in a prefork pool process: it may end itself (_Watch)


@worker_process_init.connect
def _fresh_connections_after_fork(**_kw):
    """Pool children must not share the parent's DB sockets."""
    global _IN_POOL_CHILD
    _IN_POOL_CHILD = True
    dispose_all()


def _test_crash_hook(unit_id: int) -> None:
    """TEST-ONLY fault injection, off by default: with ``SVROBS_TEST_CRASH_UNIT=<unit id>``
    in the worker's environment, running that unit kills the worker process (as a
    segfaulting extension would). ``tests/faults`` uses it to check that a unit which
    keeps killing its worker is failed after MAX_UNIT_ATTEMPTS attempts."""
    if settings.TEST_CRASH_UNIT == unit_id:
        os._exit(1)


def is_transient(exc: BaseException) -> bool:
    """A failure that another attempt may not meet: the database or the broker was
    unreachable (a dropped connection, a restart, SQLITE_BUSY, a deadlock). Anything
    else (MemoryError, the core's SpecError/DimensionError/ValueError, a bug) fails
    the same way every time."""
    import sqlalchemy.exc

    if isinstance(exc, TRANSIENT):
        return True
    return isinstance(exc, sqlalchemy.exc.DBAPIError) and bool(exc.connection_invalidated)


def execute_unit(unit_id: int, worker_name: str | None = None) -> dict:
    """Claim, compute and store one work unit (the task body, callable without Celery).

    A transient error (:func:`is_transient`) propagates (the task retries it); any
    other failure fails the unit and its job at once, with the reason. A unit
    cancelled while it runs (its job cancelled or failed) stops within
    SVROBS_CANCEL_CHECK_SECONDS and stores nothing. After the unit, the team's next
    units are published (fair share, :func:`service.db.outbox.dispatch`).
    """
    worker_name = worker_name or f"{socket.gethostname()}:{os.getpid()}"
    t0 = time.perf_counter()
    with session_scope() as s:
        claimed = units.start_unit(
            s, unit_id, worker_name, lease_seconds(), max_attempts=get_settings().MAX_UNIT_ATTEMPTS
        )
    if claimed is None:  # done, cancelled, or just failed after MAX_UNIT_ATTEMPTS
        _dispatch_team(unit_id)
        return {"unit": unit_id, "status": "skipped"}
    spec_dict, payload = claimed
    t1 = time.perf_counter()
    try:
        with _Watch(unit_id, lease_seconds(), settings.CANCEL_CHECK_SECONDS, kill=_IN_POOL_CHILD):
            _test_crash_hook(unit_id)
            records, data = compute_unit(session_scope, spec_dict, payload)
        t2 = time.perf_counter()
        with session_scope() as s:
            stored = units.complete_unit(s, unit_id, records)
        if stored:
            after_unit(session_scope, unit_id, spec_dict, data)
    except UnitCancelled:
        log.info("unit %s: cancelled while running; stopped after %.2f s", unit_id, _since(t1))
        _dispatch_team(unit_id)
        return {"unit": unit_id, "status": "cancelled", "run_s": round(_since(t1), 4)}
    except Exception as exc:
        if is_transient(exc):
            raise
        error = f"{type(exc).__name__}: {exc}"
        log.error("unit %s failed (final): %s\n%s", unit_id, error, traceback.format_exc())
        with session_scope() as s:
            units.fail_unit(s, unit_id, error, True)
        _dispatch_team(unit_id)
        return {"unit": unit_id, "status": "failed", "error": error}
    t3 = time.perf_counter()
    _dispatch_team(unit_id)
    # logged by Celery ("succeeded in ...: {...}"): where a unit's time goes
    return {
        "unit": unit_id,
        "status": "done" if stored else "cancelled",
        "records": len(records),
        "claim_s": round(t1 - t0, 4),
        "compute_s": round(t2 - t1, 4),
        "store_s": round(t3 - t2, 4),
    }


def _since(t: float) -> float:
    return time.perf_counter() - t


def _dispatch_team(unit_id: int) -> None:
    """Publish the next units of the unit's team (its slot is free); best effort: the
    tick's relay publishes whatever this misses."""
    from service.broker import publish_units
    from svrobs_lab.dispatch import dispatch_team_of_unit

    try:
        dispatch_team_of_unit(
            get_settings(), session_scope, lambda ids: publish_units(current_app, ids), unit_id
        )
    except Exception as exc:  # noqa: BLE001 - the unit's own outcome is stored already
        log.warning("unit %s: publishing its team's next units failed: %s", unit_id, exc)


class UnitCancelled(BaseException):
    """Raised in a running unit's thread when its status became ``cancelled`` (a
    BaseException, like KeyboardInterrupt: no ``except Exception`` in the core
    swallows it)."""


class _Watch:
    """While a unit computes: a daemon thread that extends its lease every lease/3
    seconds and checks every ``check`` seconds that it is still wanted.

    The lease is what lets the relay re-queue a unit whose worker vanished without
    the broker redelivering it; the heartbeat keeps a long unit that is still alive
    from being re-queued. When the unit's status became ``cancelled`` (its job was
    cancelled or failed) or its row is gone (the job was deleted after a cancel), the
    thread interrupts the computation: a signal to the unit's (main) thread, whose
    handler raises :class:`UnitCancelled` between two Python-level steps of the core.
    A computation still running ``GRACE`` seconds later is inside one long native call
    (a cvxpy/Clarabel solve): with ``kill`` (a prefork pool process) the thread then
    SIGKILLs its own process, having stored nothing; the pool starts a new process,
    and the message, rejected as the worker was lost (acks_late), is redelivered and
    skipped (its unit is cancelled or gone). Otherwise a stuck computation is bounded
    by the Celery time limit.
    """

    SIGNAL = signal.SIGUSR2
    GRACE = 0.3  # seconds a cancelled computation gets to stop before its process ends

    def __init__(self, unit_id: int, lease: int, check: float = 1.0, *, kill: bool = False):
        self.unit_id = unit_id
        self.kill = kill
        self.lease = lease
        self.beat = max(1.0, min(300.0, lease / 3))
        self.check = max(0.05, min(check, self.beat)) if check > 0 else self.beat
        self._stop = threading.Event()
        self._cancelled = False
        self._old_handler = None
        self._target = threading.get_ident()
        self._can_signal = threading.current_thread() is threading.main_thread()
        self._thread = threading.Thread(
            target=self._run, daemon=True, name=f"svrobs-watch-{unit_id}"
        )

    def __enter__(self):
        if self._can_signal:
            self._old_handler = signal.signal(self.SIGNAL, self._on_signal)
        self._thread.start()
        return self

    def __exit__(self, *exc):
        self._stop.set()
        self._thread.join(timeout=10)
        if self._can_signal:
            signal.signal(self.SIGNAL, self._old_handler or signal.SIG_DFL)
        return False

    def _on_signal(self, signum, frame):
        if self._cancelled and not self._stop.is_set():
            raise UnitCancelled(f"unit {self.unit_id} was cancelled")

    def _run(self):
        next_beat: float | None = time.monotonic() + self.beat
        while not self._stop.wait(self.check):
            try:
                with session_scope(write=False) as s:
                    status = units.unit_status(s, self.unit_id)
                if status in ("cancelled", None):  # None: deleted with its job
                    log.info("unit %s: cancelled; stopping it", self.unit_id)
                    self._cancelled = True
                    if self._can_signal:
                        signal.pthread_kill(self._target, self.SIGNAL)
                    if self.kill and not self._stop.wait(self.GRACE):
                        self._end_process()
                    return
                if next_beat is not None and time.monotonic() >= next_beat:
                    next_beat = time.monotonic() + self.beat
                    with session_scope() as s:
                        if not units.heartbeat_unit(s, self.unit_id, self.lease):
                            # no longer running: cancelled since the check above (the
                            # next check stops it), failed or re-claimed elsewhere
                            next_beat = None
            except Exception as exc:  # noqa: BLE001 - the DB may be restarting
                log.warning("unit %s: heartbeat failed: %s", self.unit_id, exc)

    def _end_process(self) -> None:
        log.warning(
            "unit %s: still computing %.1f s after its cancel (a native call); "
            "ending pool process %s",
            self.unit_id,
            self.GRACE,
            os.getpid(),
        )
        for h in logging.getLogger().handlers:
            h.flush()
        os.kill(os.getpid(), signal.SIGKILL)


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


@shared_task(
    name="svrobs.run_unit",
    bind=True,
    acks_late=True,
    reject_on_worker_lost=True,
    ignore_result=True,
    max_retries=MAX_RETRIES,
    Request=UnitRequest,
)
def run_unit(self, unit_id: int):
    if not is_unit_id(unit_id):
        log.error(
            "run_unit message %s dropped: %s is not a unit id (an integer from 1 to %d)",
            self.request.id,
            repr(unit_id)[:100],
            MAX_ID,
        )
        return {"unit": None, "status": "invalid"}
    try:
        return execute_unit(unit_id, worker_name=self.request.hostname)
    except Retry:
        raise
    except Exception as exc:
        if not is_transient(exc):
            raise  # claiming the unit failed for good: Celery logs it, the message is acked
        log.warning(
            "unit %s: transient error, retry %d: %s", unit_id, self.request.retries + 1, exc
        )
        _release(unit_id, f"transient: {type(exc).__name__}: {exc}")
        raise self.retry(exc=exc, countdown=_backoff(self.request.retries)) from exc


def is_unit_id(value: object) -> bool:
    """An id the work_units table can hold (a 32-bit column; bool is not an id)."""
    return type(value) is int and 1 <= value <= MAX_ID


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


@shared_task(name="svrobs.tick", bind=True, ignore_result=True)
def tick(self):
    """Normally run inside beat (worker.beat.TickScheduler); a worker can run it too."""
    return run_tick(celery=self.app, reports=False)  # beat's process builds the reports
