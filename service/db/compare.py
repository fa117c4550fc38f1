"""``GET /compare`` aggregated inside the database (issue 13, bounded reads).

One metric of several jobs: count, mean and std (ddof 0) of its non-null values
per job and per combination of the ``by`` fields, one page of groups at a time.
Each source row carries ``(n, m, s)``: a result row is ``(1, x, 0)`` (``(0, NULL,
0)`` when x is null), a stored summary row is its group's (count, mean, std).
Pooling them is exact: ``mean = Σ n·m / Σ n`` and ``var = Σ n·(s² + (m −
mean)²) / Σ n`` (a window function gives each row its group's mean: two passes,
as numpy's ``std``). Aliases are prefixed ``w_``: SQLite names are case-blind,
and ``n`` would be the column ``N``. Succeeded jobs are read from their summaries when ``by``
is within the summary's group fields (a small fraction of the rows, and all
that is left of a pruned job); otherwise from the results.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from sqlalchemy import Float, case, cast, func, literal, select, union_all
from sqlalchemy.orm import Session

from svrobs_core.records import GROUP_FIELDS, SUMMARY_FIELDS

from .models import Job, Result, Summary

COMPARE_BY = ("system", "sigma_w", "N", "N0", "estimator", "gamma", "rep")


class NeedsCellRows(Exception):
    """The grouping needs cell rows that retention dropped (``job_ids``)."""

    def __init__(self, job_ids: list[int], by: list[str]):
        self.job_ids = job_ids
        super().__init__(
            f"job(s) {', '.join(map(str, job_ids))} were pruned by the team's retention "
            f"policy: grouping by {', '.join(b for b in by if b not in GROUP_FIELDS)} needs "
            f"their cell rows; group by {', '.join(GROUP_FIELDS)} (from the stored summaries)"
        )


@dataclass
class ComparePage:
    rows: list[dict]
    total: int


def _from_results(job_ids: list[int], metric: str, by: list[str]):
    t = Result.__table__
    x = cast(t.c[metric], Float)
    return select(
        t.c.job_id.label("job_id"),
        *[t.c[b].label(b) for b in by],
        case((x.is_(None), 0), else_=1).label("w_n"),
        x.label("w_m"),
        literal(0.0, Float).label("w_s"),
    ).where(t.c.job_id.in_(job_ids))


def _from_summaries(job_ids: list[int], metric: str, by: list[str]):
    t = Summary.__table__

    def stat(name: str):
        return t.c.stats[(metric, name)].as_float()

    return select(
        t.c.job_id.label("job_id"),
        *[t.c[b].label(b) for b in by],
        func.coalesce(stat("count"), 0.0).label("w_n"),
        stat("mean").label("w_m"),
        func.coalesce(stat("std"), 0.0).label("w_s"),
    ).where(t.c.job_id.in_(job_ids))


def compare_page(
    session: Session, jobs: list[Job], metric: str, by: list[str], *, limit: int, offset: int
) -> ComparePage:
    """One page of the comparison (groups ordered by the ``by`` fields, nulls last,
    then by job id) and the number of groups. Raises :class:`NeedsCellRows` when
    ``by`` needs the cell rows of a pruned job."""
    from_summaries = set(by) <= set(GROUP_FIELDS) and metric in SUMMARY_FIELDS
    pruned = [j.id for j in jobs if j.pruned_at is not None]
    if pruned and not from_summaries:
        raise NeedsCellRows(pruned, by)
    use_summary = [j.id for j in jobs if from_summaries and j.status == "succeeded"]
    use_rows = [j.id for j in jobs if j.id not in use_summary]
    parts = []
    if use_summary:
        parts.append(_from_summaries(use_summary, metric, by))
    if use_rows:
        parts.append(_from_results(use_rows, metric, by))
    src = (parts[0] if len(parts) == 1 else union_all(*parts)).subquery("src")
    keys = [src.c.job_id] + [src.c[b] for b in by]
    sum_n = func.sum(src.c.w_n).over(partition_by=keys)
    group_mean = func.sum(src.c.w_n * src.c.w_m).over(partition_by=keys) / func.nullif(sum_n, 0)
    rows = select(*keys, src.c.w_n, src.c.w_m, src.c.w_s, group_mean.label("w_gm")).subquery("rows")
    gkeys = [rows.c.job_id] + [rows.c[b] for b in by]
    dev = rows.c.w_m - rows.c.w_gm
    total_n = func.sum(rows.c.w_n)
    grouped = select(
        *gkeys,
        total_n.label("w_count"),
        func.max(rows.c.w_gm).label("w_mean"),
        (func.sum(rows.c.w_n * (rows.c.w_s * rows.c.w_s + func.coalesce(dev * dev, 0.0)))).label(
            "w_ss"
        ),
    ).group_by(*gkeys)
    order = [c for b in by for c in (rows.c[b].is_(None), rows.c[b])] + [rows.c.job_id]
    page = session.execute(grouped.order_by(*order).limit(limit).offset(offset)).all()
    total = session.scalar(select(func.count()).select_from(grouped.subquery()))
    out = []
    for row in page:
        r = row._mapping
        count = int(r["w_count"] or 0)
        out.append(
            {
                "job_id": r["job_id"],
                **{b: r[b] for b in by},
                "mean": float(r["w_mean"]) if count else None,
                "std": math.sqrt(max(float(r["w_ss"]), 0.0) / count) if count else None,
                "count": count,
            }
        )
    return ComparePage(out, int(total or 0))
