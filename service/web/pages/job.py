"""``/jobs/{id}``: one job's spec, provenance, timings, live progress and charts;
cancel, and delete with a confirmation page. Another team's job is a 404 page."""

from __future__ import annotations

import json
from typing import Annotated

from fastapi import APIRouter, BackgroundTasks, Depends, Query, Request
from fastapi.responses import HTMLResponse, JSONResponse, RedirectResponse
from sqlalchemy.orm import Session

from service.db import job_queries as queries
from service.db.models import JOB_ACTIVE, Job
from service.http.deps import ReportBuildsDep, SessionFactoryDep, get_db, submission_of
from service.web import charts, figure_charts, job_tables
from service.web.deps import CSRF, CurrentViewer
from service.web.render import PAGE_HEADERS, REPORT_HEADERS, WebError, render, with_back_link
from svrobs_lab import jobs
from svrobs_lab.auth import MAX_ID, Caller
from svrobs_lab.reports import caller_job_report

router = APIRouter(include_in_schema=False)
DB = Annotated[Session, Depends(get_db)]
FINISHED_EVENT = "svrobs:job-finished"


def _job(db: Session, viewer, job_id: int) -> Job:
    job = queries.team_job(db, viewer.team_id, job_id) if 1 <= job_id <= MAX_ID else None
    if job is None:
        raise WebError(404, f"Job {job_id} not found.")
    return job


def _progress_context(job: Job) -> dict:
    total, done = job.progress_total or 0, job.progress_done or 0
    return {"job": job, "active": job.status in JOB_ACTIVE, "done": done, "total": total}


@router.get("/jobs/{job_id:int}")
def job_page(request: Request, db: DB, viewer: CurrentViewer, job_id: int):
    job = _job(db, viewer, job_id)
    return render(
        request,
        "job.html",
        presets=figure_charts.preset_options(),
        viewer=viewer,
        nav="jobs",
        spec_json=json.dumps(job.spec, indent=2),
        provenance=job.provenance or {},
        x_fields=charts.X_FIELDS,
        x_labels=charts.LABELS,
        **_progress_context(job),
    )


@router.get("/jobs/{job_id:int}/progress")
def job_progress(request: Request, db: DB, viewer: CurrentViewer, job_id: int):
    """The status/progress card alone, polled by htmx every 2 s while the job is active;
    the first poll that sees it finished also fires ``svrobs:job-finished`` (charts
    reload)."""
    ctx = _progress_context(_job(db, viewer, job_id))
    response = render(request, "_job_progress.html", viewer=viewer, **ctx)
    if not ctx["active"]:
        response.headers["HX-Trigger"] = FINISHED_EVENT
    return response


@router.get("/jobs/{job_id:int}/tables")
def job_tables_card(request: Request, db: DB, viewer: CurrentViewer, job_id: int):
    """Table 2 and the RMSE findings from the stored summaries (service.web.job_tables),
    loaded by htmx after the page and again when the job finishes."""
    job = _job(db, viewer, job_id)
    groups = charts.stored_groups(db, job.id, *job_tables.TABLE_FIELDS)
    table2, findings = job_tables.summary_tables(groups)
    return render(
        request,
        "_job_tables.html",
        viewer=viewer,
        job=job,
        active=job.status in JOB_ACTIVE,
        table2=table2,
        findings=findings,
    )


@router.get("/jobs/{job_id:int}/chart-data")
def chart_data(
    db: DB,
    viewer: CurrentViewer,
    job_id: int,
    metric: Annotated[str, Query(max_length=100)] = "rmse_A",
    x: Annotated[str, Query(max_length=20)] = "N",
    preset: Annotated[str | None, Query(max_length=100)] = None,
    metrics: bool = False,
):
    """The plotted numbers as JSON, from the stored summaries (service.web.charts);
    ``preset=figure/key``: one of the report's figure series instead of ``metric``
    and ``x`` (service.web.figure_charts); with ``metrics=1`` also the fields that
    have data (the field list, asked once)."""
    return team_chart_data(
        db, viewer.caller, job_id, metric=metric, x=x, preset=preset, metrics=metrics
    )


def team_chart_data(
    db: Session,
    caller: Caller,
    job_id: int,
    *,
    metric: str,
    x: str,
    preset: str | None,
    metrics: bool,
) -> JSONResponse:
    """:func:`chart_data` of a job of the caller's team (a 404 page for another's)."""
    job = _job(db, caller, job_id)
    try:
        row = figure_charts.preset_of(preset) if preset else None
        charts.check(row.field if row else metric, x)
    except charts.ChartError as exc:
        return JSONResponse({"detail": str(exc), "field": exc.field}, status_code=422)
    if row is not None:
        groups = charts.stored_groups(db, job.id, row.field)
        data = figure_charts.preset_chart(groups, job.spec, row)
    else:
        groups = charts.stored_groups(db, job.id, metric)
        data = charts.chart_data(groups, metric=metric, x=x)
    data.update(job_id=job.id, status=job.status, groups=len(groups))
    if metrics:
        data["metrics"] = charts.stored_metrics(db, job.id)
    return JSONResponse(data, headers=PAGE_HEADERS)


@router.get("/jobs/{job_id:int}/report")
def report_page(
    db: DB,
    viewer: CurrentViewer,
    job_id: int,
    session_factory: SessionFactoryDep,
    builds: ReportBuildsDep,
):
    """The job's report (as ``GET /api/v1/jobs/{id}/report``) with a link back to its page."""
    html = caller_job_report(db, viewer.caller, job_id, session_factory, builds=builds)
    back = with_back_link(html, f"/jobs/{job_id}", f"← Job {job_id} on the dashboard")
    return HTMLResponse(back, headers=REPORT_HEADERS)


@router.post("/jobs/{job_id:int}/cancel", dependencies=[CSRF])
def cancel(
    request: Request, db: DB, viewer: CurrentViewer, job_id: int, background: BackgroundTasks
):
    """As ``POST /api/v1/jobs/{id}/cancel`` (the team's freed slots go to its other
    jobs); a succeeded or failed job is a 409 page, a cancelled one stays as it is."""
    jobs.cancel(submission_of(request, db, viewer.caller, background), job_id)
    return RedirectResponse(f"/jobs/{job_id}", status_code=303)


@router.get("/jobs/{job_id:int}/delete")
def confirm_delete(request: Request, db: DB, viewer: CurrentViewer, job_id: int):
    job = _job(db, viewer, job_id)
    return render(request, "delete.html", viewer=viewer, nav="jobs", job=job)


@router.post("/jobs/{job_id:int}/delete", dependencies=[CSRF])
def delete(db: DB, viewer: CurrentViewer, job_id: int):
    jobs.delete(db, viewer.caller, job_id)  # JobActive: a 409 page (service.web.errors)
    return RedirectResponse(f"/jobs?deleted={job_id}", status_code=303)
