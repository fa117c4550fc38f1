"""``/results``: one job's records as a paginated, sortable grid, filtered by every grid
coordinate and by ranges of any numeric field; the grid is replaced in place by htmx
(``/results/rows``). The selection is built by the API's own functions
(``GET /api/v1/jobs/{id}/results``), so the page and the REST route agree."""

from __future__ import annotations

import math
from itertools import zip_longest
from typing import Annotated
from urllib.parse import urlencode

from fastapi import APIRouter, Depends, Query, Request
from sqlalchemy import func, select
from sqlalchemy.orm import Session

from service.api.deps import get_db
from service.api.errors import FieldHTTPException
from service.api.query_params import RANGE_FIELDS, range_terms, sort_order
from service.api.record_json import ORDER
from service.api.routes.results import _results_filter as results_filter
from service.db.models import Job, Result, Summary
from service.db.results_store import decode_rows, job_codec, record_select
from service.web import queries
from service.web.deps import CurrentViewer
from service.web.render import WebError, render
from svrobs_core.records import NUMERIC_FIELDS

router = APIRouter(include_in_schema=False)
DB = Annotated[Session, Depends(get_db)]
PAGE_SIZE = 50
GRID = ("system", "sigma_w", "N", "estimator", "gamma", "rep")
MAX_ID = 2_147_483_647
Texts = Annotated[list[str], Query()]


def _choices(db: Session, job_id: int) -> dict[str, list]:
    """The values of each grid coordinate, from the job's stored summaries."""
    out = {}
    for f in ("system", "sigma_w", "N", "estimator", "gamma_key"):
        col = getattr(Summary, f)
        q = select(col).where(Summary.job_id == job_id).distinct().order_by(col)
        out[f] = list(db.scalars(q))
    out["gamma"] = ["null" if g < 0 else repr(g) for g in out.pop("gamma_key")]
    return out


def _range_rows(q) -> list[tuple[str, str, str]]:
    """The (field, min, max) rows of the range form (``rf``, ``rmin``, ``rmax``)."""
    return list(zip_longest(*(q.getlist(k) for k in ("rf", "rmin", "rmax")), fillvalue=""))


def _grid(request: Request, db: Session, viewer, job: Job, page: int) -> dict:
    q = request.query_params
    t = Result.__table__

    def floats(name):
        try:
            return [float(v) for v in q.getlist(name) if v != ""]
        except ValueError:
            raise FieldHTTPException(422, "must be a number", name) from None

    def ints(name):
        try:
            return [int(v) for v in q.getlist(name) if v != ""]
        except ValueError:
            raise FieldHTTPException(422, "must be an integer", name) from None

    pick = {f: [v for v in q.getlist(f) if v != ""] for f in ("system", "estimator", "gamma")}
    conds = results_filter(
        job.id,
        pick["system"],
        floats("sigma_w"),
        ints("N"),
        pick["estimator"],
        pick["gamma"],
        ints("rep"),
    )
    ranges = []
    for field, lo, hi in _range_rows(q):
        if field:
            ranges += [(f"{field}_gte", lo)] if lo != "" else []
            ranges += [(f"{field}_lt", hi)] if hi != "" else []
    for name, _ in ranges:
        if name.rsplit("_", 1)[0] not in RANGE_FIELDS:
            raise FieldHTTPException(422, "not a numeric record field", name)
    conds += range_terms(ranges, t)
    sort = q.get("sort") or None
    order = sort_order(sort, t) + ORDER
    total = db.scalar(select(func.count()).select_from(t).where(*conds)) or 0
    pages = max(1, math.ceil(total / PAGE_SIZE))
    page = min(page, pages)
    rows = db.execute(
        record_select()
        .where(*conds)
        .order_by(*order)
        .limit(PAGE_SIZE)
        .offset((page - 1) * PAGE_SIZE)
    ).all()
    records = decode_rows(rows, job_codec(db, job.id, job.spec))
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
    }


def _job_of(db: Session, viewer, job: int | None) -> Job | None:
    if job is None:
        return None
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
    ctx = {"viewer": viewer, "nav": "results", "job": the_job, "range_fields": RANGE_FIELDS}
    ctx["jobs"], _ = queries.job_page(
        db, viewer.team_id, viewer.caller.user_id, queries.JobFilter(), limit=200, offset=0
    )
    if the_job is not None:
        ctx["choices"] = _choices(db, the_job.id)
        ctx["picked"] = {f: request.query_params.getlist(f) for f in GRID}
        ctx["ranges"] = _range_rows(request.query_params) or [("", "", "")]
        try:
            ctx.update(_grid(request, db, viewer, the_job, page))
        except FieldHTTPException as exc:
            raise WebError(422, f"{exc.field}: {exc.detail}") from None
    return render(request, "results.html", **ctx)


@router.get("/results/rows")
def results_rows(request: Request, db: DB, viewer: CurrentViewer, job: int, page: PageNo = 1):
    """The grid alone (htmx): a bad filter is shown in its place."""
    the_job = _job_of(db, viewer, job)
    try:
        ctx = _grid(request, db, viewer, the_job, page)
    except FieldHTTPException as exc:
        ctx = {"job": the_job, "error": f"{exc.field}: {exc.detail}"}
    return render(request, "_results_grid.html", **ctx)
