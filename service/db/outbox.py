"""The outbox: work units that need (re)publishing to the broker, marking them sent,
and the fair share between teams.

Fair share (``Settings.fair_share``): at most K units of a team are *in flight*
(published and not finished) at once, and at most K' while another team has units
queued or running. By default K is the pool's size (SVROBS_WORKER_POOL_PROCESSES) and
K' one less, so that one team never holds every pool process while another waits, and
no unit of a team is queued in the broker ahead of another team's: a small job's
first unit finds a free process, or waits at most for one running unit.
:func:`dispatch` publishes a team's next units (oldest job first) as its units
finish, round-robin over teams.
It is called after a submission commits (the API), when a unit finishes (the worker,
for its team) and by beat's tick (``worker.tick.relay``, every team, also
re-publishing lost units). It reserves the units (marks them published) in one
transaction that locks the teams' rows, so that concurrent dispatchers never exceed K
nor send a unit twice, publishes, and un-marks what the broker did not take.

:func:`units_to_publish` and :func:`mark_published` take an open session and never
commit.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from contextlib import AbstractContextManager
from datetime import datetime, timedelta
from itertools import chain, zip_longest
from typing import Any, cast

from sqlalchemy import CursorResult, and_, func, or_, select, update
from sqlalchemy.orm import Session

from .clock import db_now
from .models import JOB_ACTIVE, Job, Team, WorkUnit, as_utc

log = logging.getLogger(__name__)

Publish = Callable[[Sequence[int]], Sequence[int]]  # unit ids -> the ids the broker took
Begin = Callable[[], AbstractContextManager[Session]]  # a session committed on exit

_NEW = and_(WorkUnit.status == "pending", WorkUnit.published_at.is_(None))
_IN_FLIGHT = or_(
    and_(WorkUnit.status == "pending", WorkUnit.published_at.is_not(None)),
    WorkUnit.status == "running",
)


def _active_units():
    return (
        select(WorkUnit.id).join(Job, Job.id == WorkUnit.job_id).where(Job.status.in_(JOB_ACTIVE))
    )


def units_to_publish(
    session: Session,
    limit: int = 500,
    *,
    retry_seconds: int,
    now: datetime | None = None,
    lost_before: datetime | None = None,
    cap: int | None = None,
    shared_cap: int | None = None,
    team_id: int | None = None,
    republish: bool = True,
) -> list[int]:
    """Units of active jobs that need (re)publishing, in the order to publish them.

    Re-published (with ``republish``, first): published more than ``retry_seconds``
    (SVROBS_PUBLISH_RETRY_SECONDS) ago without starting, or published before
    ``lost_before`` (when the broker's current data began: a Redis restarted without
    persistence has lost those messages; see :func:`service.broker.broker_epoch`), or
    running with an expired lease (the worker died). These are in flight already.

    New (pending, never published): with ``cap`` (K), at most K minus the team's units
    in flight per team (``shared_cap`` instead, default K, while another team has units
    of active jobs pending or running), oldest job first, interleaved round-robin over
    the teams; ``cap`` None or 0: all of them. ``team_id``: that team's units only. ``now``:
    default the database's clock (leases are the DB's too).
    """
    now = as_utc(now or db_now(session))
    out: list[int] = []
    if republish:
        stale = now - timedelta(seconds=retry_seconds)
        if lost_before is not None:
            stale = max(stale, min(as_utc(lost_before), now))
        q = _active_units().where(
            or_(
                and_(WorkUnit.status == "pending", WorkUnit.published_at < stale),
                and_(WorkUnit.status == "running", WorkUnit.lease_expires_at < now),
            )
        )
        if team_id is not None:
            q = q.where(Job.team_id == team_id)
        out = list(session.scalars(q.order_by(WorkUnit.id).limit(limit)))
    if len(out) >= limit:
        return out
    new = _new_units(session, limit - len(out), cap=cap, shared_cap=shared_cap, team_id=team_id)
    return out + new


def _new_units(
    session: Session, limit: int, *, cap: int | None, shared_cap: int | None, team_id: int | None
) -> list[int]:
    q = _active_units().where(_NEW)
    if not cap:
        if team_id is not None:
            q = q.where(Job.team_id == team_id)
        return list(session.scalars(q.order_by(WorkUnit.job_id, WorkUnit.index).limit(limit)))
    teams = [team_id] if team_id is not None else waiting_teams(session)
    busy = in_flight(session, teams)
    shared = cap if shared_cap is None else shared_cap
    working = busy_teams(session) if shared != cap else set()
    per_team = []
    for t in teams:
        team_cap = shared if working - {t} else cap
        free = min(limit, team_cap - busy.get(t, 0))
        if free > 0:
            rows = q.where(Job.team_id == t).order_by(WorkUnit.job_id, WorkUnit.index).limit(free)
            per_team.append(list(session.scalars(rows)))
    rr = [u for u in chain.from_iterable(zip_longest(*per_team)) if u is not None]
    return rr[:limit]


def waiting_teams(session: Session) -> list[int]:
    """Teams with units of active jobs never published, by id."""
    q = (
        select(Job.team_id)
        .distinct()
        .join(WorkUnit, WorkUnit.job_id == Job.id)
        .where(Job.status.in_(JOB_ACTIVE), _NEW)
        .order_by(Job.team_id)
    )
    return list(session.scalars(q))


def busy_teams(session: Session) -> set[int]:
    """Teams with units of active jobs pending (published or not) or running."""
    q = (
        select(Job.team_id)
        .distinct()
        .join(WorkUnit, WorkUnit.job_id == Job.id)
        .where(Job.status.in_(JOB_ACTIVE), WorkUnit.status.in_(("pending", "running")))
    )
    return {int(t) for t in session.scalars(q)}


def in_flight(session: Session, team_ids: Sequence[int]) -> dict[int, int]:
    """team id -> its units of active jobs published and not finished (or running)."""
    if not team_ids:
        return {}
    q = (
        select(Job.team_id, func.count(WorkUnit.id))
        .join(WorkUnit, WorkUnit.job_id == Job.id)
        .where(Job.team_id.in_(list(team_ids)), Job.status.in_(JOB_ACTIVE), _IN_FLIGHT)
        .group_by(Job.team_id)
    )
    return {int(t): int(n) for t, n in session.execute(q)}


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


def end_orphans(session: Session, *, now: datetime | None = None) -> int:
    """Running units of finished jobs whose lease expired (their worker died) ->
    cancelled, so that no unit stays ``running`` forever; returns how many."""
    now = as_utc(now)
    finished = select(Job.id).where(Job.status.not_in(JOB_ACTIVE))
    res = session.execute(
        update(WorkUnit)
        .where(
            WorkUnit.status == "running",
            WorkUnit.lease_expires_at < now,
            WorkUnit.job_id.in_(finished),
        )
        .values(status="cancelled", finished_at=now, lease_expires_at=None)
        .execution_options(synchronize_session=False)
    )
    return cast("CursorResult[Any]", res).rowcount or 0  # an UPDATE's result


def unmark_published(session: Session, unit_ids: Sequence[int]) -> None:
    """The broker did not take these: pending units become never published again."""
    ids = list(unit_ids)
    for i in range(0, len(ids), 1000):
        session.execute(
            update(WorkUnit)
            .where(WorkUnit.id.in_(ids[i : i + 1000]), WorkUnit.status == "pending")
            .values(published_at=None)
        )


def _lock_teams(session: Session, team_ids: Sequence[int]) -> None:
    """Serialise dispatchers of the same teams (PostgreSQL row locks, in id order;
    SQLite writers are serialised by BEGIN IMMEDIATE already)."""
    if team_ids and session.get_bind().dialect.name == "postgresql":
        session.execute(
            select(Team.id).where(Team.id.in_(sorted(team_ids))).order_by(Team.id).with_for_update()
        ).all()


def team_of_unit(session: Session, unit_id: int) -> int | None:
    return session.scalar(
        select(Job.team_id).join(WorkUnit, WorkUnit.job_id == Job.id).where(WorkUnit.id == unit_id)
    )


def dispatch(
    begin: Begin,
    publish: Publish,
    *,
    cap: int,
    shared_cap: int | None = None,
    retry_seconds: int,
    team_id: int | None = None,
    republish: bool = False,
    lost_before: datetime | None = None,
    limit: int = 500,
) -> int:
    """Reserve the units to publish now (:func:`units_to_publish` under the team caps
    ``cap`` and ``shared_cap``, the caller's ``Settings.fair_share``, re-publishing after
    ``retry_seconds``), publish them and un-mark those the broker did not take; returns
    how many were sent. ``publish`` may raise (the broker is down): the reservation is
    undone and the error re-raised."""
    with begin() as s:
        now = db_now(s)  # leases and publication times are the database's clock
        if republish:
            end_orphans(s, now=now)
        _lock_teams(s, [team_id] if team_id is not None else waiting_teams(s))
        ids = units_to_publish(
            s,
            limit,
            now=now,
            retry_seconds=retry_seconds,
            lost_before=lost_before,
            cap=cap,
            shared_cap=shared_cap,
            team_id=team_id,
            republish=republish,
        )
        mark_published(s, ids, now=now)
    if not ids:
        return 0
    sent: Sequence[int] = []
    try:
        sent = publish(ids)
    finally:
        unsent = sorted(set(ids) - set(sent))
        if unsent:
            log.warning("outbox: the broker took %d of %d units", len(sent), len(ids))
            with begin() as s:
                unmark_published(s, unsent)
    return len(sent)
