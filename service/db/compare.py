"""``GET /compare`` aggregated inside the database (bounded reads).

One metric of several jobs: count, mean and std (ddof 0) of its non-null values
per job and per combination of the ``by`` fields, one page of groups at a time
(with the number of groups). Each source row carries ``(n, m, s)``: a result row
is ``(1, x, 0)`` (``(0, NULL, 0)`` when x is null), a stored summary row its
group's (count, mean, std). They are pooled in two passes, as numpy and the
summaries do: the group's mean ``M = Σ n·m / Σ n`` (a window over the group), then
``var = Σ n·(s² + (m − M)²) / Σ n`` (the law of total variance: no cancellation).
A group whose largest |m| or s is above :data:`~service.db.aggregates.BIG` is pooled
scaled by ``TINY`` and scaled back (its squares would overflow, an error on
PostgreSQL), as the summaries of a running job are (:mod:`service.db.aggregates`).
Succeeded jobs are read from their summaries when ``by`` is within the summary's
group fields (a small fraction of the rows, and all that is left of a pruned job);
otherwise from the results. Aliases are prefixed ``w_``: SQLite names are
case-blind, and ``n`` would be the column ``N``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

from sqlalchemy import Float, Integer, case, cast, func, literal, select, union_all
from sqlalchemy.orm import Session

from svrobs_core.records import BOOL_FIELDS, GROUP_FIELDS, SUMMARY_FIELDS
from svrobs_lab.errors import NeedsCellRows

from .aggregates import BIG, TINY, scaled, square
from .models import Job, Result, Summary

COMPARE_BY = ("system", "sigma_w", "N", "N0", "estimator", "gamma", "rep")
CELL_KEY = frozenset(GROUP_FIELDS + ("rep",))  # one group is one cell: no aggregation
NULLABLE = frozenset({"gamma", "N0"})


@dataclass
class ComparePage:
    rows: list[dict]
    total: int


def _as_float(metric: str):
    """A results column as a float (PostgreSQL casts a boolean only to an integer)."""
    col = Result.__table__.c[metric]
    return cast(cast(col, Integer) if metric in BOOL_FIELDS else col, Float)


def _from_results(job_id: int, metric: str, by: list[str]):
    t = Result.__table__
    x = _as_float(metric)
    return select(
        t.c.job_id.label("job_id"),
        *[t.c[b].label(b) for b in by],
        case((x.is_(None), 0), else_=1).label("w_n"),
        x.label("w_m"),
        literal(0.0, Float).label("w_s"),
    ).where(t.c.job_id == job_id)


def _summary_stat(metric: str, name: str):
    return Summary.__table__.c.stats[(metric, name)].as_float()


def _from_summaries(job_id: int, metric: str, by: list[str]):
    t = Summary.__table__
    return select(
        t.c.job_id.label("job_id"),
        *[t.c[b].label(b) for b in by],
        func.coalesce(_summary_stat(metric, "count"), 0.0).label("w_n"),
        _summary_stat(metric, "mean").label("w_m"),
        func.coalesce(_summary_stat(metric, "std"), 0.0).label("w_s"),
    ).where(t.c.job_id == job_id)


def _pooled(src, keys: list) -> tuple[Any, list[Any]]:
    """Per group of ``keys``: w_count, the plain and scaled means w_a, w_b, the largest
    magnitude w_x and the pooled squared deviations w_q (plain or scaled as w_x says),
    and the number of groups w_total."""
    n, m, sd = src.c.w_n, src.c.w_m, src.c.w_s
    count = func.nullif(func.sum(n).over(partition_by=keys), 0)
    top = func.max(case((func.abs(m) > sd, func.abs(m)), else_=sd)).over(partition_by=keys)
    plain = func.sum(n * case((func.abs(m) > BIG, 0.0), else_=m)).over(partition_by=keys) / count
    small = func.sum(n * scaled(m)).over(partition_by=keys) / count
    rows = select(*keys, n, m, sd, plain.label("w_a"), small.label("w_b"), top.label("w_x"))
    r = rows.subquery("rows")
    big = r.c.w_x > BIG
    q = case(
        (big, r.c.w_n * (square(scaled(r.c.w_s)) + square(scaled(r.c.w_m) - r.c.w_b))),
        else_=r.c.w_n * (square(r.c.w_s) + square(r.c.w_m - r.c.w_a)),
    )
    rkeys = [r.c[k.name] for k in keys]
    return select(
        *rkeys,
        func.sum(r.c.w_n).label("w_count"),
        func.max(r.c.w_a).label("w_a"),
        func.max(r.c.w_b).label("w_b"),
        func.max(r.c.w_x).label("w_x"),
        func.sum(q).label("w_q"),
        func.count().over().label("w_total"),
    ).group_by(*rkeys), rkeys


def _finite(v: float) -> float | None:
    """A mean or std beyond the double range (scaled back) is null."""
    return v if math.isfinite(v) else None


def _order_of(col) -> tuple:
    """ORDER BY terms of a ``by`` column: nulls last (only gamma and N0 have any)."""
    return (col.is_(None), col) if col.name in NULLABLE else (col,)


def compare_page(
    session: Session, jobs: list[Job], metric: str, by: list[str], *, limit: int, offset: int
) -> ComparePage:
    """One page of the comparison (groups ordered by the ``by`` fields, nulls last,
    then by job id) and the number of groups. Raises :class:`NeedsCellRows` when
    ``by`` needs the cell rows of a pruned job."""
    from_summaries = set(by) <= set(GROUP_FIELDS) and metric in SUMMARY_FIELDS
    pruned = [j.id for j in jobs if j.pruned_at is not None]
    if pruned and not from_summaries:
        raise NeedsCellRows(pruned, by, GROUP_FIELDS)
    if set(by) >= CELL_KEY:
        return _cell_page(session, jobs, metric, by, limit=limit, offset=offset)
    parts = []
    for j in jobs:
        source = _from_summaries if from_summaries and j.status == "succeeded" else _from_results
        parts.append(source(j.id, metric, by))
    both: Any = parts[0] if len(parts) == 1 else union_all(*parts)  # mypy cannot join them
    src = both.subquery("src")
    grouped, rkeys = _pooled(src, [src.c.job_id] + [src.c[b] for b in by])
    order = [c for k in rkeys[1:] for c in _order_of(k)] + [rkeys[0]]
    page = session.execute(grouped.order_by(*order).limit(limit).offset(offset)).all()
    if page:
        total = page[0]._mapping["w_total"]
    else:  # past the end: count the groups
        total = session.scalar(select(func.count()).select_from(grouped.subquery()))
    out = []
    for row in page:
        r = row._mapping
        count = int(r["w_count"] or 0)
        mean = std = None
        if count:
            scale = 1.0 / TINY if float(r["w_x"]) > BIG else 1.0
            mean = _finite(float(r["w_b"] if scale != 1.0 else r["w_a"]) * scale)
            std = _finite(math.sqrt(max(float(r["w_q"] or 0.0), 0.0) / count) * scale)
        out.append(
            {
                "job_id": r["job_id"],
                **{b: r[b] for b in by},
                "mean": mean,
                "std": std,
                "count": count,
            }
        )
    return ComparePage(out, int(total or 0))


def _cell_page(session, jobs, metric, by, *, limit, offset) -> ComparePage:
    """``by`` holds the whole cell key: each group is one row, read in index order."""
    t = Result.__table__
    ids = [j.id for j in jobs]
    x = _as_float(metric)
    order = [c for b in by for c in _order_of(t.c[b])]
    if by.index("estimator") < by.index("gamma"):
        # gamma is null exactly for ols: within one estimator, gamma_key (-1 for ols)
        # orders as gamma with nulls last, and lets the cell-key index give the order
        i = next(k for k, c in enumerate(order) if c is t.c.gamma)
        order[i - 1 : i + 1] = [t.c.gamma_key]
    q = (
        select(t.c.job_id, *[t.c[b] for b in by], x.label("w_x"))
        .where(t.c.job_id.in_(ids))
        .order_by(*order, t.c.job_id)
        .limit(limit)
        .offset(offset)
    )
    out = []
    for row in session.execute(q):
        r = row._mapping
        v = r["w_x"]
        ok = v is not None and math.isfinite(v)
        out.append(
            {
                "job_id": r["job_id"],
                **{b: r[b] for b in by},
                "mean": float(v) if ok else None,
                "std": 0.0 if ok else None,
                "count": int(ok),
            }
        )
    # a succeeded job holds each of its n_cells cells once: count only the others' rows
    total = sum(j.n_cells for j in jobs if j.status == "succeeded")
    running = [j.id for j in jobs if j.status != "succeeded"]
    if running:
        total += session.scalar(select(func.count()).select_from(t).where(t.c.job_id.in_(running)))
    return ComparePage(out, int(total))
