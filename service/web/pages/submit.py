"""``/jobs/new``: submit a spec pasted, uploaded as a .json file or taken from a preset.

The body is checked exactly as ``POST /api/v1/jobs`` checks it (its ``JobSubmit``
model, then the core's ``parse_spec``) and created by the API's one submit-and-
publish step (``svrobs_lab.jobs.Submission``, under the viewer's caller). The
spec comes from the form's fields (service.web.spec_form) or from its JSON view;
every error is shown at once, each beside its field and naming the spec path
(``systems[0].A``). A hidden Idempotency-Key per form makes a double submit one job.
"""

from __future__ import annotations

import json
import secrets
from typing import Annotated, NamedTuple

from fastapi import APIRouter, BackgroundTasks, Depends, File, Form, Query, Request, UploadFile
from fastapi.responses import RedirectResponse
from pydantic import ValidationError
from sqlalchemy.orm import Session
from starlette.datastructures import FormData

from service.http.deps import get_db, submission_of
from service.web import spec_form
from service.web.deps import CSRF, CurrentViewer
from service.web.errors import field_message
from service.web.render import render
from svrobs_core.errors import SpecError
from svrobs_core.paper import PRESET_NAME, paper_specs
from svrobs_core.spec_fields import spec_errors
from svrobs_core.systems import PRESETS
from svrobs_lab import json_text
from svrobs_lab.auth import MAX_ID
from svrobs_lab.datasets.overview import datasets_page, starter_spec
from svrobs_lab.errors import IdempotencyConflict, QuotaExceeded
from svrobs_lab.jobs import JobRequest, data_errors
from svrobs_lab.schemas import SPEC_FIELD_NAMES, JobSubmit

router = APIRouter(include_in_schema=False)
DB = Annotated[Session, Depends(get_db)]
FORM_FIELDS = ("name", "tags")  # shown beside their own inputs; anything else is the spec's
# where each field is on the page: the list of errors at the top follows it
_PAGE_ORDER = {
    key: i
    for i, key in enumerate(
        (*FORM_FIELDS, *(f.form_key for _, fs in spec_form.groups() for f in fs), "spec", "file")
    )
}


class Preset(NamedTuple):
    label: str
    spec: dict
    name: str
    tags: tuple[str, ...]


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


def presets() -> dict[str, Preset]:
    """``id -> Preset``: a starter sweep per system preset (GET /api/v1/presets) and the
    paper's Section 6 experiments, named and tagged as POST
    /api/v1/presets/paper-section-6/run names and tags them."""
    out = {
        f"system:{n}": Preset(
            f"{n}: a sweep of N, σ_w and γ", _starter(n), f"{n} sweep", ("sweep", n)
        )
        for n in sorted(PRESETS)
    }
    for scale in ("reduced", "full"):
        for exp, spec in sorted(paper_specs(scale).items()):
            label = f"{PRESET_NAME} {exp} ({scale})"
            out[f"{PRESET_NAME}:{exp}:{scale}"] = Preset(label, spec, label, (PRESET_NAME, exp))
    return out


def _field(loc) -> str:
    out = ""
    for part in loc:
        out += f"[{part}]" if isinstance(part, int) else (f".{part}" if out else str(part))
    return out or "spec"


def _dataset_choices(db: Session, viewer, chosen: str) -> list[tuple[str, str]]:
    """(id, label) of the team's newest datasets for the dataset field, and the chosen
    id if it is not among them (the server then says whether the team has it)."""
    items = datasets_page(db, viewer.caller)["items"]
    out = [
        (str(d["id"]), f"{d['id']}: {d['name']} ({d['rollouts']} rollouts, n={d['n']}, m={d['m']})")
        for d in items
    ]
    if chosen and chosen not in {k for k, _ in out}:
        out.append((chosen, f"{chosen}"))
    return out


def _form(
    request,
    db,
    viewer,
    *,
    status=200,
    errors=None,
    spec_errors=None,
    spec=None,
    shown=None,
    **values,
):
    """The form: its fields show ``spec`` (else the defaults), each error of
    ``spec_errors`` ({path: message}) beside its field and all of them in a list at the
    top; ``errors``: those of the name, tags, file, JSON text and the form as a whole;
    ``shown``: the fields' values as posted (instead of ``spec``'s). The dataset field
    lists the team's datasets."""
    if not values.get("idempotency_key"):
        values["idempotency_key"] = secrets.token_urlsafe(16)
    errors, spec_errors = errors or {}, spec_errors or {}
    fields = shown or spec_form.values_of(spec or {})
    chosen = str(fields.get("dataset") or "")
    on_dataset = bool(chosen)
    listed = [(spec_form.field_of(p, dataset=on_dataset), p, m) for p, m in spec_errors.items()]
    listed += [(k, path or k, m) for k, (path, m) in errors.items() if k != "form"]
    listed.sort(key=lambda e: _PAGE_ORDER.get(e[0], len(_PAGE_ORDER)))  # as the fields are
    return render(
        request,
        "submit.html",
        status=status,
        viewer=viewer,
        nav="submit",
        presets=[(k, p.label) for k, p in presets().items()],
        errors=errors,
        errors_list=listed,
        field_errors=spec_form.errors_by_field(spec_errors, dataset=on_dataset),
        groups=spec_form.groups(),
        job_of=spec_form.job_of,
        datasets=_dataset_choices(db, viewer, chosen),
        values=fields,
        form={
            "spec": values.pop("spec_text", ""),
            **{"name": "", "tags": "", "preset": "", "source": "form", **values},
        },
    )


def _json(spec: dict) -> str:
    return json.dumps(spec, indent=2)


