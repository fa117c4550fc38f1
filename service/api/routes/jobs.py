"""POST/GET /jobs, GET/DELETE /jobs/{id}, POST /jobs/{id}/cancel."""

from __future__ import annotations

from typing import Annotated, Literal

from fastapi import APIRouter, Header, Query, Response

from service.api.deps import DB, CurrentCaller, JobId, SubmissionDep
from service.api.errors import BODY_ERRORS, ERRORS
from service.db.job_queries import JobFilter
from svrobs_lab import jobs
from svrobs_lab.schemas import SPEC_FIELD_NAMES, ErrorOut, JobOut, JobPage, JobSubmit
from svrobs_lab.views import job_out

router = APIRouter(tags=["jobs"])


@router.post(
    "/jobs",
    status_code=202,
    response_model=JobOut,
    responses={**BODY_ERRORS, 409: {"model": ErrorOut}},
)
def submit_job(
    body: JobSubmit,
    submission: SubmissionDep,
    idempotency_key: Annotated[str | None, Header(max_length=200)] = None,
):
    """Validate and queue a job (a spec, docs/spec.md#spec-fields, plus `name` and `tags`).

    A retry with the same `Idempotency-Key` returns the same job. The job and its
    work units are committed before anything is sent to the workers.
    """
    data = body.model_dump(exclude_unset=True)
    request = jobs.JobRequest(
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
    """The team's jobs, newest first, filtered by status, tag and owner; each with a
    compact `spec_summary` (the full spec is at `GET /jobs/{id}`)."""
    f = JobFilter(status=status, tag=tag, owner=owner)
    return jobs.list_jobs(session, caller, f, limit=limit, offset=offset)


@router.get("/jobs/{job_id}", response_model=JobOut, responses=ERRORS)
def get_job(job_id: JobId, session: DB, caller: CurrentCaller):
    """Status, progress done/total, timings, provenance and error of one job."""
    return job_out(jobs.team_job(session, caller, job_id))


@router.post(
    "/jobs/{job_id}/cancel", response_model=JobOut, responses={**ERRORS, 409: {"model": ErrorOut}}
)
def cancel(job_id: JobId, submission: SubmissionDep):
    """Cancel a queued or running job: units not yet started never run, running
    units stop within seconds and store nothing; `cells_done` says what was done."""
    return jobs.cancel(submission, job_id)


@router.delete("/jobs/{job_id}", status_code=204, responses={**ERRORS, 409: {"model": ErrorOut}})
def delete(job_id: JobId, session: DB, caller: CurrentCaller):
    """Delete a finished or cancelled job with its units, results and summaries (one
    transaction); 409 while it is queued or running (cancel it first)."""
    jobs.delete(session, caller, job_id)
    return Response(status_code=204)
