"""``/jobs/new``: submit a spec pasted, uploaded as a .json file or taken from a preset.

The body is checked exactly as ``POST /api/v1/jobs`` checks it (its ``JobSubmit``
model, then the core's ``parse_spec``) and created by the API's one submit-and-
publish step (``svrobs_lab.jobs.Submission``, under the viewer's caller); each error is shown beside its field, naming the spec path
(``systems[0].A``). A hidden Idempotency-Key per form makes a double submit one job.
"""

from __future__ import annotations

import json
import secrets
from typing import Annotated

from fastapi import APIRouter, BackgroundTasks, Depends, File, Form, Request, UploadFile
from fastapi.responses import RedirectResponse
from pydantic import ValidationError
from sqlalchemy.orm import Session

from service.http.deps import get_db, submission_of
from service.web.deps import CSRF, CurrentViewer
from service.web.render import render
from svrobs_core import parse_spec
from svrobs_core.errors import SpecError
from svrobs_core.paper import PRESET_NAME, paper_specs
from svrobs_core.systems import PRESETS
from svrobs_lab.datasets.overview import starter_spec
from svrobs_lab.errors import IdempotencyConflict, QuotaExceeded
from svrobs_lab.jobs import JobRequest
from svrobs_lab.schemas import SPEC_FIELD_NAMES, JobSubmit

router = APIRouter(include_in_schema=False)
DB = Annotated[Session, Depends(get_db)]
FORM_FIELDS = ("name", "tags")  # shown beside their own inputs; anything else is the spec's


def _starter(system: str) -> dict:
    """A small sweep of one preset system (the README tour's grid)."""
    return {
        "systems": [system],
        "sigma_w": [0.1, 1.0],
        "N": {"start": 10, "stop": 100, "step": 10},
        "gamma": [0.01, 0.05, 0.1],
        "reps": 20,
        "stages": ["estimate", "bounds"],
        "seed": 7,
    }


def presets() -> dict[str, tuple[str, dict]]:
    """``id -> (label, spec)``: a starter sweep per system preset (GET /api/v1/presets)
    and the paper's Section 6 experiments (POST /api/v1/presets/paper-section-6/run)."""
    out = {f"system:{n}": (f"{n}: a sweep of N, σ_w and γ", _starter(n)) for n in sorted(PRESETS)}
    for scale in ("reduced", "full"):
        for exp, spec in sorted(paper_specs(scale).items()):
            out[f"{PRESET_NAME}:{exp}:{scale}"] = (f"{PRESET_NAME} {exp} ({scale})", spec)
    return out


def _field(loc) -> str:
    out = ""
    for part in loc:
        out += f"[{part}]" if isinstance(part, int) else (f".{part}" if out else str(part))
    return out or "spec"


def _form(request, viewer, *, status=200, errors=None, **values):
    if not values.get("idempotency_key"):
        values["idempotency_key"] = secrets.token_urlsafe(16)
    catalogue = presets()
    return render(
        request,
        "submit.html",
        status=status,
        viewer=viewer,
        nav="submit",
        presets=[(k, label) for k, (label, _) in catalogue.items()],
        errors=errors or {},
        form={"spec": "", "name": "", "tags": "", "preset": "", **values},
    )


@router.get("/jobs/new")
def submit_form(
    request: Request, db: DB, viewer: CurrentViewer, preset: str = "", dataset: int | None = None
):
    """The form, filled with a preset, or with a first job on one of the team's
    datasets (``?dataset=ID``, the dataset page's "new job on this dataset")."""
    if dataset is not None:
        spec = starter_spec(db, viewer.caller, dataset)  # NotFound: a 404 page
        return _form(request, viewer, spec=json.dumps(spec, indent=2))
    spec = presets().get(preset)
    text = json.dumps(spec[1], indent=2) if spec else ""
    return _form(request, viewer, spec=text, preset=preset if spec else "")


