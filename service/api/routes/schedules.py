"""Schedules CRUD: a cron expression in a time zone, a spec template, enabled
(:mod:`svrobs_lab.schedules`). Beat's tick turns each due time into exactly one job."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Path, Response

from service.api.deps import DB, MAX_ID, CurrentCaller, SettingsDep
from service.api.errors import error_docs
from svrobs_lab import schedules
from svrobs_lab.schemas import ScheduleCreate, ScheduleOut, ScheduleRunOut, ScheduleUpdate

router = APIRouter(tags=["schedules"])
ERRORS = error_docs(401, 404, 409, 422, 429, 503)
BODY_ERRORS = {**ERRORS, **error_docs(413)}  # routes with a body: SVROBS_MAX_BODY_BYTES
ScheduleId = Annotated[int, Path(ge=1, le=MAX_ID)]


@router.post("/schedules", status_code=201, response_model=ScheduleOut, responses=BODY_ERRORS)
def create_schedule(
    body: ScheduleCreate, session: DB, caller: CurrentCaller, settings: SettingsDep
):
    """Create a schedule; the cron expression, time zone and spec template are validated."""
    return schedules.create(session, caller, settings, body.model_dump())


@router.get("/schedules", response_model=list[ScheduleOut], responses=ERRORS)
def list_schedules(session: DB, caller: CurrentCaller):
    return schedules.list_schedules(session, caller)


@router.get("/schedules/{schedule_id}", response_model=ScheduleOut, responses=ERRORS)
def get_schedule(schedule_id: ScheduleId, session: DB, caller: CurrentCaller):
    return schedules.get(session, caller, schedule_id)


@router.patch("/schedules/{schedule_id}", response_model=ScheduleOut, responses=BODY_ERRORS)
def update_schedule(
    schedule_id: ScheduleId,
    body: ScheduleUpdate,
    session: DB,
    caller: CurrentCaller,
    settings: SettingsDep,
):
    """Change any of name, cron, timezone, spec_template, tags, enabled, seed_policy."""
    data = body.model_dump(exclude_unset=True)
    return schedules.update(session, caller, settings, schedule_id, data)


@router.delete("/schedules/{schedule_id}", status_code=204, responses=ERRORS)
def delete_schedule(schedule_id: ScheduleId, session: DB, caller: CurrentCaller):
    """Delete a schedule (its jobs stay)."""
    schedules.delete(session, caller, schedule_id)
    return Response(status_code=204)


@router.get("/schedules/{schedule_id}/runs", response_model=list[ScheduleRunOut], responses=ERRORS)
def schedule_runs(schedule_id: ScheduleId, session: DB, caller: CurrentCaller):
    """The due times taken, newest first (last 100): the job made, or why none was."""
    return schedules.runs(session, caller, schedule_id)
