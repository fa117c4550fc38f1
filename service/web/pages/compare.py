"""``/compare``: one metric across picked jobs, grouped by grid coordinates, as a
Chart.js chart (mean per group against one coordinate, a line per job and remaining
group) and a table. The numbers are those of ``GET /api/v1/compare`` (the same
function, :func:`svrobs_lab.results.compare`, computes them)."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Depends, Query, Request
from pydantic import Field
from sqlalchemy.orm import Session

from service.db import job_queries as queries
from service.http.deps import get_db
from service.web.deps import CurrentViewer
from service.web.render import WebError, render
from svrobs_core.records import NUMERIC_FIELDS
from svrobs_lab import results
from svrobs_lab.auth import MAX_ID

router = APIRouter(include_in_schema=False)
DB = Annotated[Session, Depends(get_db)]
X_CHOICES = ("N", "sigma_w", "gamma", "N0", "rep")
Ids = Annotated[list[Annotated[int, Field(ge=1, le=MAX_ID)]], Query(max_length=50)]
Names = Annotated[list[str], Query(max_length=20)]


@router.get("/compare")
def compare_page(
    request: Request,
    db: DB,
    viewer: CurrentViewer,
    jobs: Ids = [],  # noqa: B006 - FastAPI copies defaults
    metric: Annotated[str, Query(max_length=100)] = "rmse_A",
    by: Names = [],  # noqa: B006
    x: Annotated[str, Query(max_length=20)] = "N",
):
    if x not in X_CHOICES:
        raise WebError(422, f"x: must be one of {', '.join(X_CHOICES)}")
    by = list(dict.fromkeys(by or ["N", "estimator", "gamma"]))
    if x not in by:
        by.insert(0, x)
    team_jobs, _ = queries.job_page(
        db, viewer.team_id, viewer.caller.user_id, queries.JobFilter(), limit=200, offset=0
    )
    data = None
    if jobs:
        data = results.compare(  # a LabError is a page (service.web.errors)
            db, viewer.caller, jobs=",".join(map(str, jobs)), metric=metric, by=",".join(by)
        )
    return render(
        request,
        "compare.html",
        viewer=viewer,
        nav="compare",
        team_jobs=team_jobs,
        picked=set(jobs),
        metric=metric,
        metrics=NUMERIC_FIELDS,
        by=by,
        by_choices=results.COMPARE_BY,
        x=x,
        x_choices=X_CHOICES,
        data=data,
        chart={"x": x, "metric": metric, **data} if data else None,
    )
