"""Deleting a job with everything stored for it, in the caller's transaction.

A queued or running job is refused (:class:`JobActive`): cancel it first. Units are
locked before the job, the lock order of the rest of the DB package, so a unit that a
worker is finishing right now either commits first (its rows are deleted too) or
finds itself gone and stores nothing.
"""

from __future__ import annotations

from typing import Any, cast

from sqlalchemy import CursorResult, delete, select, update
from sqlalchemy.orm import Session

from service.db.models import (
    JOB_ACTIVE,
    Job,
    JobTag,
    JobValidation,
    Result,
    ResultBlock,
    ResultConstant,
    ScheduleRun,
    ShareLink,
    Summary,
    WorkUnit,
)
from svrobs_lab.errors import JobActive


def delete_job(session: Session, job: Job) -> dict[str, int]:
    """Delete ``job``, its work units, results (and their shared matrices), summaries,
    tags and validation (a schedule run that
    made it keeps its due time, without the job) -> the number of rows per table.
    Flushes; the caller commits. Raises :class:`JobActive` for a queued/running job."""
    job_id = job.id
    session.execute(
        select(WorkUnit.id).where(WorkUnit.job_id == job_id).order_by(WorkUnit.id).with_for_update()
    ).all()
    locked = session.scalar(
        select(Job)
        .where(Job.id == job_id)
        .with_for_update()
        .execution_options(populate_existing=True)
    )
    if locked is None:
        return {}
    if locked.status in JOB_ACTIVE:
        raise JobActive(job_id, locked.status)
    counts: dict[str, int] = {}
    for model in (
        Result,
        ResultBlock,
        ResultConstant,
        Summary,
        WorkUnit,
        JobTag,
        ShareLink,
        JobValidation,
    ):
        res = session.execute(delete(model).where(model.job_id == job_id))
        counts[model.__tablename__] = cast("CursorResult[Any]", res).rowcount  # a DELETE's result
    session.execute(update(ScheduleRun).where(ScheduleRun.job_id == job_id).values(job_id=None))
    session.execute(delete(Job).where(Job.id == job_id))
    session.expunge(locked)
    session.flush()
    return counts
