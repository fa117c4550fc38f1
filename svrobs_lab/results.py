"""Results: a job's records filtered, sorted, paged or streamed (CSV, JSON lines), its
summary, and one metric compared across jobs (docs/spec.md#record-fields).

The REST routes (``GET /jobs/{id}/results``, ``/summary``, ``/compare``) and the
web's results and compare pages select through these functions, so both agree.
"""

from __future__ import annotations

import json
import math
import weakref
from collections.abc import Iterable, Iterator
from dataclasses import dataclass

from sqlalchemy.orm import Session

from service.db import result_queries as rq
from service.db.aggregates import count_groups_in_db, summarize_in_db
from service.db.compare import COMPARE_BY, compare_page
from service.db.models import Job
from service.db.result_codec import ResultCodec
from service.db.results_store import count_cells, decode_rows, job_codec
from svrobs_core.records import GROUP_FIELDS, NUMERIC_FIELDS, RECORD_FIELDS

from .auth import MAX_ID, Caller
from .errors import Gone, Invalid
from .jobs import team_job
from .params import is_float_text, is_int_text, read_number
from .record_json import encode_lines, encode_page
from .slots import TeamSlots

STREAM_CHUNK = 1000  # rows read at a time by a stream, at most
STREAM_ENTRIES = 250_000  # matrix entries read at a time by a stream, at most
COMPARE_MAX_JOBS = 50
# a text cell starting with one of these is a formula to a spreadsheet (OWASP, "CSV
# injection"): it is written with a leading single quote
FORMULA_START = ("=", "+", "-", "@", "\t", "\r")
CSV_HEADER = ",".join(RECORD_FIELDS) + "\r\n"


@dataclass(frozen=True)
class Selection:
    """A job's rows: WHERE conditions, ORDER BY terms, and whether a range filter is
    among them (then the count is read, not computed from the grid)."""

    job: Job
    conds: list
    order: list
    gamma_keys: list[float] | None
    has_ranges: bool
    grid: tuple


def gamma_keys(gamma: Iterable[str]) -> list[float]:
    """``gamma`` filter values as stored keys: a finite decimal >= 0, or null/none/ols
    (stored as -1, which a number typed as -1 must not reach)."""
    keys = []
    for g in gamma:
        if g.lower() in ("null", "none", "ols"):
            keys.append(-1.0)
            continue
        if not is_float_text(g) or not math.isfinite(float(g)):
            raise Invalid("must be a finite decimal number or 'null'", field="gamma")
        if float(g) < 0:
            raise Invalid("must be >= 0, or 'null' for OLS", field="gamma")
        keys.append(float(g))
    return keys


def not_pruned(job: Job) -> None:
    """Gone for a job whose cell rows retention dropped (what is left, and where)."""
    if job.pruned_at is not None:
        raise Gone(
            f"job {job.id}'s cell rows were dropped on {job.pruned_at:%Y-%m-%d %H:%M} UTC by "
            "the team's retention policy; its summary (GET /jobs/{id}/summary), compare by "
            "system, sigma_w, N, estimator and gamma, and its report remain"
        )


def select_rows(
    job: Job,
    *,
    system=None,
    sigma_w=None,
    N=None,
    estimator=None,
    gamma=None,
    rep=None,
    ranges: Iterable[tuple[str, str]] = (),
    sort: str | None = None,
) -> Selection:
    """The rows of ``job`` at these grid values (lists; empty or None: all), within
    the range parameters ``ranges`` (``(name, value)`` pairs), in ``sort`` order."""
    keys = gamma_keys(gamma) if gamma else None
    conds = rq.grid_conditions(job.id, system, sigma_w, N, estimator, keys, rep)
    bounds = [(name, read_number(name, text)) for name, text in ranges if rq.is_range_param(name)]
    range_conds = rq.range_terms(bounds)
    return Selection(
        job=job,
        conds=conds + range_conds,
        order=rq.sort_order(sort),
        gamma_keys=keys,
        has_ranges=bool(range_conds),
        grid=(system, sigma_w, N, estimator, rep),
    )


def count(session: Session, sel: Selection, *, grid: bool = True) -> int:
    """How many rows the selection has (with ``grid``, computed from the grid for a
    succeeded job without range filters: every cell is stored)."""
    if grid and sel.job.status == "succeeded" and not sel.has_ranges:
        system, sigma_w, N, estimator, rep = sel.grid
        return count_cells(sel.job.spec, system, sigma_w, N, estimator, sel.gamma_keys, rep)
    return rq.count_rows(session, sel.conds)


