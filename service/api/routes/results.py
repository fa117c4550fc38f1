"""GET /jobs/{id}/results (JSON page, CSV or JSONL stream), /jobs/{id}/summary, /compare."""

from __future__ import annotations

import csv
import io
import json
import math
from collections import defaultdict
from typing import Annotated, Literal

import numpy as np
from fastapi import APIRouter, Query
from fastapi.responses import Response, StreamingResponse
from pydantic import Field
from sqlalchemy import Select, func, select

from service.api.deps import DB, MAX_ID, CurrentCaller, JobId, SessionFactoryDep, team_job
from service.api.errors import ERRORS, FieldHTTPException
from service.api.record_json import ORDER, encode_lines, encode_page
from service.api.schemas import CompareOut, ResultPage, SummaryOut
from service.db.models import Result, Summary
from service.db.result_codec import ResultCodec
from service.db.results_store import count_cells, decode_rows, job_codec, record_select
from service.db.units import summarize_job
from svrobs_core.records import GROUP_FIELDS, NUMERIC_FIELDS, RECORD_FIELDS

router = APIRouter(tags=["results"])

# built once (a select of 41 columns costs ~1 ms to construct); routes add WHERE/ORDER
RECORDS = record_select()  # as stored: decoded by results_store.decode_rows
COUNT = select(func.count()).select_from(Result.__table__)
COMPARE_BY = ("system", "sigma_w", "N", "N0", "estimator", "gamma", "rep")
STREAM_CHUNK = 1000

FloatList = Annotated[list[float] | None, Query()]
# N and rep are 32-bit integer columns: a larger filter value would overflow the driver.
Int32 = Annotated[int, Field(ge=-MAX_ID - 1, le=MAX_ID)]
IntList = Annotated[list[Int32] | None, Query()]


def _results_filter(job_id, system, sigma_w, N, estimator, gamma, rep) -> list:
    """The WHERE conditions of a results selection (422 naming a bad filter value)."""
    t = Result.__table__
    conds = [t.c.job_id == job_id]
    if system:
        conds.append(t.c.system.in_(system))
    if sigma_w:
        if not all(math.isfinite(v) for v in sigma_w):
            raise FieldHTTPException(422, "must be finite", "sigma_w")
        conds.append(t.c.sigma_w.in_(sigma_w))
    if N:
        conds.append(t.c.N.in_(N))
    if estimator:
        conds.append(t.c.estimator.in_(estimator))
    if gamma:
        conds.append(t.c.gamma_key.in_(_gamma_keys(gamma)))
    if rep:
        conds.append(t.c.rep.in_(rep))
    return conds


def _gamma_keys(gamma: list[str]) -> list[float]:
    keys = []
    for g in gamma:
        if g.lower() in ("null", "none", "ols"):
            keys.append(-1.0)
            continue
        try:
            v = float(g)
        except ValueError:
            raise FieldHTTPException(422, "must be a number or 'null'", "gamma") from None
        if not math.isfinite(v):
            raise FieldHTTPException(422, "must be finite", "gamma")
        keys.append(v)
    return keys


def _csv_value(v):
    if v is None:
        return ""
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, float):
        return repr(v) if math.isfinite(v) else ""
    if isinstance(v, (list, dict)):
        return json.dumps(v, allow_nan=False, separators=(",", ":"))
    return v


def _stream(session_factory, query: Select, fmt: str, codec: ResultCodec):
    def gen():
        session = session_factory(False)
        try:
            if fmt == "csv":
                buf = io.StringIO()
                writer = csv.writer(buf, lineterminator="\n")
                writer.writerow(RECORD_FIELDS)
                yield buf.getvalue()
            rows = session.execute(query.execution_options(yield_per=STREAM_CHUNK))
            for chunk in rows.partitions(STREAM_CHUNK):
                if fmt == "csv":
                    buf = io.StringIO()
                    writer = csv.writer(buf, lineterminator="\n")
                    for rec in decode_rows(chunk, codec):
                        writer.writerow([_csv_value(rec[f]) for f in RECORD_FIELDS])
                    yield buf.getvalue()
                else:
                    yield encode_lines(chunk, codec)
        finally:
            session.close()

    media = "text/csv; charset=utf-8" if fmt == "csv" else "application/x-ndjson"
    return gen(), media


