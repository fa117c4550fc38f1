"""Share links: ``/jobs/{id}/share`` makes and revokes them (signed in,
CSRF); ``/s/{token}`` is the read-only view of the job's report and charts, opened
without a key. An unknown, expired or revoked token is a 404 page, like a job of
another team. The token is shown once, when the link is made (only its hash is
stored: svrobs_lab.shares)."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Depends, Form, Query, Request
from fastapi.responses import HTMLResponse, RedirectResponse
from sqlalchemy.orm import Session

from service.db.models import Job
from service.http.deps import ReportBuildsDep, SessionFactoryDep, SettingsDep, get_db
from service.web import charts, figure_charts
from service.web.deps import CSRF, CurrentViewer
from service.web.pages import job as job_pages
from service.web.render import REPORT_HEADERS, render, with_back_link
from svrobs_lab import shares
from svrobs_lab.reports import caller_job_report

router = APIRouter(include_in_schema=False)
DB = Annotated[Session, Depends(get_db)]
Token = Annotated[str, Query(max_length=200)]


def _links_page(request, db, viewer, job: Job, *, created: int | None = None, status=200):
    """The job's links; ``created``: the id of the link just made (its URL is in the
    page's fragment, ``#new=<token>``, put there by the redirect and read by the
    page's script: it reaches neither the server's logs nor a reload)."""
    links = shares.job_links(db, viewer.caller, job.id)
    return render(
        request,
        "share.html",
        status=status,
        viewer=viewer,
        nav="jobs",
        job=job,
        links=links,
        live=shares.is_live,
        created=next((link for link in links if link.id == created), None),
        label_max=shares.LABEL_MAX,
        default_days=shares.DEFAULT_DAYS,
        max_days=shares.MAX_DAYS,
        min_days=round(shares.MIN_DAYS, 4),  # 0.0417: not under an hour
    )


@router.get("/jobs/{job_id:int}/share")
def share_page(
    request: Request,
    db: DB,
    viewer: CurrentViewer,
    job_id: int,
    created: Annotated[int | None, Query(ge=1)] = None,
):
    job = job_pages._job(db, viewer, job_id)
    return _links_page(request, db, viewer, job, created=created)


@router.post("/jobs/{job_id:int}/share", dependencies=[CSRF])
def make_link(
    db: DB,
    viewer: CurrentViewer,
    settings: SettingsDep,
    job_id: int,
    days: Annotated[str, Form(max_length=40)] = str(shares.DEFAULT_DAYS),
    label: Annotated[str, Form(max_length=shares.LABEL_MAX)] = "",
):
    """Make a link, then redirect (POST-redirect-GET: a reload makes no second link);
    over SVROBS_MAX_SHARES_PER_JOB live links, the 422 error page."""
    job = job_pages._job(db, viewer, job_id)
    link, token = shares.create(db, viewer.caller, settings, job.id, shares.days_of(days), label)
    return RedirectResponse(f"/jobs/{job.id}/share?created={link.id}#new={token}", 303)


@router.post("/shares/{share_id:int}/revoke", dependencies=[CSRF])
def revoke_link(db: DB, viewer: CurrentViewer, share_id: int):
    link = shares.revoke(db, viewer.caller, share_id)  # NotFound: a 404 page
    return RedirectResponse(f"/jobs/{link.job_id}/share", status_code=303)


@router.get("/s/{token}")
def shared_job(request: Request, db: DB, token: str):
    link, job = shares.open_link(db, token)
    response = render(
        request,
        "shared.html",
        viewer=None,
        job=job,
        link=link,
        token=token,
        x_fields=charts.X_FIELDS,
        x_labels=charts.LABELS,
        presets=figure_charts.preset_options(),
    )
    response.headers["X-Robots-Tag"] = "noindex"
    return response


@router.get("/s/{token}/chart-data")
def shared_chart_data(
    db: DB,
    token: str,
    metric: Annotated[str, Query(max_length=100)] = "rmse_A",
    x: Annotated[str, Query(max_length=20)] = "N",
    preset: Annotated[str | None, Query(max_length=100)] = None,
    metrics: bool = False,
):
    """The job page's chart data (service.web.pages.job.chart_data) for a shared job."""
    link, job = shares.open_link(db, token)
    return job_pages.team_chart_data(
        db, shares.reader(link), job.id, metric=metric, x=x, preset=preset, metrics=metrics
    )


@router.get("/s/{token}/report")
def shared_report(db: DB, token: str, session_factory: SessionFactoryDep, builds: ReportBuildsDep):
    link, job = shares.open_link(db, token)
    report = caller_job_report(db, shares.reader(link), job.id, session_factory, builds=builds)
    back = with_back_link(report, f"/s/{token}", f"← Job {job.id} (shared)")
    return HTMLResponse(back, headers={**REPORT_HEADERS, "X-Robots-Tag": "noindex"})
