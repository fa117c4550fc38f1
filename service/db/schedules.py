"""Schedules: validating a cron expression (and how often it fires) and a time zone,
the latest due time, and turning due schedules into jobs (once per due time, however
many ticks run; within the team's cap).

A cron is read in its time zone's wall-clock time, and its due times are the instants
at which those wall times occur (docs/client.md#daylight-saving-time): a wall time
skipped by a change to summer time is due when the gap ends (one hour later, at the
usual one-hour change); a wall time that occurs twice when the clocks go back is due
at both instants if the cron's hour field is ``*`` (an hourly or more frequent
schedule keeps its rhythm), else at the first only (a daily run stays one run).
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from datetime import UTC, datetime, timedelta
from typing import TYPE_CHECKING, Any
from zoneinfo import ZoneInfo

from croniter import croniter
from sqlalchemy import func, select
from sqlalchemy.exc import DataError, IntegrityError
from sqlalchemy.orm import Session

from svrobs_core.errors import SpecError
from svrobs_lab.errors import IdempotencyConflict, QuotaExceeded

from .jobs import create_job
from .models import TAG_MAX, Job, Schedule, ScheduleRun, as_utc, utcnow

if TYPE_CHECKING:
    from sqlalchemy.dialects import postgresql, sqlite

log = logging.getLogger(__name__)

SEED_POLICIES = ("fixed", "due-time")
SEED_MODULUS = 2**31  # a derived seed stays a 32-bit integer


def _width(column: Any) -> int:
    """A text column's width in characters (its model declares it)."""
    length = getattr(column.type, "length", None)
    assert isinstance(length, int), column
    return length


def _fitted(name: str, prefix: str, suffix: str, width: int) -> str:
    """prefix + name + suffix in ``width`` characters: the name cut, ending in "…"."""
    room = width - len(prefix) - len(suffix)
    return prefix + (name if len(name) <= room else name[: room - 1] + "…") + suffix


def run_job_name(name: str, due: datetime, suffix: str = "") -> str:
    """The name of a schedule's job due at ``due``: "<schedule> @ <due><suffix>", the
    schedule's name cut to fit the job's name column."""
    stamp = due.strftime("%Y-%m-%dT%H:%M:%SZ")
    return _fitted(name, "", f" @ {stamp}{suffix}", _width(Job.__table__.c.name))


def schedule_tag(name: str) -> str:
    """The tag every job of the schedule ``name`` carries, cut to the length a tag
    may have (TAG_MAX: a client can filter by it)."""
    return _fitted(name, "schedule:", "", TAG_MAX)


def run_spec(template: dict, policy: str, due: datetime) -> dict:
    """The spec of the run due at ``due``. ``fixed``: the template as is (every run
    repeats the same experiment). ``due-time``: its seed replaced by (template seed +
    the due time in Unix seconds) mod 2^31, so each due time draws fresh repetitions
    and the same due time always the same ones."""
    if policy != "due-time":
        return template
    base = int(template.get("seed", 0) or 0)
    return {**template, "seed": (base + int(as_utc(due).timestamp())) % SEED_MODULUS}


CRON_ALIASES = ("@yearly", "@annually", "@monthly", "@weekly", "@daily", "@midnight", "@hourly")


def validate_cron(expr: str) -> str:
    """The normalised cron expression (5 fields or an @alias); SpecError('cron') if bad."""
    expr = " ".join(expr.split())
    if expr.startswith("@"):
        if expr.lower() not in CRON_ALIASES:
            raise SpecError("cron", f"unknown alias {expr!r}; known: {list(CRON_ALIASES)}")
        return expr.lower()
    if len(expr.split(" ")) != 5:
        raise SpecError("cron", "must have 5 fields: minute hour day-of-month month day-of-week")
    try:
        ok = croniter.is_valid(expr)
        if ok:
            croniter(expr, datetime.now(UTC)).get_next(datetime)
    except Exception:  # noqa: BLE001 - croniter raises several types
        ok = False
    if not ok:
        raise SpecError("cron", f"invalid cron expression {expr!r}")
    return expr


# a change of a zone's UTC offset is at most this (a day's changes of a few zones
# included): wall times further apart than this are in the same order as their instants
_OFFSET_CHANGE = timedelta(hours=3)


def _wall(moment: datetime, zone: ZoneInfo) -> datetime:
    """``moment``'s wall-clock time in ``zone``, naive."""
    return as_utc(moment).astimezone(zone).replace(tzinfo=None)


