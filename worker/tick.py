"""The tick: due schedules -> jobs, the outbox relay, retention, and (in a background
thread) the stored reports of newly finished jobs.

``run_tick`` is what beat runs every TICK_SECONDS (in the beat process itself:
see :mod:`worker.beat`); it is safe to run from any number of processes at
once:

* ``schedules.create_due_schedule_jobs`` is keyed on (schedule, due time), so a
  doubled or restarted beat never creates a sweep twice;
* the relay publishes work units that were committed but never published
  (the API's publish failed, e.g. the broker was down, or the team had its
  fair share of units in flight) or whose lease ran out (the worker died and
  the broker did not redeliver), marking them first under the teams' locks.
  Publishing twice is harmless: ``units.start_unit`` lets one delivery run a
  unit and the other skip it, and results are upserted on the cell key.
"""

from __future__ import annotations

import atexit
import logging
import os
import threading
import time
from contextlib import nullcontext
from datetime import datetime, timedelta
from pathlib import Path

from service.report_crashes import FILE_NAME, CrashRecord

log = logging.getLogger(__name__)

RELAY_BATCH = 500
RELAY_MAX_PER_TICK = 20_000
PRUNE_MAX_PER_TICK = 5
REPORTS_PER_TICK = 2
REPORT_RECENT_DAYS = 2  # reports are built ahead for jobs finished this recently
REPORT_EXIT_WAIT_SECONDS = 8.0  # inside the supervisor's 10 s stop grace
_report_thread: threading.Thread | None = None
_stop_reports = threading.Event()  # set at exit: the report thread ends after its build
REPORT_RETRY_SECONDS = 600.0  # a job whose report build failed is tried again after this
_failed_reports: dict[int, float] = {}  # job id -> when its build failed (monotonic)
# builds that ended the process (service.report_crashes); set by the report thread's start
_crash_record: CrashRecord | None = None


def session_scope(write: bool = True):
    """A committing session context (:func:`service.db.session.session_scope`) on
    SVROBS_DATABASE_URL, read when called."""
    from service.config import get_settings
    from service.db import session

    return session.session_scope(get_settings().DATABASE_URL, write=write)


def create_due_jobs(now: datetime | None = None) -> list[int]:
    from service.config import get_settings
    from service.db.clock import db_now
    from svrobs_lab import schedules

    with session_scope() as s:
        jobs = schedules.create_due_jobs(get_settings(), s, now or db_now(s))
        ids = [j if isinstance(j, int) else j.id for j in jobs or ()]
    if ids:
        log.info("tick: created jobs %s for due schedules", ids)
    return ids


def relay(celery=None, limit: int = RELAY_MAX_PER_TICK) -> int:
    """Publish units that need it, every team within its fair share
    (:func:`service.db.outbox.dispatch`); returns how many were published.

    Units published before the broker's current data began (``broker_epoch``: a
    Redis restarted without persistence lost them) are re-published at once. Every
    time compared is the database's (leases, publication times; the broker's epoch
    translated into it), never this host's clock.
    """
    from service.broker import broker_epoch, publish_units
    from service.config import get_settings
    from service.db.clock import db_now
    from svrobs_lab import dispatch

    if celery is None:  # a tick run outside a worker or beat: a publisher of its own
        from service.broker import make_celery

        celery = make_celery(get_settings())
    with session_scope(write=False) as s:
        start = db_now(s)
    # raises if the broker is unreachable: retried next tick
    epoch = broker_epoch(celery, now=start)
    sent = dispatch.relay(
        get_settings(),
        session_scope,
        lambda ids: publish_units(celery, ids),
        lost_before=epoch,
        limit=limit,
        batch=RELAY_BATCH,
    )
    if sent:
        log.info("tick: relayed %d work units", sent)
    return sent


