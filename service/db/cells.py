"""One job's cells picked by their grid coordinates (the model export's ``cell``):
the keys that match a partial set of coordinates, then the one record."""

from __future__ import annotations

from sqlalchemy import select
from sqlalchemy.orm import Session

from .models import Result
from .results_store import gamma_key, load_records

CELL_COORDINATES = ("system", "sigma_w", "N", "estimator", "gamma", "rep")


def cell_conditions(job_id: int, coordinates: dict) -> list:
    """WHERE conditions of the cells of ``job_id`` at ``coordinates`` (a subset of
    CELL_COORDINATES; gamma None is OLS)."""
    t = Result.__table__
    conds = [t.c.job_id == job_id]
    for key, value in coordinates.items():
        if key == "gamma":
            conds.append(t.c.gamma_key == gamma_key(value))
        else:
            conds.append(t.c[key] == value)
    return conds


def matching_keys(session: Session, job_id: int, coordinates: dict, limit: int) -> list[dict]:
    """The coordinates of at most ``limit`` cells matching ``coordinates``, in grid order."""
    t = Result.__table__
    cols = [t.c[c] for c in ("system", "sigma_w", "N", "estimator", "gamma_key", "rep")]
    rows = session.execute(
        select(*cols).where(*cell_conditions(job_id, coordinates)).order_by(*cols).limit(limit)
    ).all()
    return [
        {"system": s, "sigma_w": w, "N": n, "estimator": e, "gamma": None if g < 0 else g, "rep": r}
        for s, w, n, e, g, r in rows
    ]


def cell_record(session: Session, job_id: int, coordinates: dict) -> dict | None:
    """The one record at full ``coordinates`` (every key of CELL_COORDINATES), or None."""
    found = load_records(session, job_id, *cell_conditions(job_id, coordinates)[1:])
    return found[0] if found else None