def _instants(wall: datetime, zone: ZoneInfo, both: bool) -> list[datetime]:
    """The UTC instants (ascending) at which the naive wall time ``wall`` of ``zone`` is
    due: the one instant it occurs; in a gap, the instant as far after the gap's start
    as ``wall`` is; when it occurs twice, both with ``both``, else the first."""
    first = wall.replace(tzinfo=zone, fold=0).astimezone(UTC)
    second = wall.replace(tzinfo=zone, fold=1).astimezone(UTC)
    if first == second:
        return [first]
    occurs = [u for u in (first, second) if _wall(u, zone) == wall]
    if not occurs:  # skipped by the change: fold=0 reads it with the offset before
        return [first]
    return sorted(occurs) if both else [min(occurs)]


def _hour_wildcard(cron: str) -> bool:
    return croniter(cron).expanded[1] == ["*"]


def shortest_interval(cron: str, tz: str = "UTC", *, start: datetime | None = None) -> float:
    """The shortest time (seconds) between two consecutive runs of ``cron`` in ``tz``,
    over its next :data:`INTERVAL_SAMPLES` due times from ``start`` (default now). A
    cron that fires more than that many times a day fires less than 86400/500 s apart,
    so the sample always holds at least one whole day's firings when it matters."""
    zone, both = ZoneInfo(tz), _hour_wildcard(cron)
    it = croniter(cron, _wall(start or utcnow(), zone))
    due = sorted(
        {
            u
            for _ in range(INTERVAL_SAMPLES + 1)
            for u in _instants(it.get_next(datetime), zone, both)
        }
    )
    gaps = [(b - a).total_seconds() for a, b in zip(due, due[1:])]
    return min(gaps, default=float("inf"))


INTERVAL_SAMPLES = 500


def check_interval(cron: str, tz: str, min_seconds: float) -> str:
    """``cron`` if its runs are at least ``min_seconds`` apart (SVROBS_MIN_SCHEDULE_INTERVAL_SECONDS);
    SpecError('cron') naming the shortest interval and the limit otherwise."""
    if min_seconds > 0:
        gap = shortest_interval(cron, tz)
        if gap < min_seconds:
            raise SpecError(
                "cron",
                f"runs {gap:.0f} s apart; schedules must run at least {min_seconds:.0f} s "
                "apart (SVROBS_MIN_SCHEDULE_INTERVAL_SECONDS)",
            )
    return cron


def validate_timezone(tz: str) -> str:
    """``tz`` if it is an IANA time zone; SpecError('timezone') if not."""
    try:
        ZoneInfo(tz)
    except Exception:  # noqa: BLE001 - ZoneInfoNotFoundError, ValueError for odd paths
        raise SpecError(
            "timezone",
            f"unknown time zone {tz!r} (use an IANA name such as 'Europe/Paris' or 'UTC')",
        ) from None
    return tz


def latest_due(cron: str, tz: str, now: datetime) -> datetime:
    """The latest due time <= ``now`` of ``cron`` in time zone ``tz`` (as UTC, whole
    seconds): the wall times matched are walked back from ``now``'s wall time plus the
    largest offset change, until they are that much before the latest found."""
    zone, both, now = ZoneInfo(tz), _hour_wildcard(cron), as_utc(now)
    # croniter's get_prev excludes an exact match, so start just after
    it = croniter(cron, _wall(now, zone) + _OFFSET_CHANGE + timedelta(seconds=1))
    best: datetime | None = None
    while True:
        wall = it.get_prev(datetime)
        if best is not None and wall < _wall(best, zone) - _OFFSET_CHANGE:
            return best.replace(microsecond=0)
        for u in _instants(wall, zone, both):
            if u <= now and (best is None or u > best):
                best = u


def create_due_schedule_jobs(
    session: Session,
    now: datetime,
    *,
    limits: dict | None = None,
    min_interval_seconds: float = 0,
    git_commit: str | None = None,
) -> list[Job]:
    """Create one job per enabled schedule whose latest due time (<= now, not before
    the schedule was created) has no run yet. A ScheduleRun row is inserted on the
    unique (schedule, due_at) first and the job is made only by the inserter, so a
    doubled or restarted tick never runs one sweep twice. The team's cap on active
    jobs and every job limit (``limits``: the keyword limits of
    :func:`~service.db.jobs.create_job`) apply as for ``POST /jobs``; a due time that
    makes no job says why on its run (``skipped_reason`` for the cap or a run less
    than ``min_interval_seconds`` (SVROBS_MIN_SCHEDULE_INTERVAL_SECONDS) after the
    previous job, ``error`` for a spec over a limit). ``git_commit``: as for
    :func:`~service.db.jobs.create_job`. Not committed."""
    now = as_utc(now)
    dialect = session.get_bind().dialect.name
    dialect_insert: Callable[[type[ScheduleRun]], postgresql.Insert | sqlite.Insert]
    if dialect == "postgresql":
        from sqlalchemy.dialects.postgresql import insert as dialect_insert
    else:
        from sqlalchemy.dialects.sqlite import insert as dialect_insert

    min_gap = timedelta(seconds=min_interval_seconds)
    jobs: list[Job] = []
    schedules = session.scalars(
        select(Schedule).where(Schedule.enabled.is_(True)).order_by(Schedule.id)
    ).all()
    for sched in schedules:
        try:
            due = latest_due(sched.cron, sched.timezone, now)
        except Exception:  # noqa: BLE001 - an invalid cron or zone in the DB must not stop the others
            continue
        created_at = sched.created_at.replace(microsecond=0) if sched.created_at else None
        if created_at is not None and due < created_at:
            continue
        try:  # one schedule's failure (deleted meanwhile) must not undo the others' runs
            with session.begin_nested():
                job = _due_run(session, sched, due, dialect_insert, min_gap, limits, git_commit)
        except IntegrityError as exc:
            log.warning("schedule %s: no run at %s: %s", sched.id, due, exc.orig)
            continue
        if job is not None:
            jobs.append(job)
    session.flush()
    return jobs


