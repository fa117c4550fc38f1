"""A job's HTML report, built once per finished job and then served as stored.

A finished job's report is built at its first request (or beforehand, by the
retention tick before it prunes the job's rows: :func:`store_if_missing`) and
stored in ``job_reports`` with the page layout it was built with
(:data:`~svrobs_lab.report_html.REPORT_LAYOUT`); a stored report of another layout
counts as missing and is built again, unless the job's rows were pruned (then it
is the only copy, served as stored). A running job's is built again only when its progress
changed (docs/security.md#reports-of-running-jobs). A request reads the job, closes its
database session, and then waits for or runs the one build of that job
(:class:`~svrobs_lab.report_builds.ReportBuilds`: single-flight, bounded per team);
the build reads the rows in a short session of its own (as columns:
``service.db.reports``), renders with no connection held, and stores a finished
job's page through a new session. At most ``BUILD_SLOTS`` builds render at once in
a process, so memory stays bounded however many reports are asked for.
"""

from __future__ import annotations

import ctypes
import gc
import logging
import threading
from collections.abc import Callable
from contextlib import closing
from dataclasses import dataclass
from datetime import datetime
from typing import Any, NamedTuple

from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session

from service.db.models import JOB_ACTIVE, Job
from service.db.reports import is_final, load_columns, servable_report, store_report
from svrobs_core.report.columns import Columns
from svrobs_lab.auth import Caller
from svrobs_lab.dispatch import SessionFactory
from svrobs_lab.figure_pool import figure_renderer
from svrobs_lab.jobs import team_job
from svrobs_lab.report_builds import ReportBuilds
from svrobs_lab.report_html import REPORT_LAYOUT, job_report_html

log = logging.getLogger(__name__)

BUILD_SLOTS = threading.BoundedSemaphore(1)
# the builds of callers that pass none (the CLI, tests); the API passes its app's
DEFAULT_BUILDS = ReportBuilds(per_team=2, waiters_per_team=8)


class JobKey(NamedTuple):
    """What is built of one job (``report``, ``validation``), for the builds in memory:
    the job is known by its id and creation time. SQLite gives the id of a deleted job
    to the next job made (another team's, maybe), which must not be served the deleted
    job's kept report."""

    what: str
    id: int
    created_at: datetime

    def __str__(self) -> str:  # in the builds' log lines
        return f"the {self.what} of job {self.id} (made {self.created_at.isoformat()})"


@dataclass(frozen=True)
class JobSnapshot:
    """What a report is built from, read before the request's session is closed."""

    id: int
    created_at: datetime
    team_id: int
    status: str
    progress_done: int
    progress_total: int
    cells_done: int
    spec: dict[str, Any]
    provenance: dict[str, Any]
    name: str

    @classmethod
    def of(cls, job: Job) -> JobSnapshot:
        return cls(
            id=job.id,
            created_at=job.created_at,
            team_id=job.team_id,
            status=job.status,
            progress_done=job.progress_done,
            progress_total=job.progress_total,
            cells_done=job.cells_done or 0,
            spec=dict(job.spec),
            provenance=dict(job.provenance or {}),
            name=job.name or f"job-{job.id}",
        )

    @property
    def key(self) -> JobKey:
        return JobKey("report", self.id, self.created_at)

    @property
    def version(self) -> tuple:
        """The report changes only when one of these does."""
        return (self.status, self.progress_done, self.progress_total, self.cells_done)

    @property
    def final(self) -> bool:
        return self.status not in JOB_ACTIVE


def _release_memory() -> None:
    """Hand the build's freed arrays back to the OS (glibc keeps them otherwise, and
    the API process's resident size would stay at its peak)."""
    gc.collect()
    try:
        ctypes.CDLL("libc.so.6").malloc_trim(0)
    except (OSError, AttributeError):  # not glibc
        pass


def _render(job: JobSnapshot, cols: Columns) -> str:
    provenance = {
        **job.provenance,
        "job_id": job.id,
        "status": job.status,
        "progress": f"{job.progress_done}/{job.progress_total} units",
    }
    return job_report_html(job.spec, cols, provenance, name=job.name, render=figure_renderer())


def _render_columns(job: JobSnapshot, cols: Columns) -> tuple[str, int]:
    """(HTML, number of records); the caller's reference to ``cols`` is its last, so
    the columns are freed on return, before :func:`_release_memory`."""
    return _render(job, cols), len(cols)


