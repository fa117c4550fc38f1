"""Schedules: a cron expression in a time zone, a spec template, tags, a seed policy;
create, read, update, delete, run now, their runs, and the tick's due jobs.

Validation is the same for REST and the web's forms: the cron expression (and how
often it fires: SVROBS_MIN_SCHEDULE_INTERVAL_SECONDS), the time zone, the template
(a valid spec within the job limits, naming ``spec_template.<field>``), the team's
SVROBS_MAX_SCHEDULES_PER_TEAM. A name the team already uses is a Conflict.
"""

from __future__ import annotations

import logging
from datetime import UTC, datetime
from zoneinfo import ZoneInfo

from croniter import CroniterBadCronError, croniter
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session

from service.config import Settings
from service.db import schedules as store
from service.db.datasets import spec_data
from service.db.models import Job, Schedule, utcnow
from service.db.quota import lock_team_quota
from svrobs_core.errors import SpecError
from svrobs_core.parsing import parse_spec

from .auth import Caller
from .errors import Conflict, Invalid, NotFound
from .jobs import JobRequest, Submission, admit_spec, limits

log = logging.getLogger(__name__)
FIELDS = ("name", "cron", "timezone", "spec_template", "tags", "enabled", "seed_policy")


def validate_template(spec: dict, settings: Settings, session: Session, team_id: int) -> dict:
    """``spec`` if it is a valid spec within the job limits, on one of the team's
    datasets if it names one (checked against its shape), else a SpecError naming
    ``spec_template.<field>`` (anything else is a bug, not a 422).

    The session's transaction is ended first (what the caller read is not kept): a
    simulated spec is parsed and admitted with no transaction open, which takes
    tenths of a second for a spec of thousands of systems, and a writing session on
    SQLite holds the database's one write lock from its first read (a dataset spec reads its
    dataset's shape, then is admitted in a few milliseconds)."""
    session.rollback()
    try:
        parsed = parse_spec(spec)
        _, data = spec_data(session, team_id, parsed)
    except SpecError as exc:
        raise SpecError(f"spec_template.{exc.field}", exc.message) from None
    admit_spec(parsed, settings, field="spec_template", data=data)
    return spec


SEED_POLICIES = store.SEED_POLICIES


def _checked_cron(cron: str, timezone: str, settings: Settings) -> str:
    return store.check_interval(
        store.validate_cron(cron), timezone, settings.MIN_SCHEDULE_INTERVAL_SECONDS
    )


def timing_errors(cron: str, timezone: str, settings: Settings) -> dict[str, str]:
    """The errors of a schedule's cron and time zone, each checked on its own (a form
    shows them all at once; :func:`create` and :func:`update` stop at the first):
    ``{field: message}``, empty when both are valid."""
    errors: dict[str, str] = {}
    for field, check in (("cron", store.validate_cron), ("timezone", store.validate_timezone)):
        try:
            check(cron if field == "cron" else timezone)
        except SpecError as exc:
            errors[field] = exc.message
    if not errors:
        try:
            _checked_cron(cron, timezone, settings)
        except SpecError as exc:
            errors["cron"] = exc.message
    return errors


def next_run(cron: str, tz: str) -> datetime | None:
    """The next due time (UTC), or None for a cron or zone that no longer parses."""
    try:
        zone = ZoneInfo(tz)
        nxt = croniter(cron, datetime.now(UTC).astimezone(zone)).get_next(datetime)
    except (CroniterBadCronError, ValueError, KeyError) as exc:
        log.warning("schedule cron %r in %r has no next run: %s", cron, tz, exc)
        return None
    return (nxt if nxt.tzinfo else nxt.replace(tzinfo=zone)).astimezone(UTC)


def schedule_out(s: Schedule) -> dict:
    return {
        "id": s.id,
        "name": s.name,
        "cron": s.cron,
        "timezone": s.timezone,
        "spec_template": s.spec_template,
        "tags": list(s.tags or []),
        "enabled": s.enabled,
        "seed_policy": s.seed_policy,
        "next_run_at": next_run(s.cron, s.timezone) if s.enabled else None,
        "created_at": s.created_at,
        "updated_at": s.updated_at,
    }


def team_schedule(
    session: Session, caller: Caller, schedule_id: int, *, lock: bool = False
) -> Schedule:
    """The caller's schedule (``lock``: locked until the commit), or NotFound."""
    s = store.team_schedule(session, caller.team_id, schedule_id, lock=lock)
    if s is None:
        raise NotFound(f"schedule {schedule_id} not found")
    return s


def _commit_or_conflict(session: Session, name: str) -> None:
    try:
        session.commit()
    except IntegrityError:
        session.rollback()
        raise Conflict(f"the team already has a schedule named {name!r}", field="name") from None


