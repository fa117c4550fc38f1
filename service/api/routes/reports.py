"""GET /jobs/{id}/report (HTML) and POST /presets/paper-section-6/run."""

from __future__ import annotations

from typing import Annotated, Literal

from fastapi import APIRouter, Header
from fastapi.responses import HTMLResponse
from pydantic import BaseModel, ConfigDict

from service.api.deps import (
    DB,
    CurrentCaller,
    JobId,
    ReportBuildsDep,
    SessionFactoryDep,
    SubmissionDep,
)
from service.api.errors import BODY_ERRORS, ERRORS
from service.http.security import INLINE_STYLE_CSP
from svrobs_core.paper import PRESET_NAME, paper_specs
from svrobs_lab.jobs import JobRequest
from svrobs_lab.reports import caller_job_report
from svrobs_lab.schemas import ErrorOut, JobOut

router = APIRouter(tags=["reports"])

# Marks the page as an svrobs job report (its value: the job's id); the client saves
# no page without it (svrobs_client.errors.REPORT_HEADER).
REPORT_HEADER = "X-Svrobs-Report"


# The page is HTML but its errors are JSON (ERRORS with a model would document them as
# text/html, the route's media type).
JSON_ERRORS = {
    s: {
        "description": "error",
        "content": {"application/json": {"schema": {"$ref": "#/components/schemas/ErrorOut"}}},
    }
    for s in ERRORS
}
REPORT_RESPONSES = {
    200: {
        "description": "the report page",
        "headers": {REPORT_HEADER: {"description": "the job's id", "schema": {"type": "string"}}},
    },
    **JSON_ERRORS,
}


@router.get("/jobs/{job_id}/report", response_class=HTMLResponse, responses=REPORT_RESPONSES)
def job_report(
    job_id: JobId,
    session: DB,
    caller: CurrentCaller,
    session_factory: SessionFactoryDep,
    builds: ReportBuildsDep,
) -> HTMLResponse:
    """The job's report as one HTML page: tables, figures (embedded PNG), the spec,
    provenance and the data-generated findings. Built from the stored records, once
    for a finished job (then served as stored), and for a running job again only when
    its progress changed; 429 with Retry-After while the team builds too many. The
    header X-Svrobs-Report (the job's id) tells a client the page is the report."""
    html = caller_job_report(session, caller, job_id, session_factory, builds=builds)
    headers = {"Content-Security-Policy": INLINE_STYLE_CSP, REPORT_HEADER: str(job_id)}
    return HTMLResponse(html, headers=headers)


class PresetRun(BaseModel):
    model_config = ConfigDict(extra="forbid")
    scale: Literal["full", "reduced"] = "full"
    experiments: list[Literal["E1", "E2", "E3", "E4", "A1", "A2"]] | None = None


@router.post(
    f"/presets/{PRESET_NAME}/run",
    status_code=202,
    response_model=list[JobOut],
    responses={**BODY_ERRORS, 409: {"model": ErrorOut}},
)
def run_paper_preset(
    submission: SubmissionDep,
    body: PresetRun | None = None,
    idempotency_key: Annotated[str | None, Header(max_length=180)] = None,
):
    """Queue the paper's Section 6
    (docs/science.md#91-the-preset-paper-section-6): one job per experiment, the
    paper's E1-E4 and the audits of the uncertainty sets A1 (self-normalized
    box) and A2 (bootstrap box) on E2's grid, tagged `paper-section-6` and the
    experiment name."""
    body = body or PresetRun()
    specs = paper_specs(body.scale)
    names: list[str] = list(body.experiments or []) or sorted(specs)
    requests = [
        JobRequest(
            spec=specs[name],
            name=f"{PRESET_NAME} {name} ({body.scale})",
            tags=(PRESET_NAME, name),
            idempotency_key=f"{idempotency_key}:{name}" if idempotency_key else None,
        )
        for name in names
    ]
    return submission.submit(requests)
