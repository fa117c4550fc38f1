"""GET /jobs/{id}/results (JSON page, CSV or JSONL stream), /jobs/{id}/summary, /compare."""

from __future__ import annotations

from typing import Annotated, Literal

from fastapi import APIRouter, Query, Request
from fastapi.responses import Response, StreamingResponse
from pydantic import Field

from service.api.deps import DB, MAX_ID, CurrentCaller, JobId, SessionFactoryDep, SettingsDep
from service.api.errors import ERRORS, error_docs
from service.api.query_params import accepts_query
from service.db.result_queries import is_range_param
from service.http.security import attachment
from svrobs_lab import results
from svrobs_lab.jobs import team_job
from svrobs_lab.schemas import CompareOut, ResultPage, SummaryOut

router = APIRouter(tags=["results"])

COMPARE_MAX_ROWS = 10_000
GONE = error_docs(410)  # a job pruned by retention

FloatList = Annotated[list[float] | None, Query()]
# N and rep are 32-bit integer columns: a larger filter value would overflow the driver.
Int32 = Annotated[int, Field(ge=-MAX_ID - 1, le=MAX_ID)]
IntList = Annotated[list[Int32] | None, Query()]


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
    settings: SettingsDep,
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
    """The job's records (field names of docs/spec.md#record-fields; matrices as nested lists; null,
    never NaN), filtered by any grid coordinate (repeat a parameter for several
    values). JSON is paginated (default limit 100): a page holds at most
    SVROBS_MAX_PAGE_MATRIX_ENTRIES matrix entries (1,000,000), so with large
    systems its `limit` is lowered; `next_offset` is where the next page starts
    (null after the last). CSV and JSONL stream the whole selection (or
    `limit`/`offset` if given) at constant memory; a team streams at most
    SVROBS_STREAMS_PER_TEAM at once (429 with Retry-After beyond).

    `sort`: comma-separated numeric record fields, `-` for descending
    (`sort=-rmse_A,N`); nulls last; ties in grid order. Range filters on any numeric
    field: `<field>_lt`, `_lte`, `_gt`, `_gte` (`rmse_A_lt=0.01&N_gte=100`)."""
    job = team_job(session, caller, job_id)
    results.not_pruned(job)
    sel = results.select_rows(
        job,
        system=system,
        sigma_w=sigma_w,
        N=N,
        estimator=estimator,
        gamma=gamma,
        rep=rep,
        ranges=request.query_params.multi_items(),
        sort=sort,
    )
    if format == "json":
        body = results.page_json(
            session,
            sel,
            limit=limit or 100,
            offset=offset,
            max_entries=settings.MAX_PAGE_MATRIX_ENTRIES,
        )
        return Response(body, media_type="application/json")
    chunks, media = results.stream(
        session,
        session_factory,
        sel,
        format,
        limit=limit,
        offset=offset,
        slots=request.app.state.stream_slots,
    )
    ext = "csv" if format == "csv" else "jsonl"
    return StreamingResponse(
        chunks,
        media_type=media,
        headers={"Content-Disposition": attachment(f"job-{job_id}-results.{ext}")},
    )


@router.get("/jobs/{job_id}/summary", response_model=SummaryOut, responses=ERRORS)
def get_summary(
    job_id: JobId,
    session: DB,
    caller: CurrentCaller,
    limit: Annotated[int, Query(ge=1, le=results.SUMMARY_PAGE_MAX)] = results.SUMMARY_PAGE_MAX,
    offset: Annotated[int, Query(ge=0, le=10**9)] = 0,
):
    """Mean, std and count of every numeric field per (system, sigma_w, N, estimator,
    gamma), a page of `limit` groups (at most 10,000) from `offset` in grid order, and
    `total`. Stored when the job succeeds; aggregated in the database from the results
    so far otherwise (`partial: true`)."""
    job = team_job(session, caller, job_id)
    return results.summary(session, job, limit=limit, offset=offset)


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
    return results.compare(
        session, caller, jobs=jobs, metric=metric, by=by, limit=limit, offset=offset
    )
