"""The database's clock: the one clock every host of a deployment shares.

Leases, publication times and retention compare times written by different
hosts (API, workers, beat), so they use :func:`db_now`, never the local clock.
"""

from __future__ import annotations

from datetime import UTC, datetime

from sqlalchemy import func, select, text
from sqlalchemy.orm import Session

from .models import as_utc


def db_now(session: Session) -> datetime:
    """The database server's current time (UTC; on SQLite, the local file's host)."""
    if session.get_bind().dialect.name == "sqlite":
        value = session.scalar(select(func.strftime("%Y-%m-%d %H:%M:%f", "now")))
        return datetime.fromisoformat(str(value)).replace(tzinfo=UTC)
    return as_utc(session.scalar(select(func.now())))


def ping(session: Session) -> None:
    """One round trip to the database (raises when it does not answer)."""
    session.execute(text("SELECT 1"))
