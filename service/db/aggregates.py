"""A running job's summary aggregated inside the database (bounded reads).

What :func:`svrobs_core.records.summarize_columns` computes from the rows (count,
mean and std with ddof 0 of every summary field per (system, sigma_w, N,
estimator, gamma)), as two SQL passes over the job's rows: the group means,
then the squared deviations from them (as numpy does), so that the API never
reads the rows themselves. Finished jobs have their summaries stored.
"""

from __future__ import annotations

import math

from sqlalchemy import Float, Integer, and_, cast, func, select
from sqlalchemy.orm import Session

from svrobs_core.records import BOOL_FIELDS, GROUP_FIELDS, SUMMARY_FIELDS

from .models import Result

# the group's key columns; gamma_key (never null) joins the two passes
KEY = ("system", "sigma_w", "N", "estimator", "gamma_key")


def _value(f: str):
    col = Result.__table__.c[f]
    return cast(cast(col, Integer) if f in BOOL_FIELDS else col, Float)


def summarize_in_db(session: Session, job_id: int) -> list[dict]:
    """The job's groups as ``summarize_columns`` gives them, ordered by group."""
    t = Result.__table__
    means = (
        select(
            *[t.c[k] for k in KEY],
            *[func.avg(_value(f)).label(f"w_m{i}") for i, f in enumerate(SUMMARY_FIELDS)],
        )
        .where(t.c.job_id == job_id)
        .group_by(*[t.c[k] for k in KEY])
        .subquery("means")
    )
    cols = []
    for i, f in enumerate(SUMMARY_FIELDS):
        dev = _value(f) - means.c[f"w_m{i}"]
        cols += [
            func.count(t.c[f]).label(f"w_n{i}"),
            func.max(means.c[f"w_m{i}"]).label(f"w_a{i}"),
            func.sum(dev * dev).label(f"w_q{i}"),
        ]
    q = (
        select(*[t.c[g] for g in GROUP_FIELDS], func.count().label("w_c"), *cols)
        .join(means, and_(*[t.c[k] == means.c[k] for k in KEY]))
        .where(t.c.job_id == job_id)
        .group_by(*[t.c[k] for k in KEY], t.c.gamma)
        .order_by(*[t.c[k] for k in KEY])
    )
    out = []
    for row in session.execute(q):
        r = row._mapping
        stats = {}
        for i, f in enumerate(SUMMARY_FIELDS):
            n = int(r[f"w_n{i}"])
            if n == 0:
                stats[f] = {"mean": None, "std": None, "count": 0}
            else:
                std = math.sqrt(max(float(r[f"w_q{i}"]), 0.0) / n)
                stats[f] = {"mean": float(r[f"w_a{i}"]), "std": std, "count": n}
        out.append({**{g: r[g] for g in GROUP_FIELDS}, "count": int(r["w_c"]), "stats": stats})
    return out
