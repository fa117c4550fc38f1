"""Selections of a job's result rows: filters on the grid coordinates, range filters
and sort keys of numeric record fields, counted, paged or streamed; the stored
summary rows; the grid's values per coordinate.

A bad filter value is :class:`~svrobs_lab.errors.Invalid` naming the parameter.
``sort=-rmse_A,N`` orders by numeric record fields, ``-`` descending, nulls last;
``rmse_A_lt=0.01``, ``N_gte=100`` are range conditions (suffixes ``_lt``, ``_lte``,
``_gt``, ``_gte``).
"""

from __future__ import annotations

import math
import re
from collections.abc import Iterable, Iterator, Sequence

from sqlalchemy import JSON, Select, String, column, func, select, true
from sqlalchemy.orm import Session

from svrobs_core.records import BOOL_FIELDS, NUMERIC_FIELDS, SUMMARY_FIELDS
from svrobs_lab.errors import Invalid

from .models import Result, Summary
from .results_store import record_select

RANGE_OPS = {"lt": "__lt__", "lte": "__le__", "gt": "__gt__", "gte": "__ge__"}
RANGE_RE = re.compile(r"^(?P<field>\w+?)_(?P<op>lt|lte|gt|gte)$")
MAX_SORT_KEYS = 5
# range filters of one request: 28 fields x 4 bounds need no more, and SQLite refuses
# a WHERE whose ANDs nest deeper than 1000 ("Expression tree is too large")
MAX_RANGE_FILTERS = 100
RANGE_FIELDS = tuple(f for f in NUMERIC_FIELDS if f not in BOOL_FIELDS)  # booleans: no <
T = Result.__table__
# built once (a select of 41 columns costs ~1 ms to construct); callers add WHERE/ORDER
RECORDS = record_select()  # as stored: decoded by results_store.decode_rows
COUNT = select(func.count()).select_from(T)
# the key order (the primary key's): a page is read off its index
ORDER = (T.c.system, T.c.sigma_w, T.c.N, T.c.estimator, T.c.gamma_key, T.c.rep)


def is_range_param(name: str) -> bool:
    m = RANGE_RE.match(name)
    return m is not None and m.group("field") in RANGE_FIELDS


def _numeric(field: str, param: str) -> None:
    if field not in NUMERIC_FIELDS:
        raise Invalid(
            f"{field!r} is not a numeric record field; one of {', '.join(NUMERIC_FIELDS)}",
            field=param,
        )


def sort_order(sort: str | None) -> list:
    """ORDER BY terms of ``sort`` (comma-separated numeric fields, ``-`` descending),
    then the key order."""
    if not sort:
        return list(ORDER)
    keys = [k.strip() for k in sort.split(",") if k.strip()]
    if not keys or len(keys) > MAX_SORT_KEYS:
        raise Invalid(f"must name 1 to {MAX_SORT_KEYS} numeric fields, e.g. -rmse_A", field="sort")
    terms = []
    for key in keys:
        desc = key.startswith("-")
        field = key.lstrip("+-")
        _numeric(field, "sort")
        col = T.c[field]
        terms.append((col.desc() if desc else col.asc()).nulls_last())
    return terms + list(ORDER)


def range_terms(bounds: Iterable[tuple[str, float]]) -> list:
    """WHERE conditions of the ``(name, bound)`` pairs whose name is a range parameter
    (each bound a finite number, read from its text by the caller:
    :func:`svrobs_lab.params.read_number`); Invalid naming the first one past
    :data:`MAX_RANGE_FILTERS`."""
    conds: list = []
    for name, bound in bounds:
        m = RANGE_RE.match(name)
        if m is None or m.group("field") not in RANGE_FIELDS:
            continue
        if len(conds) == MAX_RANGE_FILTERS:
            raise Invalid(
                f"at most {MAX_RANGE_FILTERS} range filters (<field>_lt, _lte, _gt, _gte) "
                "in one request",
                field=name,
            )
        conds.append(getattr(T.c[m.group("field")], RANGE_OPS[m.group("op")])(bound))
    return conds


