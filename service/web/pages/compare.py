"""``/compare``: one metric across picked jobs, grouped by grid coordinates, as a
Chart.js chart (mean per group against one coordinate, a line per job and remaining
group) and a table. The numbers are those of ``GET /api/v1/compare`` (the same
function, :func:`svrobs_lab.results.compare`, computes them)."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Depends, Query, Request
from pydantic import Field
from sqlalchemy.orm import Session

from service.http.deps import get_db
from service.web.deps import CurrentViewer
from service.web.job_picks import job_picks
from service.web.render import WebError, render
from svrobs_core.records import NUMERIC_FIELDS
from svrobs_lab import results

router = APIRouter(include_in_schema=False)
DB = Annotated[Session, Depends(get_db)]
X_CHOICES = ("N", "sigma_w", "gamma", "N0", "rep")
# job ids and ``by`` fields, each its own parameter (the form's checkboxes) or
# comma-separated (the API's form: ``jobs=1,2``); results.compare reads and checks them
Ids = Annotated[list[Annotated[str, Field(max_length=2000)]], Query(max_length=50)]
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
    if metric in results.COMPARE_BY:
        raise WebError(
            422, f"metric: {metric} is a grid coordinate, not a metric (pick one such as rmse_A)"
        )
    ids = ",".join(part for text in jobs for part in text.split(",") if part.strip())
    # each its own parameter (the form's checkboxes) or comma-separated (the API's form)
    by = list(dict.fromkeys(p.strip() for text in by for p in text.split(",") if p.strip()))
    by = by or ["N", "estimator", "gamma"]
    if x not in by:
        by.insert(0, x)
    data = None
    if ids:
        data = results.compare(  # a LabError is a page (service.web.errors)
            db, viewer.caller, jobs=ids, metric=metric, by=",".join(by)
        )
    picks = job_picks(db, viewer, data["jobs"] if data else ())
    return render(
        request,
        "compare.html",
        viewer=viewer,
        nav="compare",
        team_jobs=picks.jobs,
        older=picks.older,
        picked=set(data["jobs"]) if data else set(),
        metric=metric,
        metrics=NUMERIC_FIELDS,
        by=by,
        by_choices=results.COMPARE_BY,
        x=x,
        x_choices=X_CHOICES,
        data=data,
        chart={"x": x, "metric": metric, **data} if data else None,
    )
