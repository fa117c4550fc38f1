"""Retention: a team may have the cell rows of its scheduled jobs
dropped K days after they finished, keeping the job, its summaries and its stored
report. Off by default (``teams.retention_days`` NULL).

Only succeeded jobs of schedules are pruned (their summaries are complete); a
pruned job records when (``jobs.pruned_at``). Times are the database's
(:func:`db_now`), so that hosts with skewed clocks agree on what is due.
"""

from __future__ import annotations

from datetime import datetime, timedelta
from typing import Any, cast

from sqlalchemy import CursorResult, delete, select
from sqlalchemy.orm import Session

from svrobs_lab.errors import AdminError

from .accounts import get_team
from .clock import db_now
from .models import Job, Result, ResultConstant, Team, as_utc
from .result_blocks import drop_blocks

MAX_RETENTION_DAYS = 36_500


def set_retention(session: Session, team: int | str, days: int | None) -> Team:
    """Set (``days``) or switch off (None) a team's retention of scheduled jobs' rows."""
    if days is not None and not (1 <= days <= MAX_RETENTION_DAYS):
        raise AdminError(f"--days must be between 1 and {MAX_RETENTION_DAYS}, not {days}")
    t = get_team(session, team)
    t.retention_days = days
    session.flush()
    return t


def due_for_pruning(session: Session, limit: int, now: datetime | None = None) -> list[int]:
    """Ids of succeeded scheduled jobs whose team's retention period has passed."""
    now = now or db_now(session)
    rows = session.execute(
        select(Job.id, Job.finished_at, Team.retention_days)
        .join(Team, Team.id == Job.team_id)
        .where(
            Team.retention_days.is_not(None),
            Job.schedule_id.is_not(None),
            Job.status == "succeeded",
            Job.pruned_at.is_(None),
            Job.finished_at.is_not(None),
        )
        .order_by(Job.finished_at)
    ).all()
    due = [
        j
        for j, finished, days in rows
        if days is not None and as_utc(finished) + timedelta(days=days) <= now  # not None: SQL
    ]
    return due[:limit]


def prune_job(session: Session, job_id: int, now: datetime | None = None) -> int:
    """Drop a job's cell rows and record it (summaries stay); returns the rows dropped."""
    job = session.scalar(select(Job).where(Job.id == job_id).with_for_update())
    if job is None or job.pruned_at is not None:
        return 0
    res = session.execute(delete(Result).where(Result.job_id == job_id))
    n = cast("CursorResult[Any]", res).rowcount or 0  # a DELETE's result
    session.execute(delete(ResultConstant).where(ResultConstant.job_id == job_id))
    drop_blocks(session, job_id)
    job.pruned_at = now or db_now(session)
    session.flush()
    return n