@router.get(
    "/jobs/{job_id}/results",
    response_model=ResultPage,
    responses={
        **ERRORS,
        200: {
            "content": {"text/csv": {}, "application/x-ndjson": {}},
            "description": "a JSON page, or the whole selection as CSV / JSON lines",
        },
    },
)
def get_results(
    job_id: JobId,
    session: DB,
    caller: CurrentCaller,
    session_factory: SessionFactoryDep,
    system: Annotated[list[str] | None, Query()] = None,
    sigma_w: FloatList = None,
    N: IntList = None,
    estimator: Annotated[list[str] | None, Query()] = None,
    gamma: Annotated[list[str] | None, Query(description="a value, or 'null' for ols")] = None,
    rep: IntList = None,
    format: Literal["json", "csv", "jsonl"] = "json",
    limit: Annotated[int | None, Query(ge=1, le=10_000)] = None,
    offset: Annotated[int, Query(ge=0, le=10**9)] = 0,
):
    """The job's records (SPEC section 10 field names; matrices as nested lists; null,
    never NaN), filtered by any grid coordinate (repeat a parameter for several
    values). JSON is paginated (default limit 100); CSV and JSONL stream the whole
    selection (or `limit`/`offset` if given)."""
    job = team_job(session, caller.team_id, job_id)
    codec = job_codec(session, job_id, job.spec)
    conds = _results_filter(job_id, system, sigma_w, N, estimator, gamma, rep)
    if format == "json":
        lim = limit or 100
        if job.status == "succeeded":  # every cell is stored: counted on the grid, O(1)
            keys = _gamma_keys(gamma) if gamma else None
            total = count_cells(job.spec, system, sigma_w, N, estimator, keys, rep)
        else:
            total = session.scalar(COUNT.where(*conds))
        # in key order: the primary key's order, so the page is read off its index
        page = RECORDS.where(*conds).order_by(*ORDER).limit(lim).offset(offset)
        rows = session.execute(page).all()
        body = encode_page(rows, codec, total, lim, offset)
        return Response(body, media_type="application/json")
    query = RECORDS.where(*conds).order_by(*ORDER)
    if limit is not None:
        query = query.limit(limit)
    if offset:
        query = query.offset(offset)
    session.close()  # the stream opens its own (reading) session
    body, media = _stream(session_factory, query, format, codec)
    ext = "csv" if format == "csv" else "jsonl"
    return StreamingResponse(
        body,
        media_type=media,
        headers={"Content-Disposition": f'attachment; filename="job-{job_id}-results.{ext}"'},
    )


def _group_out(g: dict) -> dict:
    return {**{k: g[k] for k in GROUP_FIELDS}, "count": g["count"], "stats": g["stats"]}


@router.get("/jobs/{job_id}/summary", response_model=SummaryOut, responses=ERRORS)
def get_summary(job_id: JobId, session: DB, caller: CurrentCaller):
    """Mean, std and count of every numeric field per (system, sigma_w, N, estimator,
    gamma). Stored when the job succeeds; computed from the results so far otherwise
    (`partial: true`)."""
    job = team_job(session, caller.team_id, job_id)
    if job.status != "succeeded":  # units store their groups' summaries as they finish
        return {
            "job_id": job_id,
            "partial": True,
            "groups": [_group_out(g) for g in summarize_job(session, job_id)],
        }
    rows = session.scalars(
        select(Summary)
        .where(Summary.job_id == job_id)
        .order_by(Summary.system, Summary.sigma_w, Summary.N, Summary.estimator, Summary.gamma_key)
    ).all()
    groups = [
        {
            "system": s.system,
            "sigma_w": s.sigma_w,
            "N": s.N,
            "estimator": s.estimator,
            "gamma": s.gamma,
            "count": s.count,
            "stats": s.stats,
        }
        for s in rows
    ]
    return {"job_id": job_id, "partial": False, "groups": groups}


def _csv_list(value: str, name: str) -> list[str]:
    items = [v.strip() for v in value.split(",") if v.strip()]
    if not items:
        raise FieldHTTPException(422, "must be a non-empty comma-separated list", name)
    return items


@router.get("/compare", response_model=CompareOut, responses=ERRORS)
def compare(
    session: DB,
    caller: CurrentCaller,
    jobs: Annotated[str, Query(description="comma-separated job ids, e.g. 1,2", max_length=1000)],
    metric: Annotated[
        str, Query(description="a numeric record field, e.g. rmse_A", max_length=100)
    ],
    by: Annotated[
        str, Query(description="comma-separated grid fields", max_length=200)
    ] = "N,estimator,gamma",
):
    """One metric across several jobs: mean, std (ddof 0) and count of the non-null
    values per job and per combination of the `by` fields."""
    try:
        ids = [int(j) for j in _csv_list(jobs, "jobs")]
    except ValueError:
        raise FieldHTTPException(422, "must be comma-separated job ids", "jobs") from None
    if len(ids) > 50 or any(i < 1 or i > MAX_ID for i in ids):
        raise FieldHTTPException(422, "at most 50 valid job ids", "jobs")
    ids = list(dict.fromkeys(ids))
    if metric not in NUMERIC_FIELDS:
        raise FieldHTTPException(
            422, f"must be a numeric record field, one of {list(NUMERIC_FIELDS)}", "metric"
        )
    by_fields = list(dict.fromkeys(_csv_list(by, "by")))
    for b in by_fields:
        if b not in COMPARE_BY:
            raise FieldHTTPException(422, f"{b!r} is not one of {list(COMPARE_BY)}", "by")
    for j in ids:
        team_job(session, caller.team_id, j)
    t = Result.__table__
    cols = [t.c.job_id] + [t.c[b] for b in by_fields] + [t.c[metric].label("__metric")]
    values: dict[tuple, list[float]] = defaultdict(list)
    seen: set[tuple] = set()
    for r in session.execute(select(*cols).where(t.c.job_id.in_(ids))):
        key = tuple(r[:-1])
        seen.add(key)
        v = r[-1]
        if v is not None and (not isinstance(v, float) or math.isfinite(v)):
            values[key].append(float(v))
    out = []
    for key in sorted(seen, key=lambda k: tuple((v is None, v) for v in k[1:]) + (k[0],)):
        vals = np.array(values.get(key, []), dtype=float)
        row = {"job_id": key[0], **dict(zip(by_fields, key[1:]))}
        row.update(
            mean=float(vals.mean()) if vals.size else None,
            std=float(vals.std()) if vals.size else None,
            count=int(vals.size),
        )
        out.append(row)
    return {"metric": metric, "by": by_fields, "jobs": ids, "rows": out}
