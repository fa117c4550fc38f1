"""Schedules CRUD: a cron expression in a time zone, a spec template, enabled.

Beat's tick (``service.db.schedules.create_due_schedule_jobs``) turns each due time into
exactly one job.
"""

from __future__ import annotations

from datetime import UTC, datetime
from typing import Annotated
from zoneinfo import ZoneInfo

from croniter import croniter
from fastapi import APIRouter, HTTPException, Path, Response
from sqlalchemy import select
from sqlalchemy.exc import IntegrityError

from service.api.deps import DB, MAX_ID, CurrentCaller, SettingsDep
from service.api.errors import FieldHTTPException, error_docs
from service.api.schemas import (
    ScheduleCreate,
    ScheduleOut,
    ScheduleRunOut,
    ScheduleUpdate,
)
from service.db.errors import JobTooLarge
from service.db.models import Schedule, ScheduleRun, utcnow
from service.db.schedules import validate_cron, validate_timezone
from svrobs_core.errors import SpecError
from svrobs_core.spec import parse_spec

router = APIRouter(tags=["schedules"])
ERRORS = error_docs(401, 404, 409, 422, 429, 503)
BODY_ERRORS = {**ERRORS, **error_docs(413)}  # routes with a body: SVROBS_MAX_BODY_BYTES
ScheduleId = Annotated[int, Path(ge=1, le=MAX_ID)]


def validate_template(spec: dict, max_cells: int) -> dict:
    try:
        parsed = parse_spec(spec)
    except SpecError as exc:
        raise SpecError(f"spec_template.{exc.field}", exc.message) from None
    except (TypeError, ValueError, KeyError, IndexError) as exc:
        raise SpecError("spec_template", f"invalid spec: {exc}") from None
    if parsed.n_cells > max_cells:
        raise JobTooLarge(
            "spec_template",
            f"the job has {parsed.n_cells} cells; the limit is {max_cells} (SVROBS_MAX_JOB_CELLS)",
        )
    return spec


def next_run(cron: str, tz: str) -> datetime | None:
    try:
        zone = ZoneInfo(tz)
        nxt = croniter(cron, datetime.now(UTC).astimezone(zone)).get_next(datetime)
        return (nxt if nxt.tzinfo else nxt.replace(tzinfo=zone)).astimezone(UTC)
    except Exception:  # noqa: BLE001
        return None


def schedule_out(s: Schedule) -> dict:
    return {
        "id": s.id,
        "name": s.name,
        "cron": s.cron,
        "timezone": s.timezone,
        "spec_template": s.spec_template,
        "tags": list(s.tags or []),
        "enabled": s.enabled,
        "next_run_at": next_run(s.cron, s.timezone) if s.enabled else None,
        "created_at": s.created_at,
        "updated_at": s.updated_at,
    }


def _team_schedule(session, team_id: int, schedule_id: int) -> Schedule:
    s = session.scalar(
        select(Schedule).where(Schedule.id == schedule_id, Schedule.team_id == team_id)
    )
    if s is None:
        raise HTTPException(404, f"schedule {schedule_id} not found")
    return s


def _commit_or_409(session, name: str) -> None:
    try:
        session.commit()
    except IntegrityError:
        session.rollback()
        raise FieldHTTPException(
            409, f"the team already has a schedule named {name!r}", "name"
        ) from None


@router.post("/schedules", status_code=201, response_model=ScheduleOut, responses=BODY_ERRORS)
def create_schedule(
    body: ScheduleCreate, session: DB, caller: CurrentCaller, settings: SettingsDep
):
    """Create a schedule; the cron expression, time zone and spec template are validated."""
    now = utcnow()
    s = Schedule(
        team_id=caller.team_id,
        user_id=caller.user_id,
        name=body.name.strip(),
        cron=validate_cron(body.cron),
        timezone=validate_timezone(body.timezone),
        spec_template=validate_template(body.spec_template, settings.MAX_JOB_CELLS),
        tags=list(dict.fromkeys(body.tags)),
        enabled=body.enabled,
        created_at=now,
        updated_at=now,
    )
    session.add(s)
    _commit_or_409(session, s.name)
    return schedule_out(s)


@router.get("/schedules", response_model=list[ScheduleOut], responses=ERRORS)
def list_schedules(session: DB, caller: CurrentCaller):
    rows = session.scalars(
        select(Schedule).where(Schedule.team_id == caller.team_id).order_by(Schedule.id)
    ).all()
    return [schedule_out(s) for s in rows]


@router.get("/schedules/{schedule_id}", response_model=ScheduleOut, responses=ERRORS)
def get_schedule(schedule_id: ScheduleId, session: DB, caller: CurrentCaller):
    return schedule_out(_team_schedule(session, caller.team_id, schedule_id))


@router.patch("/schedules/{schedule_id}", response_model=ScheduleOut, responses=BODY_ERRORS)
def update_schedule(
    schedule_id: ScheduleId,
    body: ScheduleUpdate,
    session: DB,
    caller: CurrentCaller,
    settings: SettingsDep,
):
    """Change any of name, cron, timezone, spec_template, tags, enabled."""
    s = _team_schedule(session, caller.team_id, schedule_id)
    data = body.model_dump(exclude_unset=True)
    for key in ("name", "cron", "timezone", "spec_template", "enabled"):
        if key in data and data[key] is None:
            raise SpecError(key, "must not be null")
    if "cron" in data:
        data["cron"] = validate_cron(data["cron"])
    if "timezone" in data:
        data["timezone"] = validate_timezone(data["timezone"])
    if "spec_template" in data:
        validate_template(data["spec_template"], settings.MAX_JOB_CELLS)
    if "tags" in data:
        data["tags"] = list(dict.fromkeys(data["tags"] or []))
    if "name" in data:
        data["name"] = data["name"].strip()
    for key, value in data.items():
        setattr(s, key, value)
    s.updated_at = utcnow()
    _commit_or_409(session, s.name)
    return schedule_out(s)


@router.delete("/schedules/{schedule_id}", status_code=204, responses=ERRORS)
def delete_schedule(schedule_id: ScheduleId, session: DB, caller: CurrentCaller):
    """Delete a schedule (its jobs stay)."""
    s = _team_schedule(session, caller.team_id, schedule_id)
    session.delete(s)
    session.commit()
    return Response(status_code=204)


@router.get("/schedules/{schedule_id}/runs", response_model=list[ScheduleRunOut], responses=ERRORS)
def schedule_runs(schedule_id: ScheduleId, session: DB, caller: CurrentCaller):
    """The due times already turned into jobs, newest first (last 100)."""
    _team_schedule(session, caller.team_id, schedule_id)
    rows = session.scalars(
        select(ScheduleRun)
        .where(ScheduleRun.schedule_id == schedule_id)
        .order_by(ScheduleRun.due_at.desc())
        .limit(100)
    ).all()
    return [
        {
            "id": r.id,
            "due_at": r.due_at,
            "job_id": r.job_id,
            "error": r.error,
            "created_at": r.created_at,
        }
        for r in rows
    ]
