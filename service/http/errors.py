"""The HTTP status of each kind of application error (:mod:`svrobs_lab.errors`), and the
:class:`Problem` of a request that failed FastAPI's validation or met the framework's
HTTP error (no such route, a body it cannot parse): each rule once, for the API's JSON
answers (:mod:`service.api.errors`) and the web's error pages (:mod:`service.web.errors`)
alike; and the type of their exception handlers."""

from __future__ import annotations

from collections.abc import Awaitable, Callable, Mapping, Sequence
from dataclasses import dataclass
from dataclasses import field as dc_field
from typing import Any

from fastapi.exceptions import RequestValidationError
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.requests import Request
from starlette.responses import Response

from svrobs_core.errors import SpecError, unknown_field
from svrobs_lab.errors import LabError

STATUS = {
    "invalid": 422,
    "not_found": 404,
    "conflict": 409,
    "gone": 410,
    "forbidden": 403,
    "quota": 429,
    "too_large": 413,
}

# an exception handler (``app.add_exception_handler``): called with an instance of the
# class it is registered for
ErrorHandler = Callable[[Request, Any], Awaitable[Response]]


def status_of(exc: LabError | SpecError) -> int:
    """422 for a bad spec, else the status of the error's kind."""
    return STATUS.get(exc.kind, 400) if isinstance(exc, LabError) else 422


# FastAPI's 400 for a body it cannot decode (fastapi.routing's detail)
BODY_PARSE_ERROR = "There was an error parsing the body"


@dataclass(frozen=True)
class Problem:
    """What a request got wrong, for a JSON answer (the API) or an error page (the web):
    the status, a message, the field it names, every field's error (a request that
    failed validation) and the headers to send."""

    status: int
    message: str
    field: str | None = None
    errors: list[dict[str, Any]] = dc_field(default_factory=list)
    headers: Mapping[str, str] | None = None


def loc_to_field(loc) -> str | None:
    """A validation error's location as a field path (``N[2]``, ``sls.T_fir``)."""
    parts = [p for p in loc if p not in ("body", "query", "path", "header")]
    out = ""
    for p in parts:
        if isinstance(p, int):
            out += f"[{p}]"
        else:
            out += f".{p}" if out else str(p)
    return out or None


# pydantic names the member of a union in the location ("N.list[any]"): the kinds
# a value may be, in plain words
_KINDS = {"list": "a list", "dict": "an object", "int": "an integer", "float": "a number"}
_KINDS.update(str="a string", bool="true or false", none="null", tuple="a list")


def _kind(part) -> str | None:
    """The plain name of a union member tag in a location, else None."""
    if not isinstance(part, str):
        return None
    head = part.split("[", 1)[0]
    return _KINDS.get(head) if ("[" in part or part in _KINDS) else None


def plain_errors(errors: Sequence[dict[str, Any]]) -> list[dict[str, Any]]:
    """The errors with union member tags folded: ``N`` given a string where a list
    or an object is expected is one error, "must be a list or an object"."""
    out, unions = [], {}
    for e in errors:
        loc = tuple(e.get("loc", ()))
        tags = [i for i, p in enumerate(loc) if _kind(p)]
        if not tags:
            out.append(e)
            continue
        base = loc[: tags[0]]
        if base not in unions:
            unions[base] = {**e, "loc": base, "kinds": []}
            out.append(unions[base])
        kind = _kind(loc[tags[0]])
        if kind not in unions[base]["kinds"]:
            unions[base]["kinds"].append(kind)
    for u in unions.values():
        u["msg"], u["type"] = "must be " + " or ".join(u.pop("kinds")), "type_error"
    return out


def body_field_names(request: Request | None) -> set[str]:
    """The fields of the request's body model (its route's), or none when unknown."""
    route = request.scope.get("route") if request is not None else None
    body = getattr(route, "body_field", None)
    model = getattr(getattr(body, "field_info", None), "annotation", None)
    fields = getattr(model, "model_fields", None)
    if not isinstance(fields, dict):
        return set()
    return {f.alias or name for name, f in fields.items()}


def validation_problem(exc: RequestValidationError, request: Request | None = None) -> Problem:
    """A request that failed FastAPI's validation: 422 naming its first bad field, with
    every field's error (``{field, message, type}``). An unknown field of the body
    (``sigmaw``) names the body's field it is a typo of, when one is close."""
    raw = plain_errors(exc.errors())
    errors = [
        {"field": loc_to_field(e.get("loc", ())), "message": e.get("msg"), "type": e.get("type")}
        for e in raw
    ]
    first = errors[0] if errors else {"field": None, "message": "invalid request", "type": None}
    message = str(first["message"])
    if first["type"] == "extra_forbidden":
        loc = tuple(raw[0].get("loc", ()))
        top = len(loc) == 2 and loc[0] == "body" and isinstance(loc[1], str)
        message = unknown_field(loc[1], body_field_names(request)) if top else "unknown field"
    return Problem(422, message, first["field"], errors)


def http_problem(request: Request, exc: StarletteHTTPException) -> Problem:
    """An HTTP error raised by the framework (no route, wrong method, a body it cannot
    parse): its status and detail, except that a body it cannot decode is a 422 naming
    the body, like malformed JSON."""
    if exc.status_code == 400 and exc.detail == BODY_PARSE_ERROR:
        # not UTF-8, nested too deep
        return Problem(422, "the request body is not valid JSON (UTF-8)", "body")
    if exc.status_code == 400 and request.headers.get("content-type", "").startswith(
        "multipart/form-data"
    ):
        # Starlette's 400 for a multipart body it cannot parse (a form with a file)
        return Problem(422, f"not valid multipart/form-data: {exc.detail}", "body")
    return Problem(exc.status_code, exc.detail, headers=exc.headers)