# the matrices a record holds with each stage (the others are null)
STAGE_MATRICES = {
    "estimate": ("A_hat", "B_hat"),
    "bounds": ("radii_A", "radii_B"),
    "gain": ("L", "K"),
}


def row_entries(codec: ResultCodec, spec: dict) -> int:
    """The matrix entries of one record of the job (its largest system's): A_hat and
    B_hat, radii_A and radii_B with ``bounds``, L and K with ``gain``."""
    stages = set(spec.get("stages") or ()) | {"estimate"}
    fields = [f for st in stages for f in STAGE_MATRICES.get(st, ())]
    return max(
        (sum(shapes[f][0] * shapes[f][1] for f in fields) for shapes in codec.shapes.values()),
        default=0,
    )


def rows_within(codec: ResultCodec, spec: dict, max_entries: int | None, rows: int) -> int:
    """At most ``rows``, and at most as many rows as hold ``max_entries`` matrix
    entries (at least one; None: no cap)."""
    per_row = row_entries(codec, spec)
    if not max_entries or per_row == 0:
        return rows
    return max(1, min(rows, max_entries // per_row))


def page_json(
    session: Session, sel: Selection, *, limit: int, offset: int, max_entries: int | None = None
) -> bytes:
    """One page of the selection as a ``ResultPage`` JSON body: at most ``limit``
    rows, fewer when they would hold more than ``max_entries`` matrix entries (its
    ``limit`` is then the lowered one); ``next_offset`` is where the next page starts
    (null after the last; docs/deploy.md#bounded-responses)."""
    codec = job_codec(session, sel.job.id, sel.job.spec)
    limit = rows_within(codec, sel.job.spec, max_entries, limit)
    total = count(session, sel)
    rows = rq.page_rows(session, sel.conds, sel.order, limit=limit, offset=offset)
    after = offset + len(rows)
    nxt = after if len(rows) == limit and after < total else None
    return encode_page(rows, codec, total, limit, offset, next_offset=nxt)


def page_records(session: Session, sel: Selection, *, limit: int, offset: int) -> list[dict]:
    """One page of the selection as decoded records."""
    rows = rq.page_rows(session, sel.conds, sel.order, limit=limit, offset=offset)
    return decode_rows(rows, job_codec(session, sel.job.id, sel.job.spec))


def _csv_field(v) -> str:
    """One field of a CSV row (RFC 4180). A number is written as it is (-0.5 stays a
    number), null as an empty field; any other value is text (true/false, a matrix as
    JSON, a name or a note), always in double quotes, so that no comma, semicolon or
    tab inside it starts another cell in a spreadsheet that splits the line on it, and
    with a leading single quote when it starts like a formula (:data:`FORMULA_START`,
    OWASP's advice against CSV injection)."""
    if v is None:
        return ""
    if isinstance(v, str):
        text = "'" + v if v.startswith(FORMULA_START) else v
    elif isinstance(v, bool):
        text = "true" if v else "false"
    elif isinstance(v, (list, dict)):
        text = json.dumps(v, allow_nan=False, separators=(",", ":"))
    elif isinstance(v, float):
        return repr(v) if math.isfinite(v) else ""
    else:
        return str(v)  # an int
    return '"' + text.replace('"', '""') + '"'


def _csv_row(values: Iterable) -> str:
    """One line of CSV (CRLF-terminated) of these values (:func:`_csv_field`)."""
    return ",".join(_csv_field(v) for v in values) + "\r\n"


def stream(
    session: Session,
    session_factory,
    sel: Selection,
    fmt: str,
    *,
    limit=None,
    offset: int = 0,
    slots: TeamSlots | None = None,
) -> tuple[Iterator, str]:
    """(chunks, media type) of the selection as CSV (RFC 4180: CRLF line ends, every
    text field quoted, :func:`_csv_row`) or JSON lines, read in chunks by a reading
    session of its own (``session_factory(False)``) once iterated. ``session``, the
    request's, is closed first. A chunk holds at most STREAM_CHUNK rows and
    STREAM_ENTRIES matrix entries.

    The reading session holds a database connection until the client has read the
    last chunk, however slowly it reads: with ``slots``
    (:func:`svrobs_lab.slots.stream_slots`) the stream takes one of the job's team's
    first (RateLimited when none is free) and gives it back when it ends, is closed,
    or is dropped unread."""
    release = slots.take(sel.job.team_id) if slots is not None else None
    try:
        codec: ResultCodec = job_codec(session, sel.job.id, sel.job.spec)
        query = rq.rows_query(sel.conds, sel.order, limit=limit, offset=offset)
        size = rows_within(
            codec, sel.job.spec, STREAM_ENTRIES, STREAM_CHUNK
        )  # constant memory whatever n is
        session.close()
    except BaseException:
        if release is not None:
            release()
        raise

    def gen():
        own = session_factory(False)
        try:
            if fmt == "csv":
                yield CSV_HEADER
            for chunk in rq.row_chunks(own, query, size):
                if fmt == "csv":
                    recs = decode_rows(chunk, codec)
                    yield "".join(_csv_row(rec[f] for f in RECORD_FIELDS) for rec in recs)
                else:
                    yield encode_lines(chunk, codec)
        finally:
            own.close()
            if release is not None:
                release()

    chunks = gen()
    if release is not None:  # a generator never started runs no finally
        weakref.finalize(chunks, release)
    media = "text/csv; charset=utf-8" if fmt == "csv" else "application/x-ndjson"
    return chunks, media


def _group_out(g: dict) -> dict:
    return {**{k: g[k] for k in GROUP_FIELDS}, "count": g["count"], "stats": g["stats"]}


# a page of a job's summary holds at most this many groups (about 1.5 kB each as JSON)
SUMMARY_PAGE_MAX = 10_000


def summary(session: Session, job: Job, *, limit: int = SUMMARY_PAGE_MAX, offset: int = 0) -> dict:
    """Mean, std and count of every numeric field per group, one page of ``limit``
    groups from ``offset`` in grid order, with how many there are: stored when the
    job succeeded, aggregated in the database from the results so far otherwise."""
    page = {"limit": limit, "offset": offset}
    if job.status != "succeeded":  # units store their groups' summaries as they finish
        rows = summarize_in_db(session, job.id, limit=limit, offset=offset)
        total = count_groups_in_db(session, job.id)
        groups = [_group_out(g) for g in rows]
        return {"job_id": job.id, "partial": True, "groups": groups, "total": total, **page}
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
        for s in rq.summary_rows(session, job.id, limit=limit, offset=offset)
    ]
    total = rq.count_summaries(session, job.id)
    return {"job_id": job.id, "partial": False, "groups": groups, "total": total, **page}


def _csv_list(value: str, name: str) -> list[str]:
    items = [v.strip() for v in value.split(",") if v.strip()]
    if not items:
        raise Invalid("must be a non-empty comma-separated list", field=name)
    return items


def compare(
    session: Session,
    caller: Caller,
    *,
    jobs: str,
    metric: str,
    by: str = "N,estimator,gamma",
    limit: int = 1000,
    offset: int = 0,
) -> dict:
    """One metric across the caller's jobs ``jobs`` (comma-separated ids): count, mean
    and std per job and per combination of the ``by`` fields (comma-separated), one
    page of groups (``service.db.compare``)."""
    items = _csv_list(jobs, "jobs")
    if not all(is_int_text(j) for j in items):
        raise Invalid("must be comma-separated job ids (digits 0-9), e.g. 1,2", field="jobs")
    ids = [int(j) for j in items]
    if len(ids) > COMPARE_MAX_JOBS:
        raise Invalid(f"at most {COMPARE_MAX_JOBS} job ids, got {len(ids)}", field="jobs")
    bad = next((i for i in ids if i < 1 or i > MAX_ID), None)
    if bad is not None:
        raise Invalid(f"{bad} is not a job id (ids run from 1 to {MAX_ID})", field="jobs")
    ids = list(dict.fromkeys(ids))
    if metric not in NUMERIC_FIELDS:
        raise Invalid(
            "must be a numeric record field: "
            + ", ".join(f for f in NUMERIC_FIELDS if f not in COMPARE_BY),
            field="metric",
        )
    by_fields = list(dict.fromkeys(_csv_list(by, "by")))
    for b in by_fields:
        if b not in COMPARE_BY:
            raise Invalid(f"{b!r} is not one of {', '.join(COMPARE_BY)}", field="by")
    found = [team_job(session, caller, j) for j in ids]
    page = compare_page(session, found, metric, by_fields, limit=limit, offset=offset)
    return {
        "metric": metric,
        "by": by_fields,
        "jobs": ids,
        "rows": page.rows,
        "total": page.total,
        "limit": limit,
        "offset": offset,
    }


__all__ = [
    "COMPARE_BY",
    "Selection",
    "compare",
    "count",
    "gamma_keys",
    "not_pruned",
    "page_json",
    "page_records",
    "row_entries",
    "rows_within",
    "select_rows",
    "stream",
    "summary",
]
