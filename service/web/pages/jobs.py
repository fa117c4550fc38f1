"""``/jobs``: the team's jobs with live progress, filters, search and pages."""

from __future__ import annotations

import math
from typing import Annotated
from urllib.parse import urlencode

from fastapi import APIRouter, Depends, Query, Request
from sqlalchemy.orm import Session

from service.db import job_queries as queries
from service.db.models import JOB_STATUSES
from service.http.deps import get_db
from service.web.deps import CurrentViewer
from service.web.render import WebError, render

router = APIRouter(include_in_schema=False)
PAGE_SIZE = 25
DB = Annotated[Session, Depends(get_db)]


def _table_context(db: Session, viewer, filt: queries.JobFilter, page: int) -> dict:
    jobs, total = queries.job_page(
        db,
        viewer.team_id,
        viewer.caller.user_id,
        filt,
        limit=PAGE_SIZE,
        offset=(page - 1) * PAGE_SIZE,
    )
    params = filt.params()
    return {
        "jobs": jobs,
        "total": total,
        "page": page,
        "pages": max(1, math.ceil(total / PAGE_SIZE)),
        "filt": filt,
        "polling": queries.any_active(jobs),
        "query": urlencode({**params, "page": page}),
        "page_query": lambda p: urlencode({**params, "page": p}),
    }


Text = Annotated[str, Query(max_length=200)]


def job_filter(status: Text = "", tag: Text = "", owner: Text = "", q: Text = ""):
    """The filters of the query string (a 422 page for an unknown status)."""
    if status and status not in JOB_STATUSES:
        raise WebError(422, f"status: must be one of {', '.join(JOB_STATUSES)}")
    return queries.JobFilter(
        status=status or None, tag=tag or None, owner=owner or None, q=q.strip() or None
    )


Filter = Annotated[queries.JobFilter, Depends(job_filter)]
PageNo = Annotated[int, Query(ge=1, le=10**6)]


@router.get("/jobs")
def jobs_page(
    request: Request,
    db: DB,
    viewer: CurrentViewer,
    filt: Filter,
    page: PageNo = 1,
    deleted: Annotated[int | None, Query(ge=1)] = None,
):
    return render(
        request,
        "jobs.html",
        viewer=viewer,
        nav="jobs",
        statuses=JOB_STATUSES,
        tags=queries.team_tags(db, viewer.team_id),
        owners=queries.team_owners(db, viewer.team_id),
        deleted=deleted,
        **_table_context(db, viewer, filt, page),
    )


@router.get("/jobs/rows")
def jobs_rows(request: Request, db: DB, viewer: CurrentViewer, filt: Filter, page: PageNo = 1):
    """The table alone, polled by htmx every 2 s while a job on the page is active."""
    return render(request, "_jobs_table.html", **_table_context(db, viewer, filt, page))
