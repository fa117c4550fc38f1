"""Schedules: validating a cron expression and time zone, the latest due time, and
turning due schedules into jobs (once per due time, however many ticks run).
"""

from __future__ import annotations

from datetime import UTC, datetime, timedelta
from zoneinfo import ZoneInfo

from croniter import croniter
from sqlalchemy import select
from sqlalchemy.orm import Session

from svrobs_core.errors import SpecError

from .errors import IdempotencyConflict
from .jobs import create_job
from .models import Job, Schedule, ScheduleRun, as_utc, utcnow

SEED_POLICIES = ("fixed", "due-time")
SEED_MODULUS = 2**31  # a derived seed stays a 32-bit integer


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
    """The latest time <= ``now`` matched by ``cron`` in time zone ``tz`` (as UTC)."""
    zone = ZoneInfo(tz)
    local = as_utc(now).astimezone(zone)
    # croniter's get_prev excludes an exact match, so start just after `now`
    it = croniter(cron, local + timedelta(seconds=1))
    due = it.get_prev(datetime)
    if due.tzinfo is None:
        due = due.replace(tzinfo=zone)
    return due.astimezone(UTC).replace(microsecond=0)


def create_due_schedule_jobs(session: Session, now: datetime) -> list[Job]:
    """Create one job per enabled schedule whose latest due time (<= now, not before
    the schedule was created) has no run yet. A ScheduleRun row is inserted on the
    unique (schedule, due_at) first and the job is made only by the inserter, so a
    doubled or restarted tick never runs one sweep twice. Not committed."""
    now = as_utc(now)
    dialect = session.get_bind().dialect.name
    if dialect == "postgresql":
        from sqlalchemy.dialects.postgresql import insert as dialect_insert
    else:
        from sqlalchemy.dialects.sqlite import insert as dialect_insert

    jobs: list[Job] = []
    schedules = session.scalars(
        select(Schedule).where(Schedule.enabled.is_(True)).order_by(Schedule.id)
    ).all()
    for sched in schedules:
        try:
            due = latest_due(sched.cron, sched.timezone, now)
        except Exception:  # an invalid cron in the DB must not stop the others
            continue
        created = sched.created_at.replace(microsecond=0) if sched.created_at else None
        if created is not None and due < created:
            continue
        run_id = session.execute(
            dialect_insert(ScheduleRun)
            .values(schedule_id=sched.id, due_at=due, created_at=utcnow())
            .on_conflict_do_nothing(index_elements=["schedule_id", "due_at"])
            .returning(ScheduleRun.id)
        ).scalar()
        if run_id is None:
            continue  # another tick already took this due time
        run = session.get(ScheduleRun, run_id)
        stamp = due.strftime("%Y-%m-%dT%H:%M:%SZ")
        try:
            with session.begin_nested():
                job, created = create_job(
                    session,
                    team_id=sched.team_id,
                    user_id=sched.user_id,
                    spec=run_spec(sched.spec_template, sched.seed_policy, due),
                    name=f"{sched.name} @ {stamp}",
                    tags=list(sched.tags or []) + [f"schedule:{sched.name}"],
                    idempotency_key=f"schedule:{sched.id}:{stamp}",
                    max_active_jobs=0,
                    schedule_id=sched.id,
                )
        except (SpecError, IdempotencyConflict) as exc:
            run.error = str(exc)
            continue
        run.job_id = job.id
        if created:
            jobs.append(job)
    session.flush()
    return jobs