@router.get("/jobs/new/preset")
def preset_spec(request: Request, viewer: CurrentViewer, preset: str = ""):
    """The spec textarea filled with a preset (htmx swaps it in)."""
    spec = presets().get(preset)
    text = json.dumps(spec[1], indent=2) if spec else ""
    return render(request, "_spec_field.html", form={"spec": text}, errors={})


def _read_spec(text: str, upload: UploadFile | None) -> tuple[str, dict | None, dict]:
    """(the spec text, the parsed body or None, errors)."""
    if upload is not None and upload.filename:
        raw = upload.file.read()
        try:
            text = raw.decode("utf-8")
        except UnicodeDecodeError:
            return "", None, {"file": ("file", "the file is not UTF-8 text")}
    if not text.strip():
        return text, None, {"spec": ("spec", "paste a spec, upload a .json file or pick a preset")}
    try:
        body = json.loads(text)
    except json.JSONDecodeError as exc:
        return text, None, {"spec": ("spec", f"not valid JSON: {exc}")}
    if not isinstance(body, dict):
        return text, None, {"spec": ("spec", "must be a JSON object")}
    return text, body, {}


def _body_error(exc: ValidationError, body: dict) -> dict:
    """The first error of the request model as ``{input: (field, message)}``. A spec
    value of the wrong type is reported by the core's parser, in its plain words
    (``N: must be a non-empty list``), not by the model's union internals."""
    first = exc.errors()[0]
    loc = first["loc"]
    if first["type"] == "extra_forbidden":
        return {"spec": (_field(loc), "unknown field")}
    if loc and loc[0] in FORM_FIELDS:
        return {loc[0]: (_field(loc), first["msg"])}
    try:
        parse_spec({k: v for k, v in body.items() if k not in FORM_FIELDS})
    except SpecError as err:
        return {"spec": (err.field or "spec", err.message)}
    return {"spec": (str(loc[0]), first["msg"])}


@router.post("/jobs/new", dependencies=[CSRF])
def submit(
    request: Request,
    db: DB,
    viewer: CurrentViewer,
    background: BackgroundTasks,
    spec: Annotated[str, Form()] = "",
    spec_file: Annotated[UploadFile | None, File()] = None,
    name: Annotated[str, Form()] = "",
    tags: Annotated[str, Form()] = "",
    preset: Annotated[str, Form()] = "",
    idempotency_key: Annotated[str, Form(max_length=200)] = "",
):
    values = dict(name=name, tags=tags, preset=preset, idempotency_key=idempotency_key)
    text, body, errors = _read_spec(spec, spec_file)
    values["spec"] = text
    if body is not None:
        tag_list = [t.strip() for t in tags.split(",") if t.strip()]
        body = {**body, **({"name": name.strip()} if name.strip() else {})}
        body = {**body, **({"tags": tag_list} if tag_list else {})}
        try:
            data = JobSubmit.model_validate(body).model_dump(exclude_unset=True)
        except ValidationError as exc:
            errors = _body_error(exc, body)
    if errors:
        return _form(request, viewer, status=422, errors=errors, **values)
    job = JobRequest(
        spec={k: data[k] for k in SPEC_FIELD_NAMES if k in data},
        name=data.get("name"),
        tags=data.get("tags") or (),
        idempotency_key=idempotency_key or None,
    )
    submission = submission_of(request, db, viewer.caller, background)
    try:
        (out,) = submission.submit([job])
    except SpecError as exc:
        db.rollback()
        errors = {"spec": (exc.field or "spec", exc.message)}
    except QuotaExceeded as exc:
        db.rollback()
        errors = {"form": ("", exc.message)}
    except IdempotencyConflict:
        db.rollback()
        errors = {"form": ("", "this form was already used for another spec: submit it again")}
        values.pop("idempotency_key")
    if errors:
        return _form(request, viewer, status=422, errors=errors, **values)
    return RedirectResponse(f"/jobs/{out['id']}", status_code=303)