def _due_run(
    session: Session,
    sched: Schedule,
    due: datetime,
    dialect_insert: Callable[[type[ScheduleRun]], postgresql.Insert | sqlite.Insert],
    min_gap: timedelta,
    limits: dict | None,
    git_commit: str | None,
) -> Job | None:
    """The run of ``sched`` due at ``due``, and its job if this call made one."""
    previous = session.scalar(
        select(func.max(ScheduleRun.due_at)).where(
            ScheduleRun.schedule_id == sched.id,
            ScheduleRun.due_at < due,
            ScheduleRun.job_id.is_not(None),
        )
    )
    run_id = session.execute(
        dialect_insert(ScheduleRun)
        .values(schedule_id=sched.id, due_at=due, created_at=utcnow())
        .on_conflict_do_nothing(index_elements=["schedule_id", "due_at"])
        .returning(ScheduleRun.id)
    ).scalar()
    if run_id is None:
        return None  # another tick already took this due time
    run = session.get(ScheduleRun, run_id)
    assert run is not None  # inserted just above
    if previous is not None and due - as_utc(previous) < min_gap:
        run.skipped_reason = (
            f"{(due - as_utc(previous)).total_seconds():.0f} s after the previous run; "
            f"the minimum is {min_gap.total_seconds():.0f} s "
            "(SVROBS_MIN_SCHEDULE_INTERVAL_SECONDS)"
        )
        return None
    stamp = due.strftime("%Y-%m-%dT%H:%M:%SZ")
    try:
        with session.begin_nested():
            job, created = create_job(
                session,
                team_id=sched.team_id,
                user_id=sched.user_id,
                spec=run_spec(sched.spec_template, sched.seed_policy, due),
                name=run_job_name(sched.name, due),
                tags=list(sched.tags or []) + [schedule_tag(sched.name)],
                idempotency_key=f"schedule:{sched.id}:{stamp}",
                schedule_id=sched.id,
                git_commit=git_commit,
                **(limits or {}),
            )
    except QuotaExceeded as exc:
        run.skipped_reason = str(exc)
        return None
    except (SpecError, IdempotencyConflict) as exc:
        run.error = str(exc)
        return None
    except DataError as exc:  # a value the database refuses: this run's error, not the tick's
        run.error = f"the job could not be stored: {str(exc.orig).splitlines()[0]}"
        return None
    run.job_id = job.id
    return job if created else None


def team_schedule(
    session: Session, team_id: int, schedule_id: int, *, lock: bool = False
) -> Schedule | None:
    """One of the team's schedules, or None (another team's is indistinguishable).
    ``lock``: its row locked until the commit and read afresh (None if a delete won)."""
    query = select(Schedule).where(Schedule.id == schedule_id, Schedule.team_id == team_id)
    if lock:
        query = query.with_for_update().execution_options(populate_existing=True)
    return session.scalar(query)


def count_schedules(session: Session, team_id: int) -> int:
    return int(
        session.scalar(select(func.count(Schedule.id)).where(Schedule.team_id == team_id)) or 0
    )


def team_schedules(session: Session, team_id: int) -> list[Schedule]:
    return list(
        session.scalars(select(Schedule).where(Schedule.team_id == team_id).order_by(Schedule.id))
    )


def schedule_runs(session: Session, schedule_id: int, limit: int = 100) -> list[ScheduleRun]:
    """The schedule's due times taken, newest first."""
    return list(
        session.scalars(
            select(ScheduleRun)
            .where(ScheduleRun.schedule_id == schedule_id)
            .order_by(ScheduleRun.due_at.desc())
            .limit(limit)
        )
    )
