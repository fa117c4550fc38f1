"""``/schedules``: the team's schedules; create one from an existing job's spec (cron,
time zone, seed policy), enable or disable it, and its past runs with links to their
jobs. Every action goes through the API's own route functions
(service.api.routes.schedules), so the page validates exactly as REST does."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Depends, Form, HTTPException, Query, Request
from fastapi.responses import RedirectResponse
from pydantic import ValidationError
from sqlalchemy.orm import Session

from service.api.deps import MAX_ID, get_db
from service.api.routes import schedules as api
from service.api.schemas import ScheduleCreate, ScheduleUpdate
from service.db.schedules import SEED_POLICIES
from service.web import queries
from service.web.deps import CSRF, CurrentViewer
from service.web.render import WebError, render
from svrobs_core.errors import SpecError

router = APIRouter(include_in_schema=False)
DB = Annotated[Session, Depends(get_db)]
Text = Annotated[str, Form(max_length=500)]


def _settings(request: Request):
    return request.app.state.settings


def _schedule(db: Session, viewer, schedule_id: int) -> dict:
    try:
        if not 1 <= schedule_id <= MAX_ID:
            raise HTTPException(404)
        return api.get_schedule(schedule_id, db, viewer.caller)
    except HTTPException:
        raise WebError(404, f"Schedule {schedule_id} not found.") from None


@router.get("/schedules")
def schedules_page(request: Request, db: DB, viewer: CurrentViewer):
    rows = api.list_schedules(db, viewer.caller)
    return render(request, "schedules.html", viewer=viewer, nav="schedules", schedules=rows)


def _new_form(request, db, viewer, *, status=200, errors=None, **values):
    team_jobs, _ = queries.job_page(
        db, viewer.team_id, viewer.caller.user_id, queries.JobFilter(), limit=200, offset=0
    )
    job = None
    if values.get("job"):
        job = queries.team_job(db, viewer.team_id, int(values["job"]))
    form = {"cron": "0 2 * * *", "timezone": "UTC", "seed_policy": "fixed", "name": "", "tags": ""}
    form.update({k: v for k, v in values.items() if v is not None})
    return render(
        request,
        "schedule_new.html",
        status=status,
        viewer=viewer,
        nav="schedules",
        team_jobs=team_jobs,
        job=job,
        form=form,
        errors=errors or {},
        policies=SEED_POLICIES,
    )


@router.get("/schedules/new")
def new_schedule_page(
    request: Request, db: DB, viewer: CurrentViewer, job: Annotated[int | None, Query(ge=1)] = None
):
    if job is not None and (job > MAX_ID or queries.team_job(db, viewer.team_id, job) is None):
        raise WebError(404, f"Job {job} not found.")
    name = f"nightly job {job}" if job else ""
    return _new_form(request, db, viewer, job=job, name=name)


@router.post("/schedules/new", dependencies=[CSRF])
def create_schedule(
    request: Request,
    db: DB,
    viewer: CurrentViewer,
    job: Annotated[int, Form(ge=1, le=MAX_ID)],
    name: Text = "",
    cron: Text = "",
    timezone: Text = "UTC",
    seed_policy: Text = "fixed",
    tags: Text = "",
):
    values = dict(job=job, name=name, cron=cron, timezone=timezone, seed_policy=seed_policy)
    values["tags"] = tags
    source = queries.team_job(db, viewer.team_id, job)
    if source is None:
        raise WebError(404, f"Job {job} not found.")
    try:
        body = ScheduleCreate(
            name=name,
            cron=cron,
            timezone=timezone,
            seed_policy=seed_policy,
            spec_template=source.spec,
            tags=[t.strip() for t in tags.split(",") if t.strip()],
        )
        made = api.create_schedule(body, db, viewer.caller, _settings(request))
    except ValidationError as exc:
        first = exc.errors()[0]
        field = str(first["loc"][0]) if first.get("loc") else "form"
        return _new_form(request, db, viewer, status=422, errors={field: first["msg"]}, **values)
    except SpecError as exc:
        field = (exc.field or "form").split(".")[0]
        return _new_form(request, db, viewer, status=422, errors={field: exc.message}, **values)
    except HTTPException as exc:
        field = getattr(exc, "field", None) or "form"
        return _new_form(request, db, viewer, status=422, errors={field: exc.detail}, **values)
    return RedirectResponse(f"/schedules/{made['id']}", status_code=303)


@router.get("/schedules/{schedule_id:int}")
def schedule_page(request: Request, db: DB, viewer: CurrentViewer, schedule_id: int):
    s = _schedule(db, viewer, schedule_id)
    runs = api.schedule_runs(schedule_id, db, viewer.caller)
    return render(request, "schedule.html", viewer=viewer, nav="schedules", schedule=s, runs=runs)


@router.post("/schedules/{schedule_id:int}/enabled", dependencies=[CSRF])
def set_enabled(
    request: Request,
    db: DB,
    viewer: CurrentViewer,
    schedule_id: int,
    enabled: Annotated[str, Form(pattern="^(yes|no)$")],
):
    _schedule(db, viewer, schedule_id)
    body = ScheduleUpdate(enabled=enabled == "yes")
    api.update_schedule(schedule_id, body, db, viewer.caller, _settings(request))
    return RedirectResponse(f"/schedules/{schedule_id}", status_code=303)
