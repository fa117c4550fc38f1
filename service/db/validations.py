"""A dataset job's stored validation summary (``job_validations``): read it, store it
once (a concurrent writer's copy wins; both are the same numbers)."""

from __future__ import annotations

from typing import cast

from sqlalchemy import select
from sqlalchemy.orm import Session

from .models import Dataset, Job, JobValidation, WorkUnit
from .results_store import insert_ignore

TABLE = JobValidation.__table__


def stored_validation(session: Session, job_id: int) -> dict | None:
    """The job's validation summary, or None when none is stored."""
    return session.scalar(select(JobValidation.summary).where(JobValidation.job_id == job_id))


def store_validation(session: Session, job_id: int, summary: dict) -> None:
    """Store the job's validation summary unless one is (not committed)."""
    row = {"job_id": job_id, "summary": summary}
    session.execute(insert_ignore(session, TABLE, ["job_id"]), [row])


def unit_dataset_job(session: Session, unit_id: int) -> tuple[int, int] | None:
    """(job id, dataset id) of a work unit of a dataset job, else None."""
    row = session.execute(
        select(Job.id, Job.dataset_id)
        .join(WorkUnit, WorkUnit.job_id == Job.id)
        .where(WorkUnit.id == unit_id, Job.dataset_id.is_not(None))
    ).first()
    return None if row is None else (row[0], cast(int, row[1]))  # dataset_id is not None


def dataset_digest(session: Session, dataset_id: int) -> str | None:
    """The sha256 of a dataset's stored arrays (what a cached copy is checked by)."""
    return session.scalar(select(Dataset.arrays_sha256).where(Dataset.id == dataset_id))
