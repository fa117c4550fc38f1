"""POST/GET /jobs, GET /jobs/{id}, POST /jobs/{id}/cancel."""

from __future__ import annotations

import logging
from typing import Annotated, Literal

from fastapi import APIRouter, BackgroundTasks, Header, HTTPException, Query
from sqlalchemy import func, select
from sqlalchemy.orm import joinedload

from service.api.deps import DB, CurrentCaller, PublisherDep, SessionFactoryDep, SettingsDep
from service.api.routes.common import FieldHTTPException, JobId, job_out, team_job
from service.api.schemas import SPEC_FIELD_NAMES, ErrorOut, JobOut, JobPage, JobSubmit
from service.db.errors import IdempotencyConflict, QuotaExceeded
from service.db.jobs import cancel_job, create_job, unit_ids_of_job
from service.db.models import Job, JobTag, User
from service.db.outbox import mark_published
from svrobs_core.errors import SpecError

log = logging.getLogger(__name__)
router = APIRouter(tags=["jobs"])

ERRORS = {s: {"model": ErrorOut} for s in (401, 404, 422, 429, 503)}
BODY_ERRORS = {**ERRORS, 413: {"model": ErrorOut}}  # routes with a body: SVROBS_MAX_BODY_BYTES


def publish_after_commit(publisher, session_factory, unit_ids: list[int]) -> None:
    """Send the committed units to the broker and mark them; on failure nothing is lost:
    the relay (beat) re-publishes units never marked published."""
    try:
        sent = publisher(unit_ids)
    except Exception as exc:  # pragma: no cover - publishers catch their own errors
        log.warning("publishing failed: %s", exc)
        return
    if not sent:
        return
    try:
        session = session_factory(True)
        try:
            mark_published(session, sent)
            session.commit()
        finally:
            session.close()
    except Exception as exc:
        log.warning("marking %d units published failed: %s", len(sent), exc)


@router.post(
    "/jobs",
    status_code=202,
    response_model=JobOut,
    responses={**BODY_ERRORS, 409: {"model": ErrorOut}},
)
def submit_job(
    body: JobSubmit,  # type: ignore[valid-type]
    session: DB,
    caller: CurrentCaller,
    settings: SettingsDep,
    publisher: PublisherDep,
    session_factory: SessionFactoryDep,
    background: BackgroundTasks,
    idempotency_key: Annotated[str | None, Header(max_length=200)] = None,
):
    """Validate and queue a job (SPEC section 10 spec plus `name` and `tags`).

    A retry with the same `Idempotency-Key` returns the same job. The job and its
    work units are committed before anything is sent to the workers.
    """
    data = body.model_dump(exclude_unset=True)
    spec = {k: data[k] for k in SPEC_FIELD_NAMES if k in data}
    try:
        job, created = create_job(
            session,
            team_id=caller.team_id,
            user_id=caller.user_id,
            spec=spec,
            name=data.get("name"),
            tags=data.get("tags") or (),
            idempotency_key=idempotency_key or None,
            max_cells=settings.MAX_JOB_CELLS,
            max_active_jobs=settings.MAX_QUEUED_JOBS_PER_TEAM,
        )
    except SpecError:
        session.rollback()
        raise
    except (TypeError, ValueError, KeyError, IndexError) as exc:  # a spec the core choked on
        session.rollback()
        raise FieldHTTPException(422, f"invalid spec: {exc}", "spec") from exc
    except QuotaExceeded as exc:
        session.rollback()
        raise HTTPException(429, str(exc)) from exc
    except IdempotencyConflict as exc:
        session.rollback()
        raise FieldHTTPException(409, str(exc), "Idempotency-Key") from exc
    unit_ids = unit_ids_of_job(session, job.id) if created else []
    out = job_out(job)  # flushed: ids and defaults are set; no read-back after COMMIT
    session.commit()
    session.close()  # end this request's transaction before publishing
    if unit_ids:
        background.add_task(publish_after_commit, publisher, session_factory, unit_ids)
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
