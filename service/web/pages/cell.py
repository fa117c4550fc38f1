"""``/results/cell``: one cell of a job (a row of ``/results``) with its matrices
(Â, B̂, the radii, L, K: whatever the record holds) as small tables under the
glossary's names and units, and its other fields (docs/web.md#a-cells-matrices). The
record is :func:`svrobs_lab.results.page_records` of the cell's grid coordinates,
as ``GET /api/v1/jobs/{id}/results`` selects it."""

from __future__ import annotations

from typing import Annotated
from urllib.parse import urlencode

from fastapi import APIRouter, Depends, Query, Request
from sqlalchemy.orm import Session

from service.db import job_queries as queries
from service.http.deps import get_db
from service.web.deps import CurrentViewer
from service.web.fields import unit
from service.web.render import WebError, render
from svrobs_core.records import FIELD_GLOSSARY, MATRIX_FIELDS, RECORD_FIELDS, json_value
from svrobs_lab import results
from svrobs_lab.auth import MAX_ID

router = APIRouter(include_in_schema=False)
DB = Annotated[Session, Depends(get_db)]
KEYS = ("system", "sigma_w", "N", "estimator", "gamma", "rep")
Int32 = Annotated[int, Query(ge=0, le=MAX_ID)]


def cell_query(job_id: int, record: dict) -> str:
    """The query of a record's cell page: the job and the cell's grid coordinates
    (γ ``null`` for OLS; floats as their shortest round-trip text)."""
    gamma = record["gamma"]
    return urlencode(
        [
            ("job", job_id),
            ("system", record["system"]),
            ("sigma_w", repr(record["sigma_w"])),
            ("N", record["N"]),
            ("estimator", record["estimator"]),
            ("gamma", "null" if gamma is None else repr(gamma)),
            ("rep", record["rep"]),
        ]
    )


def _matrix(field: str, value) -> dict | None:
    """A matrix field as rows of numbers (None entries stay None), or None if absent."""
    rows = json_value(value)
    if not rows:
        return None
    rows = [r if isinstance(r, list) else [r] for r in rows]
    meaning = FIELD_GLOSSARY[field][2]
    return {
        "field": field,
        "unit": unit(field),
        "meaning": meaning,
        "rows": rows,
        "cols": max(map(len, rows)),
    }


@router.get("/results/cell")
def cell_page(
    request: Request,
    db: DB,
    viewer: CurrentViewer,
    job: Annotated[int, Query(ge=1, le=MAX_ID)],
    system: str,
    sigma_w: float,
    N: Int32,
    estimator: str,
    gamma: str,
    rep: Int32,
):
    the_job = queries.team_job(db, viewer.team_id, job)
    if the_job is None:
        raise WebError(404, f"Job {job} not found.")
    results.not_pruned(the_job)
    sel = results.select_rows(
        the_job,
        system=[system],
        sigma_w=[sigma_w],
        N=[N],
        estimator=[estimator],
        gamma=[gamma],
        rep=[rep],
    )  # Invalid (a bad γ): a 422 page
    found = results.page_records(db, sel, limit=1, offset=0)
    if not found:
        raise WebError(404, f"Job {job} has no cell at these grid coordinates (yet).")
    record = found[0]
    matrices = [m for f in MATRIX_FIELDS if (m := _matrix(f, record[f])) is not None]
    skip = set(KEYS) | set(MATRIX_FIELDS) | {"notes"}
    scalars = [(f, json_value(record[f])) for f in RECORD_FIELDS if f not in skip]
    back = [(k, v) for k, v in request.query_params.multi_items() if k == "back"]
    return render(
        request,
        "cell.html",
        viewer=viewer,
        nav="results",
        job=the_job,
        record=record,
        matrices=matrices,
        scalars=[(f, v) for f, v in scalars if v is not None],
        missing=[f for f, v in scalars if v is None]
        + [f for f in MATRIX_FIELDS if record[f] is None],
        unit=unit,
        back="/results?" + (back[0][1] if back else urlencode({"job": job})),
    )