def grid_conditions(job_id: int, system, sigma_w, N, estimator, gamma_keys, rep) -> list:
    """The WHERE conditions of the job's rows at these grid values (each a list, or
    empty/None for all; ``gamma_keys`` as stored: -1 for ols)."""
    conds = [T.c.job_id == job_id]
    if system:
        conds.append(T.c.system.in_(system))
    if sigma_w:
        if not all(math.isfinite(v) for v in sigma_w):
            raise Invalid("must be finite", field="sigma_w")
        conds.append(T.c.sigma_w.in_(sigma_w))
    if N:
        conds.append(T.c.N.in_(N))
    if estimator:
        conds.append(T.c.estimator.in_(estimator))
    if gamma_keys:
        conds.append(T.c.gamma_key.in_(gamma_keys))
    if rep:
        conds.append(T.c.rep.in_(rep))
    return conds


def count_rows(session: Session, conds: Sequence) -> int:
    return int(session.scalar(COUNT.where(*conds)) or 0)


def rows_query(conds: Sequence, order: Sequence, *, limit=None, offset: int = 0) -> Select:
    """The selection's rows (as stored), in ``order``."""
    query = RECORDS.where(*conds).order_by(*order)
    if limit is not None:
        query = query.limit(limit)
    if offset:
        query = query.offset(offset)
    return query


def page_rows(session: Session, conds, order, *, limit: int, offset: int) -> list:
    return list(session.execute(rows_query(conds, order, limit=limit, offset=offset)).all())


def row_chunks(session: Session, query: Select, size: int) -> Iterator[Sequence]:
    """The rows of ``query`` in chunks of ``size``, read as they are consumed."""
    rows = session.execute(query.execution_options(yield_per=size))
    yield from rows.partitions(size)


def summary_rows(
    session: Session, job_id: int, *, limit: int | None = None, offset: int = 0
) -> list[Summary]:
    """The job's stored summaries in grid order, a page of ``limit`` from ``offset``."""
    return list(
        session.scalars(
            select(Summary)
            .where(Summary.job_id == job_id)
            .order_by(
                Summary.system, Summary.sigma_w, Summary.N, Summary.estimator, Summary.gamma_key
            )
            .limit(limit)
            .offset(offset)
        )
    )


def count_summaries(session: Session, job_id: int) -> int:
    """How many stored summary groups the job has."""
    q = select(func.count()).select_from(Summary).where(Summary.job_id == job_id)
    return int(session.scalar(q) or 0)


def grid_choices(session: Session, job_id: int) -> dict[str, list]:
    """The values of each grid coordinate, from the job's stored summaries."""
    out = {}
    for f in ("system", "sigma_w", "N", "estimator", "gamma_key"):
        col = getattr(Summary, f)
        q = select(col).where(Summary.job_id == job_id).distinct().order_by(col)
        out[f] = list(session.scalars(q))
    out["gamma"] = ["null" if g < 0 else repr(g) for g in out.pop("gamma_key")]
    return out


def summary_stats(session: Session, job_id: int, fields: Sequence[str]) -> list[dict]:
    """The job's summary groups with the stats of ``fields`` only: the database takes
    those fields out of each row's stats (the rest is never decoded)."""
    rows = session.execute(
        select(
            Summary.system,
            Summary.sigma_w,
            Summary.N,
            Summary.estimator,
            Summary.gamma,
            *(Summary.stats[f] for f in fields),
        ).where(Summary.job_id == job_id)
    ).all()
    return [
        dict(
            system=r[0],
            sigma_w=r[1],
            N=r[2],
            estimator=r[3],
            gamma=r[4],
            stats=dict(zip(fields, r[5:])),
        )
        for r in rows
    ]


def summary_metrics(session: Session, job_id: int) -> list[str]:
    """Summary fields with a non-null mean in at least one of the job's groups, in
    record order (json_each: each row's stats parsed once, on either dialect)."""
    each = func.json_each(Summary.stats).table_valued(column("key", String), column("value", JSON))
    seen = set(
        session.scalars(
            select(each.c.key)
            .select_from(Summary)
            .join(each, true())
            .where(Summary.job_id == job_id, each.c.value["mean"].as_float().is_not(None))
            .distinct()
        )
    )
    return [f for f in SUMMARY_FIELDS if f in seen]
