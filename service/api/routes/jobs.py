"""POST/GET /jobs, GET/DELETE /jobs/{id}, POST /jobs/{id}/cancel."""

from __future__ import annotations

from typing import Annotated, Literal

from fastapi import APIRouter, Header, HTTPException, Query, Response
from sqlalchemy import func, select
from sqlalchemy.orm import joinedload

from service.api.deps import DB, CurrentCaller, JobId, team_job
from service.api.errors import BODY_ERRORS, ERRORS
from service.api.schemas import SPEC_FIELD_NAMES, ErrorOut, JobOut, JobPage, JobSubmit
from service.api.submission import JobRequest, SubmissionDep
from service.api.views import job_out
from service.db.job_delete import JobActive, delete_job
from service.db.jobs import cancel_job
from service.db.models import Job, JobTag, User

router = APIRouter(tags=["jobs"])


@router.post(
    "/jobs",
    status_code=202,
    response_model=JobOut,
    responses={**BODY_ERRORS, 409: {"model": ErrorOut}},
)
def submit_job(
    body: JobSubmit,  # type: ignore[valid-type]
    submission: SubmissionDep,
    idempotency_key: Annotated[str | None, Header(max_length=200)] = None,
):
    """Validate and queue a job (SPEC section 10 spec plus `name` and `tags`).

    A retry with the same `Idempotency-Key` returns the same job. The job and its
    work units are committed before anything is sent to the workers.
    """
    data = body.model_dump(exclude_unset=True)
    request = JobRequest(
        spec={k: data[k] for k in SPEC_FIELD_NAMES if k in data},
        name=data.get("name"),
        tags=data.get("tags") or (),
        idempotency_key=idempotency_key or None,
    )
    (out,) = submission.submit([request])
    return out


@router.get("/jobs", response_model=JobPage, responses=ERRORS)
def list_jobs(
    session: DB,
    caller: CurrentCaller,
    status: Literal["queued", "running", "succeeded", "failed", "cancelled"] | None = None,
    tag: str | None = None,
    owner: Annotated[str | None, Query(description="an email, or 'me'")] = None,
    limit: Annotated[int, Query(ge=1, le=500)] = 50,
    offset: Annotated[int, Query(ge=0, le=10**9)] = 0,
):
    """The team's jobs, newest first, filtered by status, tag and owner."""
    q = select(Job).where(Job.team_id == caller.team_id)
    if status:
        q = q.where(Job.status == status)
    if tag:
        q = q.where(Job.id.in_(select(JobTag.job_id).where(JobTag.tag == tag)))
    if owner:
        if owner == "me":
            q = q.where(Job.user_id == caller.user_id)
        else:
            q = q.where(
                Job.user_id.in_(
                    select(User.id).where(
                        User.email == owner.strip().lower(), User.team_id == caller.team_id
                    )
                )
            )
    total = session.scalar(select(func.count()).select_from(q.subquery()))
    rows = session.scalars(
        q.options(joinedload(Job.user)).order_by(Job.id.desc()).limit(limit).offset(offset)
    ).all()
    return {"items": [job_out(j) for j in rows], "total": total, "limit": limit, "offset": offset}


@router.get("/jobs/{job_id}", response_model=JobOut, responses=ERRORS)
def get_job(job_id: JobId, session: DB, caller: CurrentCaller):
    """Status, progress done/total, timings, provenance and error of one job."""
    return job_out(team_job(session, caller.team_id, job_id))


@router.post(
    "/jobs/{job_id}/cancel", response_model=JobOut, responses={**ERRORS, 409: {"model": ErrorOut}}
)
def cancel(job_id: JobId, session: DB, caller: CurrentCaller):
    """Cancel a queued or running job: units not yet started never run."""
    job = team_job(session, caller.team_id, job_id)
    if job.status in ("succeeded", "failed"):
        raise HTTPException(409, f"job {job_id} already {job.status}")
    job = cancel_job(session, job)
    session.commit()
    return job_out(team_job(session, caller.team_id, job_id))


@router.delete("/jobs/{job_id}", status_code=204, responses={**ERRORS, 409: {"model": ErrorOut}})
def delete(job_id: JobId, session: DB, caller: CurrentCaller):
    """Delete a finished or cancelled job with its units, results and summaries (one
    transaction); 409 while it is queued or running (cancel it first)."""
    job = team_job(session, caller.team_id, job_id)
    try:
        delete_job(session, job)
    except JobActive as exc:
        raise HTTPException(409, str(exc)) from exc
    session.commit()
    return Response(status_code=204)