def prune_expired(limit: int = PRUNE_MAX_PER_TICK, scope=None) -> list[int]:
    """Retention: drop the cell rows of scheduled jobs past their team's retention
    period (``service.db.retention``), after storing the report if it is not yet;
    returns the pruned jobs. Read, then write: the report is built outside the
    write transaction (on SQLite a writer blocks every other writer). ``scope``:
    ``scope(write=...)`` -> a committing session context (default :func:`session_scope`)."""
    from service.db import retention
    from svrobs_lab.reports import store_if_missing

    scope = scope or session_scope
    with scope(write=False) as s:
        ids = retention.due_for_pruning(s, limit)
    done = []
    for job_id in ids:
        with scope(write=False) as r, scope(write=True) as w:
            store_if_missing(r, w, job_id)
            n = retention.prune_job(w, job_id)
        log.info("tick: retention dropped the %d cell rows of job %s", n, job_id)
        done.append(job_id)
    return done


def build_reports(limit: int = REPORTS_PER_TICK, scope=None) -> list[int]:
    """Store the reports of recently finished jobs that have none, or one of an old
    page layout (``jobs_without_report``), so that the API serves them as stored
    from the first request; returns the jobs done. A job whose
    build fails is logged once and left alone for REPORT_RETRY_SECONDS (its report is
    then built at its first request), so it holds up neither the others nor the log;
    a database that is unreachable is raised (the caller polls again). Once the
    process is stopping, no build starts, and none renders after its read. Each build
    is marked in flight in the crash record (service.report_crashes) when the report
    thread has one."""
    from sqlalchemy.exc import DBAPIError, IntegrityError

    from service.db.clock import db_now
    from service.db.reports import jobs_without_report
    from svrobs_lab.report_html import REPORT_LAYOUT
    from svrobs_lab.reports import store_if_missing

    scope = scope or session_scope
    now = time.monotonic()
    for job_id, failed_at in list(_failed_reports.items()):
        if now - failed_at >= REPORT_RETRY_SECONDS:
            del _failed_reports[job_id]
    record = _crash_record
    skip = list(_failed_reports) + (record.given_up() if record is not None else [])
    with scope(write=False) as s:
        since = db_now(s) - timedelta(days=REPORT_RECENT_DAYS)
        ids = jobs_without_report(s, limit, layout=REPORT_LAYOUT, finished_after=since, skip=skip)
    done = []
    for job_id in ids:
        if _stop_reports.is_set():  # the process is stopping: no new build
            break
        mark = record.in_flight(job_id) if record is not None else nullcontext()
        try:
            with mark, scope(write=False) as r, scope(write=True) as w:
                if store_if_missing(r, w, job_id, proceed=lambda: not _stop_reports.is_set()):
                    done.append(job_id)
        except IntegrityError:  # an API request stored it meanwhile: the same page
            continue
        except DBAPIError as exc:
            if _database_down(exc, scope):  # not this job's: the next poll tries again
                raise
            _set_aside(job_id)  # this job's (e.g. a timeout on its read)
        except Exception:  # noqa: BLE001 - logged with its traceback by _set_aside
            _set_aside(job_id)
    if done:
        log.info("tick: stored the reports of jobs %s", done)
    return done


def _set_aside(job_id: int) -> None:
    """Log a job's failed build with its traceback, and skip the job for
    REPORT_RETRY_SECONDS."""
    log.exception(
        "tick: the report of job %s failed; retried in %.0f s", job_id, REPORT_RETRY_SECONDS
    )
    _failed_reports[job_id] = time.monotonic()


def _database_down(exc: Exception, scope) -> bool:
    """Whether a database error during a build means the database is unreachable (its
    connection was lost, or a new one cannot run ``SELECT 1``) rather than a failure
    of that job's build."""
    from sqlalchemy import text
    from sqlalchemy.exc import DBAPIError

    if getattr(exc, "connection_invalidated", False):
        return True
    try:
        with scope(write=False) as s:
            s.execute(text("SELECT 1"))
    except DBAPIError:
        return True
    return False


