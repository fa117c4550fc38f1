"""GET /jobs/{id}/report (HTML) and POST /presets/paper-section-6/run (issue 4)."""

from __future__ import annotations

from typing import Annotated, Literal

from fastapi import APIRouter, BackgroundTasks, Header
from fastapi.responses import HTMLResponse
from pydantic import BaseModel, ConfigDict

from service.api.deps import DB, CurrentCaller, PublisherDep, SessionFactoryDep, SettingsDep
from service.api.routes.common import FieldHTTPException, JobId, job_out, team_job
from service.api.routes.jobs import BODY_ERRORS, ERRORS, publish_after_commit
from service.api.schemas import ErrorOut, JobOut
from service.db.errors import IdempotencyConflict, QuotaExceeded
from service.db.jobs import create_job, unit_ids_of_job
from service.db.results_store import load_records
from service.reports.html import job_report_html
from svrobs_core.paper import PRESET_NAME, paper_specs

router = APIRouter(tags=["reports"])


# The page is HTML but its errors are JSON (ERRORS with a model would document them as
# text/html, the route's media type).
JSON_ERRORS = {
    s: {
        "description": "error",
        "content": {"application/json": {"schema": {"$ref": "#/components/schemas/ErrorOut"}}},
    }
    for s in ERRORS
}


@router.get("/jobs/{job_id}/report", response_class=HTMLResponse, responses=JSON_ERRORS)
def job_report(job_id: JobId, session: DB, caller: CurrentCaller) -> HTMLResponse:
    """The job's report as one HTML page: tables, figures (embedded PNG), the spec,
    provenance and the data-generated findings. Built from the stored records."""
    job = team_job(session, caller.team_id, job_id)
    records = load_records(session, job.id)
    provenance = {
        **(job.provenance or {}),
        "job_id": job.id,
        "status": job.status,
        "progress": f"{job.progress_done}/{job.progress_total} units",
    }
    html = job_report_html(job.spec, records, provenance, name=job.name or f"job-{job.id}")
    return HTMLResponse(html)


class PresetRun(BaseModel):
    model_config = ConfigDict(extra="forbid")
    scale: Literal["full", "reduced"] = "full"
    experiments: list[Literal["E1", "E2", "E3", "E4"]] | None = None


@router.post(
    f"/presets/{PRESET_NAME}/run",
    status_code=202,
    response_model=list[JobOut],
    responses={**BODY_ERRORS, 409: {"model": ErrorOut}},
)
def run_paper_preset(
    session: DB,
    caller: CurrentCaller,
    settings: SettingsDep,
    publisher: PublisherDep,
    session_factory: SessionFactoryDep,
    background: BackgroundTasks,
    body: PresetRun | None = None,
    idempotency_key: Annotated[str | None, Header(max_length=180)] = None,
):
    """Queue the paper's Section 6 (SPEC section 9): one job per experiment E1-E4,
    tagged `paper-section-6` and the experiment name."""
    body = body or PresetRun()
    specs = paper_specs(body.scale)
    names = body.experiments or sorted(specs)
    jobs, unit_ids = [], []
    try:
        for name in names:
            job, created = create_job(
                session,
                team_id=caller.team_id,
                user_id=caller.user_id,
                spec=specs[name],
                name=f"{PRESET_NAME} {name} ({body.scale})",
                tags=(PRESET_NAME, name),
                idempotency_key=f"{idempotency_key}:{name}" if idempotency_key else None,
                max_cells=settings.MAX_JOB_CELLS,
                max_active_jobs=settings.MAX_QUEUED_JOBS_PER_TEAM,
            )
            jobs.append(job.id)
            if created:
                unit_ids += unit_ids_of_job(session, job.id)
    except QuotaExceeded as exc:
        session.rollback()
        raise FieldHTTPException(429, str(exc)) from exc
    except IdempotencyConflict as exc:  # the key was used with another scale
        session.rollback()
        raise FieldHTTPException(409, str(exc), "Idempotency-Key") from exc
    session.commit()
    out = [job_out(team_job(session, caller.team_id, j)) for j in jobs]
    session.close()
    if unit_ids:
        background.add_task(publish_after_commit, publisher, session_factory, unit_ids)
    return out
