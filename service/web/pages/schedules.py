"""``/schedules``: the team's schedules; create one from an existing job's spec (cron,
time zone, seed policy), edit it, enable or disable it, run it now, and its past runs
with links to their jobs. Every action goes through :mod:`svrobs_lab.schedules`, as
REST does, so the page validates exactly as REST does; the form checks each field
first, so that every error is shown at once (a bad time zone does not hide a bad
cron)."""

from __future__ import annotations

from typing import Annotated, cast

from fastapi import APIRouter, BackgroundTasks, Depends, Form, Query, Request
from fastapi.responses import RedirectResponse
from pydantic import ValidationError
from sqlalchemy.orm import Session

from service.db import job_queries as queries
from service.http.deps import get_db, submission_of
from service.web.deps import CSRF, CurrentViewer
from service.web.errors import field_message
from service.web.job_picks import job_picks
from service.web.render import WebError, render
from svrobs_core.errors import SpecError
from svrobs_lab import schedules as lab
from svrobs_lab.auth import MAX_ID
from svrobs_lab.errors import Conflict, Invalid, LabError, NotFound
from svrobs_lab.schemas import ScheduleCreate, ScheduleUpdate, SeedPolicy

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


def _tags(text: str) -> list[str]:
    return [t.strip() for t in text.split(",") if t.strip()]


def field_errors(request: Request, values: dict) -> dict[str, str]:
    """Every error of the schedule form's fields (name, cron, timezone, seed_policy,
    tags), each checked on its own: ``{field: message}``."""
    errors: dict[str, str] = {}
    try:
        ScheduleUpdate(
            name=values["name"],
            cron=values["cron"],
            timezone=values["timezone"],
            seed_policy=values["seed_policy"],
            tags=_tags(values["tags"]),
        )
    except ValidationError as exc:
        for e in exc.errors():
            errors.setdefault(str(e["loc"][0]) if e.get("loc") else "form", field_message(e))
    timing = lab.timing_errors(values["cron"], values["timezone"], _settings(request))
    for field, message in timing.items():
        errors.setdefault(field, message)
    return errors


# the refusals a form shows beside its fields (422); any other error of the
# application layer (not found, over a quota) is its own page, with its own status
FORM_ERRORS = (SpecError, Invalid, Conflict)


def _lab_error(exc: SpecError | LabError) -> dict[str, str]:
    """A refusal of svrobs_lab.schedules as ``{field: message}`` (a spec template's
    error under spec_template)."""
    if isinstance(exc, SpecError):
        field = (exc.field or "form").split(".")[0]
        return {field: exc.message}
    return {getattr(exc, "field", None) or "form": exc.message}


def _new_form(request, db, viewer, *, status=200, errors=None, **values):
    job = None
    if values.get("job"):
        job = queries.team_job(db, viewer.team_id, int(values["job"]))
    team_jobs = job_picks(db, viewer, [job.id] if job else []).jobs
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
        policies=lab.SEED_POLICIES,
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
    errors = field_errors(request, values)
    if not errors:
        try:
            body = ScheduleCreate(
                name=name,
                cron=cron,
                timezone=timezone,
                # one of SEED_POLICIES: field_errors checked it (the model checks it again)
                seed_policy=cast(SeedPolicy, seed_policy),
                spec_template=source.spec,
                tags=_tags(tags),
            )
            made = lab.create(db, viewer.caller, _settings(request), body.model_dump())
        except FORM_ERRORS as exc:  # the form shows it beside its field
            errors = _lab_error(exc)
    if errors:
        return _new_form(request, db, viewer, status=422, errors=errors, **values)
    return RedirectResponse(f"/schedules/{made['id']}", status_code=303)


def _schedule_page(request, db, viewer, schedule_id: int, *, status=200, errors=None, form=None):
    s = _schedule(db, viewer, schedule_id)
    runs = lab.runs(db, viewer.caller, schedule_id)
    fields = {k: s[k] for k in ("name", "cron", "timezone", "seed_policy")}
    return render(
        request,
        "schedule.html",
        status=status,
        viewer=viewer,
        nav="schedules",
        schedule=s,
        runs=runs,
        errors=errors or {},
        form=form or {**fields, "tags": ", ".join(s["tags"])},
    )


@router.get("/schedules/{schedule_id:int}")
def schedule_page(request: Request, db: DB, viewer: CurrentViewer, schedule_id: int):
    return _schedule_page(request, db, viewer, schedule_id)


@router.post("/schedules/{schedule_id:int}/edit", dependencies=[CSRF])
def edit_schedule(
    request: Request,
    db: DB,
    viewer: CurrentViewer,
    schedule_id: int,
    name: Text = "",
    cron: Text = "",
    timezone: Text = "UTC",
    seed_policy: Text = "fixed",
    tags: Text = "",
):
    """Change the name, cron, time zone, seed policy and tags (every error at once)."""
    _schedule(db, viewer, schedule_id)
    form = dict(name=name, cron=cron, timezone=timezone, seed_policy=seed_policy, tags=tags)
    errors = field_errors(request, form)
    if not errors:
        data = {**{k: v for k, v in form.items() if k != "tags"}, "tags": _tags(tags)}
        try:
            lab.update(db, viewer.caller, _settings(request), schedule_id, data)
        except FORM_ERRORS as exc:
            errors = _lab_error(exc)
    if errors:
        return _schedule_page(
            request, db, viewer, schedule_id, status=422, errors=errors, form=form
        )
    return RedirectResponse(f"/schedules/{schedule_id}?saved=1", status_code=303)


@router.post("/schedules/{schedule_id:int}/run", dependencies=[CSRF])
def run_now(
    request: Request, db: DB, viewer: CurrentViewer, schedule_id: int, background: BackgroundTasks
):
    """A job of the schedule's spec now (its seed policy at this time), tagged and
    linked to the schedule like its due runs; the due runs are not changed."""
    _schedule(db, viewer, schedule_id)
    submission = submission_of(request, db, viewer.caller, background)
    try:
        job = lab.run_now(submission, schedule_id)
    except (SpecError, Invalid) as exc:  # NotFound, over a quota: their own pages
        message = "; ".join(f"{k}: {v}" for k, v in _lab_error(exc).items())
        raise WebError(422, f"The schedule's spec was refused: {message}") from None
    return RedirectResponse(f"/jobs/{job['id']}", status_code=303)


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
