"""``/results``: one job's records as a paginated, sortable grid, filtered by every grid
coordinate and by ranges of any numeric field; the grid is replaced in place by htmx
(``/results/rows``). The selection is :func:`svrobs_lab.results.select_rows`, as for
``GET /api/v1/jobs/{id}/results``, so the page and the REST route agree."""

from __future__ import annotations

import math
from itertools import zip_longest
from typing import Annotated, Any
from urllib.parse import urlencode

from fastapi import APIRouter, Depends, Query, Request
from sqlalchemy.orm import Session

from service.db import job_queries as queries
from service.db.models import Job
from service.db.result_queries import RANGE_FIELDS, grid_choices
from service.http.deps import get_db
from service.web.deps import CurrentViewer
from service.web.errors import plain
from service.web.job_picks import job_picks
from service.web.pages.cell import cell_query
from service.web.render import WebError, render
from svrobs_core.records import NUMERIC_FIELDS
from svrobs_lab import results
from svrobs_lab.auth import MAX_ID
from svrobs_lab.errors import Invalid
from svrobs_lab.params import read_int32, read_number

router = APIRouter(include_in_schema=False)
DB = Annotated[Session, Depends(get_db)]
PAGE_SIZE = 50
GRID = ("system", "sigma_w", "N", "estimator", "gamma", "rep")
Texts = Annotated[list[str], Query()]


def _range_rows(q) -> list[tuple[str, str, str]]:
    """The (field, min, max) rows of the range form (``rf``, ``rmin``, ``rmax``)."""
    return list(zip_longest(*(q.getlist(k) for k in ("rf", "rmin", "rmax")), fillvalue=""))


def _grid(request: Request, db: Session, viewer, job: Job, page: int) -> dict:
    results.not_pruned(job)  # Gone: the page says what is left, as the API does
    q = request.query_params

    def values(name, read):  # an empty field of the form is no filter
        return [read(name, v) for v in q.getlist(name) if v != ""]

    pick = {f: [v for v in q.getlist(f) if v != ""] for f in ("system", "estimator", "gamma")}
    ranges = []
    for field, lo, hi in _range_rows(q):
        if field:
            ranges += [(f"{field}_gte", lo)] if lo != "" else []
            ranges += [(f"{field}_lt", hi)] if hi != "" else []
    for name, _ in ranges:
        if name.rsplit("_", 1)[0] not in RANGE_FIELDS:
            raise Invalid("not a numeric record field", field=name)
    sort = q.get("sort") or None
    sel = results.select_rows(
        job,
        system=pick["system"],
        sigma_w=values("sigma_w", read_number),
        N=values("N", read_int32),
        estimator=pick["estimator"],
        gamma=pick["gamma"],
        rep=values("rep", read_int32),
        ranges=ranges,
        sort=sort,
    )
    total = results.count(db, sel, grid=False)
    pages = max(1, math.ceil(total / PAGE_SIZE))
    page = min(page, pages)
    records = results.page_records(db, sel, limit=PAGE_SIZE, offset=(page - 1) * PAGE_SIZE)
    shown = [f for f in NUMERIC_FIELDS if f not in GRID and any(r[f] is not None for r in records)]
    params = [(k, v) for k, v in q.multi_items() if k not in ("page", "sort")]

    def link(**kw):
        extra = [(k, v) for k, v in kw.items() if v is not None]
        return urlencode(params + extra)

    return {
        "job": job,
        "records": records,
        "columns": list(GRID) + shown,
        "total": total,
        "page": page,
        "pages": pages,
        "sort": sort,
        "sort_query": lambda f: link(sort=("-" + f) if sort == f else f),
        "page_query": lambda p: link(sort=sort, page=p),
        "cell_link": lambda r: (
            "/results/cell?"
            + cell_query(job.id, r)
            + "&"
            + urlencode({"back": urlencode(q.multi_items())})
        ),
    }


def _job_of(db: Session, viewer, job: int | None) -> Job | None:
    return None if job is None else _team_job(db, viewer, job)


def _team_job(db: Session, viewer, job: int) -> Job:
    found = queries.team_job(db, viewer.team_id, job) if 1 <= job <= MAX_ID else None
    if found is None:
        raise WebError(404, f"Job {job} not found.")
    return found


JobParam = Annotated[int | None, Query(ge=1)]
PageNo = Annotated[int, Query(ge=1, le=10**6)]


@router.get("/results")
def results_page(
    request: Request, db: DB, viewer: CurrentViewer, job: JobParam = None, page: PageNo = 1
):
    the_job = _job_of(db, viewer, job)
    ctx: dict[str, Any] = {
        "viewer": viewer,
        "nav": "results",
        "job": the_job,
        "range_fields": RANGE_FIELDS,
    }
    ctx["jobs"] = job_picks(db, viewer, [the_job.id] if the_job else []).jobs
    if the_job is not None:
        ctx["choices"] = grid_choices(db, the_job.id)
        ctx["picked"] = {f: request.query_params.getlist(f) for f in GRID}
        ctx["ranges"] = _range_rows(request.query_params) or [("", "", "")]
        ctx.update(_grid(request, db, viewer, the_job, page))  # Invalid: a 422 page
    return render(request, "results.html", **ctx)


@router.get("/results/rows")
def results_rows(request: Request, db: DB, viewer: CurrentViewer, job: int, page: PageNo = 1):
    """The grid alone (htmx): a bad filter is shown in its place."""
    the_job = _team_job(db, viewer, job)
    try:
        ctx = _grid(request, db, viewer, the_job, page)
    except Invalid as exc:
        ctx = {"job": the_job, "error": plain(exc)}
    return render(request, "_results_grid.html", **ctx)