@router.get("/jobs/new")
def submit_form(
    request: Request,
    db: DB,
    viewer: CurrentViewer,
    preset: str = "",
    dataset: Annotated[int | None, Query(ge=1, le=MAX_ID)] = None,
):
    """The form, empty (the defaults), filled by a preset (every field, name and tags),
    or with a first job on one of the team's datasets (``?dataset=ID``, the dataset
    page's "new job on this dataset")."""
    if dataset is not None:
        spec = starter_spec(db, viewer.caller, dataset)  # NotFound: a 404 page
        return _form(request, db, viewer, spec=spec, spec_text=_json(spec_form.complete(spec)))
    chosen = presets().get(preset)
    spec = spec_form.complete(chosen.spec if chosen else {})
    if chosen is None:
        return _form(request, db, viewer, spec=spec, spec_text=_json(spec))
    return _form(
        request,
        db,
        viewer,
        spec=spec,
        spec_text=_json(spec),
        preset=preset,
        name=chosen.name,
        tags=", ".join(chosen.tags),
    )


def _read_spec(text: str, upload: UploadFile | None) -> tuple[str, dict | None, dict]:
    """(the spec text, the parsed body or None, errors)."""
    if upload is not None and upload.filename:
        raw = upload.file.read()
        try:
            text = raw.decode("utf-8-sig")  # a byte-order mark, as some editors save
        except UnicodeDecodeError:
            return "", None, {"file": ("file", "the file is not UTF-8 text")}
    if not text.strip():
        return text, None, {"spec": ("spec", "paste a spec, upload a .json file or pick a preset")}
    try:
        body = json_text.loads(text)
    except ValueError as exc:
        return text, None, {"spec": ("spec", str(exc))}
    if not isinstance(body, dict):
        return text, None, {"spec": ("spec", "must be a JSON object")}
    return text, body, {}


def _name_tag_errors(exc: ValidationError) -> dict:
    """The errors of the name and tags (the spec's are spec_errors')."""
    out = {}
    for e in exc.errors():
        loc = e["loc"]
        if loc and loc[0] in FORM_FIELDS and loc[0] not in out:
            out[loc[0]] = (_field(loc), field_message(e))
    return out


async def form_data(request: Request):
    """Every field of the posted form (the spec's inputs are named per field)."""
    return await request.form()


@router.post("/jobs/new", dependencies=[CSRF])
def submit(
    request: Request,
    db: DB,
    viewer: CurrentViewer,
    background: BackgroundTasks,
    posted: Annotated[FormData, Depends(form_data)],
    spec: Annotated[str, Form()] = "",
    spec_file: Annotated[UploadFile | None, File()] = None,
    name: Annotated[str, Form()] = "",
    tags: Annotated[str, Form()] = "",
    preset: Annotated[str, Form()] = "",
    source: Annotated[str, Form(pattern="^(form|json)$")] = "json",
    idempotency_key: Annotated[str, Form(max_length=200)] = "",
):
    """The spec of the fields (``source=form``) or of the JSON text or file
    (``source=json``, also when the field is not sent); every error at once."""
    values = dict(name=name, tags=tags, preset=preset, idempotency_key=idempotency_key)
    uploaded = spec_file is not None and spec_file.filename
    shown = None
    body: dict | None
    errors: dict
    if source == "form" and not uploaded:
        body, type_errors = spec_form.spec_of(posted, posted.getlist)
        text, errors = _json(body), {}
        shown = spec_form.posted_values(posted, posted.getlist)
    else:
        text, body, errors = _read_spec(spec, spec_file)
        type_errors = {}
    values.update(spec_text=text, source="json" if uploaded else source)
    found: dict = {}

    def refused(errors: dict, found: dict):
        """The form again (422) with every error, the values as they were sent."""
        return _form(
            request,
            db,
            viewer,
            status=422,
            errors=errors,
            spec_errors=found,
            spec=body,
            shown=shown,
            **values,
        )

    if body is not None:
        found = {**type_errors}
        on_dataset = "dataset" in body
        typed = {spec_form.field_of(p, dataset=on_dataset) for p in type_errors}
        for path, message in spec_errors(body).items():
            if spec_form.field_of(path, dataset=on_dataset) not in typed:
                found.setdefault(path, message)
        tag_list = [t.strip() for t in tags.split(",") if t.strip()]
        full = {**body, **({"name": name.strip()} if name.strip() else {})}
        full = {**full, **({"tags": tag_list} if tag_list else {})}
        try:
            data = JobSubmit.model_validate(full).model_dump(exclude_unset=True)
        except ValidationError as exc:
            errors.update(_name_tag_errors(exc))
            if not found and not errors:  # the model refused what the parser accepts
                first = exc.errors()[0]
                errors["spec"] = (_field(first["loc"]), field_message(first))
    if errors or found:
        return refused(errors, found)
    job = JobRequest(
        spec={k: data[k] for k in SPEC_FIELD_NAMES if k in data},
        name=data.get("name"),
        tags=data.get("tags") or (),
        idempotency_key=idempotency_key or None,
    )
    # every check against the dataset's shape at once (submitting stops at the first)
    found = data_errors(db, viewer.caller, job.spec)
    if found:
        return refused(errors, found)
    submission = submission_of(request, db, viewer.caller, background)
    try:
        (out,) = submission.submit([job])
    except SpecError as exc:  # the service's limits (cells, estimated work)
        db.rollback()
        found = {exc.field or "spec": exc.message}
    except QuotaExceeded as exc:
        db.rollback()
        errors = {"form": ("", exc.message)}
    except IdempotencyConflict:
        db.rollback()
        errors = {"form": ("", "this form was already used for another spec: submit it again")}
        values.pop("idempotency_key")
    if errors or found:
        return refused(errors, found)
    return RedirectResponse(f"/jobs/{out['id']}", status_code=303)
