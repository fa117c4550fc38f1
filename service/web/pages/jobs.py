"""``/jobs``: the team's jobs as a runs table: live progress, filters, search, pages,
sorting by one or more columns, a metric column (a summary field's mean over the cells
at one N), and the runs ticked to compare or delete (after a confirmation page)."""

from __future__ import annotations

import math
from typing import Annotated
from urllib.parse import urlencode

from fastapi import APIRouter, Depends, Form, Query, Request
from fastapi.responses import RedirectResponse
from sqlalchemy.orm import Session

from service.db import job_queries as queries
from service.db.models import JOB_STATUSES
from service.http.deps import get_db
from service.web.deps import CSRF, CurrentViewer
from service.web.render import WebError, render
from svrobs_core.records import SUMMARY_FIELDS
from svrobs_lab import jobs as lab_jobs
from svrobs_lab.auth import MAX_ID
from svrobs_lab.errors import JobActive, NotFound

router = APIRouter(include_in_schema=False)
PAGE_SIZE = 25
DB = Annotated[Session, Depends(get_db)]


def _sort_params(sort: queries.JobSort) -> dict[str, str]:
    out = {"sort": ",".join(sort.keys)} if sort.keys else {}
    if sort.metric:
        out["metric"] = sort.metric
    if sort.N is not None:
        out["at"] = str(sort.N)
    return out


def _table_context(
    db: Session, viewer, filt: queries.JobFilter, page: int, sort: queries.JobSort
) -> dict:
    def page_of(page: int) -> tuple[list, int]:
        return queries.job_page(
            db,
            viewer.team_id,
            viewer.caller.user_id,
            filt,
            limit=PAGE_SIZE,
            offset=(page - 1) * PAGE_SIZE,
            sort=sort,
        )

    jobs, total = page_of(page)
    pages = max(1, math.ceil(total / PAGE_SIZE))
    if page > pages:  # past the last page: the last one
        page = pages
        jobs, total = page_of(page)
        pages = max(1, math.ceil(total / PAGE_SIZE))
    params = {**filt.params(), **_sort_params(sort)}
    shown = False
    metric: dict[int, float] = {}
    if sort.metric and sort.N is not None:
        shown = True
        metric = queries.metric_values(db, [j.id for j in jobs], sort.metric, sort.N)

    def sort_query(key: str) -> str:
        """The query of a click on a column head: sort by it (again: descending)."""
        keys = ["-" + key] if list(sort.keys) == [key] else [key]
        return urlencode({**params, "sort": ",".join(keys)})

    return {
        "sort": sort,
        "sort_query": sort_query,
        "metric_shown": shown,
        "metric_values": metric,
        "summary_fields": SUMMARY_FIELDS,
        "jobs": jobs,
        "total": total,
        "page": page,
        "pages": pages,
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


def job_sort(
    sort: Text = "",
    metric: Text = "",
    at: Annotated[int | None, Query(ge=1, le=MAX_ID)] = None,
) -> queries.JobSort:
    """The order and metric column of the query string (a 422 page for an unknown one)."""
    keys = tuple(k.strip() for k in sort.split(",") if k.strip())
    for k in keys:
        if k.lstrip("-") not in queries.SORT_KEYS:
            raise WebError(422, f"sort: {k!r} is not one of {', '.join(queries.SORT_KEYS)}")
    if metric and metric not in SUMMARY_FIELDS:
        raise WebError(422, "metric: must be a numeric record field of the summaries")
    return queries.JobSort(keys=keys, metric=metric or None, N=at)


Sort = Annotated[queries.JobSort, Depends(job_sort)]


def metric_note(sort: queries.JobSort) -> str | None:
    """What the metric column lacks, when only one of its two fields is filled."""
    if sort.metric and sort.N is None:
        return f"The metric column needs an N: fill in “at N” to show {sort.metric} at that N."
    if sort.N is not None and not sort.metric:
        return f"Pick a metric to show its column at N = {sort.N}."
    return None


PageNo = Annotated[int, Query(ge=1, le=10**6)]


def _deleted_ids(text: str) -> list[int]:
    """The ids a delete left in the URL (``deleted=3,4``), for the page's message."""
    parts = [p for p in text.split(",") if p]
    if not all(p.isascii() and p.isdigit() for p in parts):
        raise WebError(422, "deleted: job ids, written with the digits 0-9 and commas")
    return [int(p) for p in parts]


@router.get("/jobs")
def jobs_page(
    request: Request,
    db: DB,
    viewer: CurrentViewer,
    filt: Filter,
    sort: Sort,
    page: PageNo = 1,
    deleted: Annotated[str, Query(max_length=2000)] = "",
):
    return render(
        request,
        "jobs.html",
        viewer=viewer,
        nav="jobs",
        statuses=JOB_STATUSES,
        tags=queries.team_tags(db, viewer.team_id),
        owners=queries.team_owners(db, viewer.team_id),
        deleted=_deleted_ids(deleted),
        metric_note=metric_note(sort),
        **_table_context(db, viewer, filt, page, sort),
    )


@router.get("/jobs/rows")
def jobs_rows(
    request: Request, db: DB, viewer: CurrentViewer, filt: Filter, sort: Sort, page: PageNo = 1
):
    """The table alone, polled by htmx every 2 s while a job on the page is active."""
    return render(request, "_jobs_table.html", **_table_context(db, viewer, filt, page, sort))


Ids = Annotated[list[Annotated[int, Query(ge=1, le=MAX_ID)]], Query(max_length=100)]


def _picked(db: Session, viewer, ids: list[int]) -> list:
    found = [queries.team_job(db, viewer.team_id, i) for i in dict.fromkeys(ids)]
    if not found or any(j is None for j in found):
        raise WebError(404, "Pick one or more of the team's jobs.")
    return found


@router.get("/jobs/delete")
def confirm_delete_many(request: Request, db: DB, viewer: CurrentViewer, jobs: Ids = []):  # noqa: B006 - FastAPI copies defaults
    """The ticked runs, and a button that deletes the finished or cancelled ones."""
    found = _picked(db, viewer, jobs)
    return render(request, "delete_many.html", viewer=viewer, nav="jobs", jobs=found)


@router.post("/jobs/delete", dependencies=[CSRF])
def delete_many(
    db: DB,
    viewer: CurrentViewer,
    jobs: Annotated[list[Annotated[int, Form(ge=1, le=MAX_ID)]], Form(max_length=100)],
):
    """Delete each of the jobs that is not queued or running (those are kept)."""
    gone = []
    for job_id in dict.fromkeys(jobs):
        try:
            lab_jobs.delete(db, viewer.caller, job_id)
        except (JobActive, NotFound):
            db.rollback()
            continue
        gone.append(job_id)
    return RedirectResponse(f"/jobs?deleted={','.join(map(str, gone))}", status_code=303)
