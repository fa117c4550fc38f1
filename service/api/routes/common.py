"""Helpers shared by the routes: team scoping, job serialisation."""

from __future__ import annotations

from typing import Annotated

from fastapi import HTTPException, Path
from sqlalchemy import select
from sqlalchemy.orm import Session, joinedload

from service.db.models import Job

MAX_ID = 2_147_483_647  # ids are 32-bit integers on every dialect
JobId = Annotated[int, Path(ge=1, le=MAX_ID, description="a job id of the caller's team")]


class FieldHTTPException(HTTPException):
    def __init__(self, status: int, detail, field: str | None = None, headers=None):
        super().__init__(status, detail, headers=headers)
        self.field = field


def team_job(session: Session, team_id: int, job_id: int, *, for_update: bool = False) -> Job:
    """The caller's job, or 404 (another team's job is indistinguishable from none)."""
    q = select(Job).where(Job.id == job_id, Job.team_id == team_id)
    job = session.scalar(q.options(joinedload(Job.user)))  # one query with the owner
    if job is None:
        raise HTTPException(404, f"job {job_id} not found")
    return job


def job_out(job: Job) -> dict:
    total = job.progress_total or 0
    done = job.progress_done or 0
    return {
        "id": job.id,
        "name": job.name,
        "tags": list(job.tags or []),
        "status": job.status,
        "progress": {
            "done": done,
            "total": total,
            "fraction": (done / total) if total else (1.0 if job.status == "succeeded" else 0.0),
        },
        "n_cells": job.n_cells,
        "owner": job.user.email if job.user is not None else None,
        "schedule_id": job.schedule_id,
        "idempotency_key": job.idempotency_key,
        "spec": job.spec,
        "provenance": job.provenance or {},
        "error": job.error,
        "timings": job.timings or {},
        "created_at": job.created_at,
        "started_at": job.started_at,
        "finished_at": job.finished_at,
    }
