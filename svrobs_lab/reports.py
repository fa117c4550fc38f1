"""A job's HTML report, built once per finished job and then served as stored.

A running job's report is built on each request (it changes); a finished job's
is built at its first request (or beforehand, by the retention tick before it
prunes the job's rows: :func:`store_if_missing`) and stored in ``job_reports``.
Concurrent requests for the same job wait for one build; at most ``BUILD_SLOTS``
builds run at once in a process, so memory stays bounded however many reports
are asked for. The build reads the rows as columns (``service.db.reports``).
"""

from __future__ import annotations

import ctypes
import gc
import logging
import threading
from collections import defaultdict
from collections.abc import Callable
from contextlib import closing

from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session

from service.db.models import Job
from service.db.reports import is_final, load_columns, store_report, stored_report
from svrobs_lab.auth import Caller
from svrobs_lab.dispatch import SessionFactory
from svrobs_lab.jobs import team_job
from svrobs_lab.report_html import job_report_html

log = logging.getLogger(__name__)

BUILD_SLOTS = threading.BoundedSemaphore(1)
_job_locks: defaultdict[int, threading.Lock] = defaultdict(threading.Lock)
_locks_guard = threading.Lock()


def _job_lock(job_id: int) -> threading.Lock:
    with _locks_guard:
        return _job_locks[job_id]


def _release_memory() -> None:
    """Hand the build's freed arrays back to the OS (glibc keeps them otherwise, and
    the API process's resident size would stay at its peak)."""
    gc.collect()
    try:
        ctypes.CDLL("libc.so.6").malloc_trim(0)
    except (OSError, AttributeError):  # not glibc
        pass


def build_job_report(session: Session, job: Job) -> tuple[str, int]:
    """(HTML, number of records) of a job, from its stored records read as columns."""
    try:
        return _build(session, job)
    finally:
        _release_memory()


def _build(session: Session, job: Job) -> tuple[str, int]:
    cols = load_columns(session, job.id)
    provenance = {
        **(job.provenance or {}),
        "job_id": job.id,
        "status": job.status,
        "progress": f"{job.progress_done}/{job.progress_total} units",
    }
    html = job_report_html(job.spec, cols, provenance, name=job.name or f"job-{job.id}")
    return html, len(cols)


def job_report(session: Session, job: Job, write_session: Callable[[], Session]) -> str:
    """The job's report: stored if the job is finished (built from ``session``, a
    reading one, and stored through a ``write_session()`` on first use)."""
    if not is_final(job):
        with BUILD_SLOTS:
            return build_job_report(session, job)[0]
    job_id = job.id
    row = stored_report(session, job_id)
    if row is not None:
        return row.html
    with _job_lock(job_id):
        session.rollback()  # a fresh snapshot: another request may have stored it meanwhile
        row = stored_report(session, job_id)
        if row is not None:
            return row.html
        with BUILD_SLOTS:
            html, n = build_job_report(session, session.get(Job, job_id))
        session.rollback()  # the read is over (and a test's shared connection is released)
        with closing(write_session()) as w:
            try:
                store_report(w, job_id, html, n)
                w.commit()
                log.info("stored the report of job %s (%d records)", job_id, n)
            except IntegrityError:  # another process stored it first: the same page
                w.rollback()
    with _locks_guard:  # stored: later requests never wait on this lock
        _job_locks.pop(job_id, None)
    return html


def store_if_missing(read_session: Session, write_session: Session, job_id: int) -> bool:
    """Build a finished job's report (reading with ``read_session``) and add it to
    ``write_session`` unless one is stored; True when it built one."""
    job = read_session.get(Job, job_id)
    if job is None or not is_final(job) or stored_report(read_session, job_id) is not None:
        return False
    with BUILD_SLOTS:
        html, n = build_job_report(read_session, job)
    read_session.rollback()
    if stored_report(write_session, job_id) is None:
        store_report(write_session, job_id, html, n)
    return True


def caller_job_report(
    session: Session, caller: Caller, job_id: int, session_factory: SessionFactory
) -> str:
    """The report of the caller's job (:func:`job_report`; NotFound for another team's)."""
    job = team_job(session, caller, job_id)
    return job_report(session, job, lambda: session_factory(True))
