"""The outbox: work units that need (re)publishing to the broker, and marking them sent.

The API publishes a job's units after committing it; when that fails (broker
down) or a unit's worker died, the one relay, ``worker.tick.relay`` (run by
beat every tick), publishes what :func:`units_to_publish` returns and calls
:func:`mark_published`. Neither function commits.
"""

from __future__ import annotations

from collections.abc import Sequence
from datetime import datetime, timedelta

from sqlalchemy import and_, or_, select, update
from sqlalchemy.orm import Session

from service.config import get_settings

from .clock import db_now
from .models import JOB_ACTIVE, Job, WorkUnit, as_utc


def units_to_publish(
    session: Session,
    limit: int = 500,
    *,
    now: datetime | None = None,
    retry_seconds: int | None = None,
    lost_before: datetime | None = None,
) -> list[int]:
    """Units of active jobs that need (re)publishing: pending and never published, or
    published more than ``retry_seconds`` (SVROBS_PUBLISH_RETRY_SECONDS) ago without
    starting, or published before ``lost_before`` (when the broker's current data
    began: a Redis restarted without persistence has lost those messages; see
    :func:`service.broker.broker_epoch`), or running with an expired lease (the
    worker died). ``now``: default the database's clock (leases are the DB's too)."""
    now = as_utc(now or db_now(session))
    retry = get_settings().PUBLISH_RETRY_SECONDS if retry_seconds is None else retry_seconds
    stale = now - timedelta(seconds=retry)
    if lost_before is not None:
        stale = max(stale, min(as_utc(lost_before), now))
    q = (
        select(WorkUnit.id)
        .join(Job, Job.id == WorkUnit.job_id)
        .where(
            Job.status.in_(JOB_ACTIVE),
            or_(
                and_(
                    WorkUnit.status == "pending",
                    or_(WorkUnit.published_at.is_(None), WorkUnit.published_at < stale),
                ),
                and_(WorkUnit.status == "running", WorkUnit.lease_expires_at < now),
            ),
        )
        .order_by(WorkUnit.id)
        .limit(limit)
    )
    return list(session.scalars(q))


def mark_published(
    session: Session, unit_ids: Sequence[int], *, now: datetime | None = None
) -> None:
    """Record that the units were sent to the broker (running units whose lease
    expired go back to pending); ``now`` defaults to the database's clock."""
    if not unit_ids:
        return
    now = as_utc(now or db_now(session))
    ids = list(unit_ids)
    for i in range(0, len(ids), 1000):
        chunk = ids[i : i + 1000]
        session.execute(
            update(WorkUnit)
            .where(
                WorkUnit.id.in_(chunk),
                WorkUnit.status == "running",
                WorkUnit.lease_expires_at < now,
            )
            .values(status="pending", lease_expires_at=None)
        )
        session.execute(
            update(WorkUnit)
            .where(WorkUnit.id.in_(chunk), WorkUnit.status == "pending")
            .values(published_at=now)
        )