def create(session: Session, caller: Caller, settings: Settings, data: dict) -> dict:
    """Create a schedule from ``data`` (a validated ``ScheduleCreate`` as a dict). It is
    checked first, then the team's schedules are counted under its quota lock, held
    until the commit (not while the template is admitted: :func:`validate_template`)."""
    timezone = store.validate_timezone(data["timezone"])
    cron = _checked_cron(data["cron"], timezone, settings)
    template = validate_template(data["spec_template"], settings, session, caller.team_id)
    lock_team_quota(session, caller.team_id)
    count = store.count_schedules(session, caller.team_id)
    if count >= settings.MAX_SCHEDULES_PER_TEAM:
        raise Invalid(
            f"the team has {count} schedules; the limit is {settings.MAX_SCHEDULES_PER_TEAM} "
            "(SVROBS_MAX_SCHEDULES_PER_TEAM)",
            field="schedules",
        )
    now = utcnow()
    s = Schedule(
        team_id=caller.team_id,
        user_id=caller.user_id,
        name=data["name"],
        cron=cron,
        timezone=timezone,
        spec_template=template,
        tags=list(dict.fromkeys(data["tags"])),
        enabled=data["enabled"],
        seed_policy=data["seed_policy"],
        created_at=now,
        updated_at=now,
    )
    session.add(s)
    _commit_or_conflict(session, s.name)
    return schedule_out(s)


def list_schedules(session: Session, caller: Caller) -> list[dict]:
    return [schedule_out(s) for s in store.team_schedules(session, caller.team_id)]


def get(session: Session, caller: Caller, schedule_id: int) -> dict:
    return schedule_out(team_schedule(session, caller, schedule_id))


def update(
    session: Session, caller: Caller, settings: Settings, schedule_id: int, data: dict
) -> dict:
    """Change the fields given in ``data`` (a ``ScheduleUpdate``, unset fields left out);
    a new template is admitted with no transaction open (:func:`validate_template`),
    then the schedule read again and locked (NotFound if it was deleted meanwhile)."""
    s = team_schedule(session, caller, schedule_id)
    for key in FIELDS:
        if key != "tags" and key in data and data[key] is None:
            raise SpecError(key, "must not be null")
    if "timezone" in data:
        data["timezone"] = store.validate_timezone(data["timezone"])
    if "cron" in data or "timezone" in data:
        data["cron"] = _checked_cron(
            data.get("cron", s.cron), data.get("timezone", s.timezone), settings
        )
    if "spec_template" in data:
        validate_template(data["spec_template"], settings, session, caller.team_id)
    # locked to the commit: a delete that came first is a NotFound, one that comes
    # later waits (not an update of a row that is gone)
    s = team_schedule(session, caller, schedule_id, lock=True)
    if "tags" in data:
        data["tags"] = list(dict.fromkeys(data["tags"] or []))
    for key, value in data.items():
        setattr(s, key, value)
    s.updated_at = utcnow()
    _commit_or_conflict(session, s.name)
    return schedule_out(s)


def run_now(submission: Submission, schedule_id: int) -> dict:
    """A job of the schedule's template now, as a due run makes one (its seed policy at
    this time, its name and tags, linked to the schedule) but outside the due times:
    no run is recorded and the next due run is unchanged. The schedule's read ends
    before the job is made, so that its spec is admitted with no transaction open (as
    :func:`validate_template` does). -> the job's body."""
    s = team_schedule(submission.session, submission.caller, schedule_id)
    now = utcnow().replace(microsecond=0)
    job = JobRequest(
        spec=store.run_spec(s.spec_template, s.seed_policy, now),
        name=store.run_job_name(s.name, now, " (run now)"),
        tags=list(s.tags or []) + [store.schedule_tag(s.name)],
        schedule_id=s.id,
    )
    submission.session.rollback()
    (out,) = submission.submit([job])
    return out


def delete(session: Session, caller: Caller, schedule_id: int) -> None:
    """Delete a schedule (its jobs stay); a concurrent delete's loser is a NotFound."""
    session.delete(team_schedule(session, caller, schedule_id, lock=True))
    session.commit()


def runs(session: Session, caller: Caller, schedule_id: int) -> list[dict]:
    """The due times taken, newest first (last 100): the job made, or why none was."""
    team_schedule(session, caller, schedule_id)
    return [
        {
            "id": r.id,
            "due_at": r.due_at,
            "job_id": r.job_id,
            "error": r.error,
            "skipped_reason": r.skipped_reason,
            "created_at": r.created_at,
        }
        for r in store.schedule_runs(session, schedule_id)
    ]


def create_due_jobs(settings: Settings, session: Session, now: datetime) -> list[Job]:
    """One job per due schedule (:func:`service.db.schedules.create_due_schedule_jobs`)
    under the job limits, the minimum interval and the git commit of ``settings``. Not
    committed."""
    return store.create_due_schedule_jobs(
        session,
        now,
        limits=limits(settings),
        min_interval_seconds=settings.MIN_SCHEDULE_INTERVAL_SECONDS,
        git_commit=settings.GIT_COMMIT,
    )
