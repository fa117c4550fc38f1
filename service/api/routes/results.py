"""GET /jobs/{id}/results (JSON page, CSV or JSONL stream), /jobs/{id}/summary, /compare."""

from __future__ import annotations

import csv
import io
import json
import math
from typing import Annotated, Literal

from fastapi import APIRouter, Query, Request
from fastapi.responses import Response, StreamingResponse
from pydantic import Field
from sqlalchemy import Select, func, select

from service.api.deps import DB, MAX_ID, CurrentCaller, JobId, SessionFactoryDep, team_job
from service.api.errors import ERRORS, FieldHTTPException, error_docs
from service.api.params import is_float_text, is_int_text
from service.api.query_params import accepts_query, is_range_param, range_conditions, sort_order
from service.api.record_json import ORDER, encode_lines, encode_page
from service.api.schemas import CompareOut, ResultPage, SummaryOut
from service.db.aggregates import summarize_in_db
from service.db.compare import COMPARE_BY, NeedsCellRows, compare_page
from service.db.models import Job, Result, Summary
from service.db.result_codec import ResultCodec
from service.db.results_store import count_cells, decode_rows, job_codec, record_select
from svrobs_core.records import GROUP_FIELDS, NUMERIC_FIELDS, RECORD_FIELDS

router = APIRouter(tags=["results"])

# built once (a select of 41 columns costs ~1 ms to construct); routes add WHERE/ORDER
RECORDS = record_select()  # as stored: decoded by results_store.decode_rows
COUNT = select(func.count()).select_from(Result.__table__)
COMPARE_MAX_ROWS = 10_000
GONE = error_docs(410)  # a job pruned by retention
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


def _not_pruned(job: Job) -> None:
    """410 for a job whose cell rows retention dropped (what is left, and where)."""
    if job.pruned_at is not None:
        raise FieldHTTPException(
            410,
            f"job {job.id}'s cell rows were dropped on {job.pruned_at:%Y-%m-%d %H:%M} UTC by "
            "the team's retention policy; its summary (GET /jobs/{id}/summary), compare by "
            "system, sigma_w, N, estimator and gamma, and its report remain",
        )


# a text cell starting with one of these is a formula to a spreadsheet (OWASP, "CSV
# injection"): it is written with a leading single quote
FORMULA_START = ("=", "+", "-", "@", "\t", "\r")


def _gamma_keys(gamma: list[str]) -> list[float]:
    keys = []
    for g in gamma:
        if g.lower() in ("null", "none", "ols"):
            keys.append(-1.0)
            continue
        if not is_float_text(g) or not math.isfinite(float(g)):
            raise FieldHTTPException(422, "must be a finite decimal number or 'null'", "gamma")
        keys.append(float(g))
    return keys


def _csv_value(v):
    if isinstance(v, str):
        return "'" + v if v.startswith(FORMULA_START) else v
    if v is None:
        return ""
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, float):
        return repr(v) if math.isfinite(v) else ""
    if isinstance(v, (list, dict)):
        return json.dumps(v, allow_nan=False, separators=(",", ":"))
    return v  # an int


