"""``/schedules``: the team's schedules; create one from an existing job's spec (cron,
time zone, seed policy), enable or disable it, and its past runs with links to their
jobs. Every action goes through :mod:`svrobs_lab.schedules`, as REST does, so the
page validates exactly as REST does."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Depends, Form, Query, Request
from fastapi.responses import RedirectResponse
from pydantic import ValidationError
from sqlalchemy.orm import Session

from service.db import job_queries as queries
from service.db.schedules import SEED_POLICIES
from service.http.deps import get_db
from service.web.deps import CSRF, CurrentViewer
from service.web.render import WebError, render
from svrobs_core.errors import SpecError
from svrobs_lab import schedules as lab
from svrobs_lab.auth import MAX_ID
from svrobs_lab.errors import LabError, NotFound
from svrobs_lab.schemas import ScheduleCreate, ScheduleUpdate

router = APIRouter(include_in_schema=False)
DB = Annotated[Session, Depends(get_db)]
Text = Annotated[str, Form(max_length=500)]


def _settings(request: Request):
    return request.app.state.settings


def _schedule(db: Session, viewer, schedule_id: int) -> dict:
    if not 1 <= schedule_id <= MAX_ID:
        raise NotFound(f"schedule {schedule_id} not found")
    return lab.get(db, viewer.caller, schedule_id)


@router.get("/schedules")
def schedules_page(request: Request, db: DB, viewer: CurrentViewer):
    rows = lab.list_schedules(db, viewer.caller)
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
        made = lab.create(db, viewer.caller, _settings(request), body.model_dump())
    except ValidationError as exc:
        first = exc.errors()[0]
        field = str(first["loc"][0]) if first.get("loc") else "form"
        return _new_form(request, db, viewer, status=422, errors={field: first["msg"]}, **values)
    except SpecError as exc:
        field = (exc.field or "form").split(".")[0]
        return _new_form(request, db, viewer, status=422, errors={field: exc.message}, **values)
    except LabError as exc:  # the form shows it beside its field
        field = exc.field or "form"
        return _new_form(request, db, viewer, status=422, errors={field: exc.message}, **values)
    return RedirectResponse(f"/schedules/{made['id']}", status_code=303)


@router.get("/schedules/{schedule_id:int}")
def schedule_page(request: Request, db: DB, viewer: CurrentViewer, schedule_id: int):
    s = _schedule(db, viewer, schedule_id)
    runs = lab.runs(db, viewer.caller, schedule_id)
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
    lab.update(
        db, viewer.caller, _settings(request), schedule_id, body.model_dump(exclude_unset=True)
    )
    return RedirectResponse(f"/schedules/{schedule_id}", status_code=303)