def start_report_builds() -> bool:
    """:func:`build_reports` in a background thread of this (beat) process, again
    every ``REPORT_POLL_SECONDS`` (at least once a ``TICK_SECONDS``) until the process exits:
    a report of a large job takes seconds, the tick must not wait for it, and a
    finished job's report should be stored before anyone asks for it. One thread
    per process; False when it already runs."""
    global _report_thread, _crash_record
    if _report_thread is not None and _report_thread.is_alive():
        return False
    from service.config import get_settings
    from svrobs_lab import figure_pool

    settings = get_settings()
    every = min(settings.REPORT_POLL_SECONDS, settings.TICK_SECONDS)
    figure_pool.configure(settings.REPORT_RENDER_PROCESSES)
    if _crash_record is None:  # the first start of this process: did the last one crash?
        _crash_record = CrashRecord(Path(settings.VAR_DIR) / FILE_NAME)
        crashed = _crash_record.recover()
        if crashed is not None:
            _failed_reports[crashed] = time.monotonic()

    def run():
        from sqlalchemy.exc import DBAPIError

        while not _stop_reports.is_set():
            try:
                build_reports()
            except DBAPIError as exc:  # the database is down: retried at the next poll
                log.warning("tick: building reports failed (%s); will retry", type(exc).__name__)
            except Exception:  # retried at the next poll (logged with its traceback)
                log.exception("tick: building reports failed; will retry")
            _stop_reports.wait(every)

    if _report_thread is None:  # the first build of this process
        atexit.register(_stop_at_exit)
    _stop_reports.clear()
    _report_thread = threading.Thread(target=run, name="svrobs-reports", daemon=True)
    _report_thread.start()
    return True


def wait_for_report_builds(timeout: float = REPORT_EXIT_WAIT_SECONDS) -> bool:
    """At exit: stop the report thread, letting a build in flight finish (its write
    is one transaction, so a build cut short stores nothing). Without it the
    interpreter would stop the daemon thread inside a native call, which aborts the
    process ("terminate called without an active exception"). True when no build is
    left running."""
    _stop_reports.set()
    t = _report_thread
    if t is None or not t.is_alive():
        return True
    t.join(min(0.5, timeout))  # an idle thread ends at once
    if t.is_alive():
        log.info("tick: waiting up to %.0f s for the report build in flight", timeout)
        t.join(max(0.0, timeout - 0.5))
    return not t.is_alive()


def _stop_at_exit() -> None:
    """At exit: :func:`wait_for_report_builds`; a build still running after that is
    abandoned (its write, one transaction, was not committed: nothing is stored) by
    ending the process at once, so that the interpreter's shutdown never meets the
    thread inside a native call."""
    if wait_for_report_builds(REPORT_EXIT_WAIT_SECONDS):
        return
    log.warning("tick: the report build in flight was abandoned at exit")
    if _crash_record is not None:  # abandoned, not crashed
        _crash_record.clear()
    logging.shutdown()  # the handlers flushed: os._exit skips the atexit handlers left
    os._exit(0)


def run_tick(now: datetime | None = None, celery=None, *, reports: bool = True) -> dict:
    """One tick. Each part is independent: a failing relay never stops schedules,
    nor does retention; reports of finished jobs are built in the background."""
    out: dict = {"created": [], "relayed": 0, "pruned": [], "errors": []}
    try:
        out["created"] = create_due_jobs(now)
    except Exception as exc:
        log.exception("tick: creating scheduled jobs failed")
        out["errors"].append(f"schedules: {type(exc).__name__}: {exc}")
    try:
        out["relayed"] = relay(celery)
    except Exception as exc:  # noqa: BLE001 - the broker or the DB may be down: the next tick retries
        log.warning("tick: relay failed (%s: %s); will retry next tick", type(exc).__name__, exc)
        out["errors"].append(f"relay: {type(exc).__name__}: {exc}")
    try:
        out["pruned"] = prune_expired()
    except Exception as exc:  # logged with its traceback; the next tick retries
        log.exception("tick: retention failed; will retry next tick")
        out["errors"].append(f"retention: {type(exc).__name__}: {exc}")
    if reports:
        start_report_builds()
    return out