def _stream(session_factory, query: Select, fmt: str, codec: ResultCodec):
    """The selection as CSV (RFC 4180: CRLF line ends, so a cell holding a CR or LF is
    quoted) or JSON lines, read in chunks by a session of its own."""

    def gen():
        session = session_factory(False)
        try:
            if fmt == "csv":
                buf = io.StringIO()
                writer = csv.writer(buf, lineterminator="\r\n")
                writer.writerow(RECORD_FIELDS)
                yield buf.getvalue()
            rows = session.execute(query.execution_options(yield_per=STREAM_CHUNK))
            for chunk in rows.partitions(STREAM_CHUNK):
                if fmt == "csv":
                    buf = io.StringIO()
                    writer = csv.writer(buf, lineterminator="\r\n")
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
        **GONE,
        200: {
            "content": {"text/csv": {}, "application/x-ndjson": {}},
            "description": "a JSON page, or the whole selection as CSV / JSON lines",
        },
    },
)
@accepts_query(is_range_param)
def get_results(
    request: Request,
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
    sort: Annotated[
        str | None, Query(max_length=300, description="e.g. -rmse_A (descending), N")
    ] = None,
    format: Literal["json", "csv", "jsonl"] = "json",
    limit: Annotated[int | None, Query(ge=1, le=10_000)] = None,
    offset: Annotated[int, Query(ge=0, le=10**9)] = 0,
):
    """The job's records (SPEC section 10 field names; matrices as nested lists; null,
    never NaN), filtered by any grid coordinate (repeat a parameter for several
    values). JSON is paginated (default limit 100); CSV and JSONL stream the whole
    selection (or `limit`/`offset` if given).

    `sort`: comma-separated numeric record fields, `-` for descending
    (`sort=-rmse_A,N`); nulls last; ties in grid order. Range filters on any numeric
    field: `<field>_lt`, `_lte`, `_gt`, `_gte` (`rmse_A_lt=0.01&N_gte=100`)."""
    job = team_job(session, caller.team_id, job_id)
    _not_pruned(job)
    codec = job_codec(session, job_id, job.spec)
    t = Result.__table__
    conds = _results_filter(job_id, system, sigma_w, N, estimator, gamma, rep)
    ranges = range_conditions(request, t)
    conds += ranges
    order = sort_order(sort, t) + ORDER
    if format == "json":
        lim = limit or 100
        if job.status == "succeeded" and not ranges:  # every cell stored: counted on the grid
            keys = _gamma_keys(gamma) if gamma else None
            total = count_cells(job.spec, system, sigma_w, N, estimator, keys, rep)
        else:
            total = session.scalar(COUNT.where(*conds))
        # in key order by default: the primary key's order, so the page is read off its index
        page = RECORDS.where(*conds).order_by(*order).limit(lim).offset(offset)
        rows = session.execute(page).all()
        body = encode_page(rows, codec, total, lim, offset)
        return Response(body, media_type="application/json")
    query = RECORDS.where(*conds).order_by(*order)
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
    gamma). Stored when the job succeeds; aggregated in the database from the results
    so far otherwise (`partial: true`)."""
    job = team_job(session, caller.team_id, job_id)
    if job.status != "succeeded":  # units store their groups' summaries as they finish
        return {
            "job_id": job_id,
            "partial": True,
            "groups": [_group_out(g) for g in summarize_in_db(session, job_id)],
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


@router.get("/compare", response_model=CompareOut, responses={**ERRORS, **GONE})
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
    limit: Annotated[int, Query(ge=1, le=COMPARE_MAX_ROWS)] = 1000,
    offset: Annotated[int, Query(ge=0, le=10**9)] = 0,
):
    """One metric across several jobs: mean, std (ddof 0) and count of the non-null
    values per job and per combination of the `by` fields, aggregated in the
    database; one page of at most `limit` groups (at most 10,000; `total` counts
    them all). Finished jobs are read from their stored summaries when `by` is
    within system, sigma_w, N, estimator and gamma."""
    items = _csv_list(jobs, "jobs")
    if not all(is_int_text(j) for j in items):
        raise FieldHTTPException(
            422, "must be comma-separated job ids (digits 0-9), e.g. 1,2", "jobs"
        )
    ids = [int(j) for j in items]
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
    found = [team_job(session, caller.team_id, j) for j in ids]
    try:
        page = compare_page(session, found, metric, by_fields, limit=limit, offset=offset)
    except NeedsCellRows as exc:
        raise FieldHTTPException(410, str(exc), "by") from None
    return {
        "metric": metric,
        "by": by_fields,
        "jobs": ids,
        "rows": page.rows,
        "total": page.total,
        "limit": limit,
        "offset": offset,
    }
