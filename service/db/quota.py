"""The per-team quota lock: a team's count-then-insert checks (its active jobs, its
schedules, a job's live share links) run one at a time, so that concurrent requests
never exceed a cap (docs/architecture.md#one-job).

Under READ COMMITTED two transactions may both count 4 of 5 and both insert;
holding this lock from before the count until the transaction ends makes the second
count see the first's committed row.
"""

from __future__ import annotations

from sqlalchemy import text
from sqlalchemy.orm import Session

# The first key of pg_advisory_xact_lock(int, int): the quota locks' own namespace.
QUOTA_LOCK_CLASS = 0x5155


def lock_team_quota(session: Session, team_id: int) -> None:
    """Hold the team's quota lock until the session's transaction ends (commit or
    rollback). PostgreSQL: ``pg_advisory_xact_lock`` on (namespace, team id), which
    never blocks readers nor the fair-share dispatcher's row locks. SQLite: a writing
    session began with ``BEGIN IMMEDIATE`` (:mod:`service.db.session`), which already
    holds the database's one write lock; nothing more is needed."""
    if session.get_bind().dialect.name == "postgresql":
        session.execute(
            text("SELECT pg_advisory_xact_lock(:ns, :team)"),
            {"ns": QUOTA_LOCK_CLASS, "team": int(team_id)},
        )
