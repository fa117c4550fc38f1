"""A running job's summary aggregated inside the database (bounded reads).

What :func:`svrobs_core.records.summarize_columns` computes from the rows (count,
mean and std with ddof 0 of every summary field per (system, sigma_w, N,
estimator, gamma)), as two SQL passes over the job's rows: the group means,
then the squared deviations from them (as numpy does), so that the API never
reads the rows themselves. Finished jobs have their summaries stored.
"""

from __future__ import annotations

import math

from sqlalchemy import Float, Integer, and_, case, cast, func, select
from sqlalchemy.orm import Session

from svrobs_core.records import BOOL_FIELDS, GROUP_FIELDS, SUMMARY_FIELDS, stat_entry

from .models import Result

# the group's key columns; gamma_key (never null) joins the two passes
KEY = ("system", "sigma_w", "N", "estimator", "gamma_key")


def _value(f: str):
    col = Result.__table__.c[f]
    return cast(cast(col, Integer) if f in BOOL_FIELDS else col, Float)


# Groups whose largest |value| is above BIG are summed as value * TINY (squares
# stay below ~1e217), then scaled back: a plain sum of squares would overflow,
# which PostgreSQL reports as an error. PostgreSQL also refuses a product that
# underflows to 0: terms below NEGLIGIBLE are taken as 0 (against a group
# maximum above BIG, or as a squared deviation below 1e-300).
BIG, TINY, NEGLIGIBLE = 1e150, 1e-200, 1e-100


def scaled(v):
    return case((func.abs(v) < NEGLIGIBLE, 0.0), else_=v * TINY)


def square(x):
    return case((func.abs(x) < 1e-150, 0.0), else_=x * x)


def count_groups_in_db(session: Session, job_id: int) -> int:
    """How many groups the job's rows hold so far."""
    t = Result.__table__
    groups = (
        select(*[t.c[k] for k in KEY]).where(t.c.job_id == job_id).group_by(*[t.c[k] for k in KEY])
    )
    return int(session.scalar(select(func.count()).select_from(groups.subquery())) or 0)


def summarize_in_db(
    session: Session, job_id: int, *, limit: int | None = None, offset: int = 0
) -> list[dict]:
    """The job's groups as ``summarize_columns`` gives them, ordered by group, a page
    of ``limit`` from ``offset`` (a mean or std beyond the double range is null with
    a note, ``stat_entry``)."""
    t = Result.__table__
    aggs = []
    for i, f in enumerate(SUMMARY_FIELDS):
        v = _value(f)
        aggs += [
            func.avg(case((func.abs(v) > BIG, 0.0), else_=v)).label(f"w_m{i}"),
            func.avg(scaled(v)).label(f"w_t{i}"),
            func.max(func.abs(v)).label(f"w_x{i}"),
        ]
    means = (
        select(*[t.c[k] for k in KEY], *aggs)
        .where(t.c.job_id == job_id)
        .group_by(*[t.c[k] for k in KEY])
        .subquery("means")
    )
    cols = []
    for i, f in enumerate(SUMMARY_FIELDS):
        big = means.c[f"w_x{i}"] > BIG
        dev = case(
            (big, scaled(_value(f)) - means.c[f"w_t{i}"]), else_=_value(f) - means.c[f"w_m{i}"]
        )
        cols += [
            func.count(t.c[f]).label(f"w_n{i}"),
            func.max(means.c[f"w_m{i}"]).label(f"w_a{i}"),
            func.max(means.c[f"w_t{i}"]).label(f"w_b{i}"),
            func.max(means.c[f"w_x{i}"]).label(f"w_x{i}"),
            func.sum(square(dev)).label(f"w_q{i}"),
        ]
    q = (
        select(*[t.c[g] for g in GROUP_FIELDS], func.count().label("w_c"), *cols)
        .join(means, and_(*[t.c[k] == means.c[k] for k in KEY]))
        .where(t.c.job_id == job_id)
        .group_by(*[t.c[k] for k in KEY], t.c.gamma)
        .order_by(*[t.c[k] for k in KEY])
        .limit(limit)
        .offset(offset)
    )
    out = []
    for row in session.execute(q):
        r = row._mapping
        stats = {}
        for i, f in enumerate(SUMMARY_FIELDS):
            n = int(r[f"w_n{i}"])
            if n == 0:
                stats[f] = {"mean": None, "std": None, "count": 0}
                continue
            scale = 1.0 / TINY if float(r[f"w_x{i}"]) > BIG else 1.0
            mean = float(r[f"w_b{i}"] if scale != 1.0 else r[f"w_a{i}"]) * scale
            std = math.sqrt(max(float(r[f"w_q{i}"]), 0.0) / n) * scale
            stats[f] = stat_entry(mean, std, n)
        out.append({**{g: r[g] for g in GROUP_FIELDS}, "count": int(r["w_c"]), "stats": stats})
    return out