def _build(job: JobSnapshot, session_factory: SessionFactory) -> tuple[str, int]:
    """Read the columns in a reading session of its own (closed before rendering),
    then render with no connection held."""
    with BUILD_SLOTS:
        try:
            return _render_columns(job, _read_columns(job.id, session_factory))
        finally:
            _release_memory()


def _read_columns(job_id: int, session_factory: SessionFactory) -> Columns:
    with closing(session_factory(False)) as s:
        return load_columns(s, job_id)


def _build_and_store(job: JobSnapshot, session_factory: SessionFactory) -> str:
    """A finished job's report: stored by another process meanwhile, else built and
    stored (or an old layout's replaced) through a new writing session. A job pruned
    while this built keeps its stored page: that is served, not the page of the rows
    this read (some or none)."""
    with closing(session_factory(False)) as s:
        row = servable_report(s, job.id, REPORT_LAYOUT)
        if row is not None:
            return row.html
    html, n = _build(job, session_factory)
    with closing(session_factory(True)) as w:
        try:
            row = servable_report(w, job.id, REPORT_LAYOUT)
            if row is not None:  # stored meanwhile, or the job's rows were pruned
                return row.html
            store_report(w, job.id, html, n, REPORT_LAYOUT)
            w.commit()
            log.info("stored the report of job %s (%d records)", job.id, n)
        except IntegrityError:  # another process stored it first: the same page
            w.rollback()
    return html


def job_report(
    session: Session,
    job: Job,
    session_factory: SessionFactory,
    *,
    builds: ReportBuilds | None = None,
) -> str:
    """The job's report: stored if the job is finished, else the one kept for its
    progress or built. ``session`` (the request's) is closed before any build."""
    builds = builds or DEFAULT_BUILDS
    snap = JobSnapshot.of(job)
    if snap.final:
        row = servable_report(session, snap.id, REPORT_LAYOUT)
        if row is not None:
            return row.html
    session.close()  # no connection is held while building or waiting for a build
    if snap.final:
        html = builds.get(
            snap.key, snap.team_id, snap.version, lambda: _build_and_store(snap, session_factory)
        )
        builds.forget(snap.key)  # stored: served from the database from now on
        return html
    return builds.get(
        snap.key, snap.team_id, snap.version, lambda: _build(snap, session_factory)[0]
    )


def store_if_missing(
    read_session: Session,
    write_session: Session,
    job_id: int,
    *,
    proceed: Callable[[], bool] | None = None,
) -> bool:
    """Build a finished job's report (reading with ``read_session``) and add it to
    ``write_session`` unless one is stored (one of an old layout is replaced, except
    for a job whose rows were pruned: :func:`servable_report`); True when it built
    one. The rows are read
    and the read transaction ended before rendering, so none is held (nor cut by a
    server's idle-in-transaction timeout) while the page renders; ``proceed()``,
    asked between the read and the rendering, can call the build off (False)."""
    with BUILD_SLOTS:
        read_session.rollback()  # a report stored while this waited for the slot is seen
        job = read_session.get(Job, job_id)
        if (
            job is None
            or not is_final(job)
            or servable_report(read_session, job_id, REPORT_LAYOUT) is not None
        ):
            return False
        snap = JobSnapshot.of(job)
        cols: Columns | None = None
        try:
            cols = _read_rows(read_session, job_id)
            if proceed is not None and not proceed():
                return False
            html, n = _render_columns(snap, cols)
        finally:
            cols = None  # freed before the heap is trimmed
            _release_memory()
    if servable_report(write_session, job_id, REPORT_LAYOUT) is None:
        store_report(write_session, job_id, html, n, REPORT_LAYOUT)
    return True


def _read_rows(session: Session, job_id: int) -> Columns:
    """The job's columns, with the session's transaction ended once they are read."""
    cols = load_columns(session, job_id)
    session.rollback()
    return cols


def caller_job_report(
    session: Session,
    caller: Caller,
    job_id: int,
    session_factory: SessionFactory,
    *,
    builds: ReportBuilds | None = None,
) -> str:
    """The report of the caller's job (:func:`job_report`; NotFound for another team's)."""
    job = team_job(session, caller, job_id)
    return job_report(session, job, session_factory, builds=builds)
