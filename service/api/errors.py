"""Every error the API answers, mapped to a response once (``install_error_handlers``).

The body is always JSON ``{"detail": ..., "field": ...}``. An application error
(:class:`svrobs_lab.errors.LabError`) is answered by its kind (``service.http.errors``): 422
for a bad value (naming the field; a bad spec is a
:class:`~svrobs_core.errors.SpecError`, also 422), 404 not found, 409 a conflict
(an Idempotency-Key reused with another spec, deleting a job that is queued or
running), 410 gone (pruned rows), 403, 429 over the team's job quota or the key's
rate, 413 for a body over SVROBS_MAX_BODY_BYTES; 503 when the database is
unreachable. Anything else is a bug: it is logged with its traceback and answered
500 ``{"detail": "internal error"}``, with no internals. On a web page (a path out of
/api), an application error is the web's error page instead (``service.app``).
"""

from __future__ import annotations

import json
import logging
from collections.abc import Mapping, Sequence
from typing import Any

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from sqlalchemy.exc import DBAPIError, OperationalError
from sqlalchemy.exc import TimeoutError as PoolTimeout
from starlette.exceptions import HTTPException as StarletteHTTPException

from service.http.errors import ErrorHandler, status_of
from svrobs_core.errors import SpecError
from svrobs_lab.errors import LabError, RateLimited
from svrobs_lab.schemas import ErrorOut

log = logging.getLogger(__name__)

BODY_PARSE_ERROR = "There was an error parsing the body"  # fastapi.routing's 400 detail


def error_docs(*statuses: int) -> dict:
    """The OpenAPI ``responses`` of a route for these error statuses."""
    return {s: {"model": ErrorOut} for s in statuses}


ERRORS = error_docs(401, 404, 422, 429, 503)
BODY_ERRORS = {**ERRORS, **error_docs(413)}  # routes with a body: SVROBS_MAX_BODY_BYTES


class _ErrorJSONResponse(JSONResponse):
    """An error body always renders: text echoed from the request (a field name, an
    unknown key) may hold a lone surrogate, which is replaced rather than raising."""

    def render(self, content: Any) -> bytes:
        return json.dumps(
            content,
            ensure_ascii=False,
            allow_nan=False,
            indent=None,
            separators=(",", ":"),
            default=str,
        ).encode("utf-8", "replace")


def error_response(
    status: int,
    detail: Any,
    field: str | None = None,
    headers: Mapping[str, str] | None = None,
    **extra: Any,
) -> JSONResponse:
    return _ErrorJSONResponse(
        {"detail": detail, "field": field, **extra}, status_code=status, headers=headers
    )


def _loc_to_field(loc) -> str | None:
    parts = [p for p in loc if p not in ("body", "query", "path", "header")]
    out = ""
    for p in parts:
        if isinstance(p, int):
            out += f"[{p}]"
        else:
            out += f".{p}" if out else str(p)
    return out or None


def lab_error_response(exc: LabError | SpecError) -> JSONResponse:
    """The JSON answer of an application error (or a bad spec)."""
    headers = {"Retry-After": str(exc.retry_after)} if isinstance(exc, RateLimited) else None
    return error_response(status_of(exc), exc.message, exc.field, headers=headers)


async def _lab_error(request: Request, exc: LabError | SpecError) -> JSONResponse:
    return lab_error_response(exc)


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


async def _validation_error(request: Request, exc: RequestValidationError) -> JSONResponse:
    errors = plain_errors(exc.errors())
    first = errors[0] if errors else {}
    field = _loc_to_field(first.get("loc", ()))
    msg = first.get("msg", "invalid request")
    if first.get("type") == "extra_forbidden":
        msg = "unknown field"
    clean = [
        {
            "field": _loc_to_field(e.get("loc", ())),
            "message": e.get("msg"),
            "type": e.get("type"),
        }
        for e in errors
    ]
    return error_response(422, msg, field, errors=clean)


async def _http_error(request: Request, exc: StarletteHTTPException) -> JSONResponse:
    if exc.status_code == 400 and exc.detail == BODY_PARSE_ERROR:
        # FastAPI's 400 for a body it cannot decode (not UTF-8, nested too deep):
        # a bad body is a 422 naming the body, like malformed JSON.
        return error_response(422, "the request body is not valid JSON (UTF-8)", "body")
    if exc.status_code == 400 and request.headers.get("content-type", "").startswith(
        "multipart/form-data"
    ):
        # Starlette's 400 for a multipart body it cannot parse (a form with a file)
        return error_response(422, f"not valid multipart/form-data: {exc.detail}", "body")
    return error_response(exc.status_code, exc.detail, headers=exc.headers)


async def _db_down(request: Request, exc: OperationalError) -> JSONResponse:
    log.warning("database unavailable: %s", exc.orig if hasattr(exc, "orig") else exc)
    return error_response(503, "database unavailable; retry later", headers={"Retry-After": "5"})


async def _db_busy(request: Request, exc: PoolTimeout) -> JSONResponse:
    log.warning("no database connection free: %s", exc)
    return error_response(503, "database busy; retry later", headers={"Retry-After": "1"})


async def _db_error(request: Request, exc: DBAPIError) -> JSONResponse:
    if exc.connection_invalidated:
        return error_response(
            503, "database connection lost; retry later", headers={"Retry-After": "5"}
        )
    log.error("database error on %s %s", request.method, request.url.path, exc_info=exc)
    return error_response(500, "internal database error")


async def _internal(request: Request, exc: Exception) -> JSONResponse:
    log.error("unhandled error on %s %s", request.method, request.url.path, exc_info=exc)
    return error_response(500, "internal error")


HANDLERS: tuple[tuple[type[Exception], ErrorHandler], ...] = (
    (LabError, _lab_error),
    (SpecError, _lab_error),
    (RequestValidationError, _validation_error),
    (StarletteHTTPException, _http_error),
    (OperationalError, _db_down),
    (PoolTimeout, _db_busy),
    (DBAPIError, _db_error),
    (Exception, _internal),
)


def install_error_handlers(app: FastAPI, *, lab_error: ErrorHandler = _lab_error) -> None:
    """Register every mapping above on ``app`` (the only place errors become JSON
    responses); ``lab_error`` replaces the handler of application errors (the app
    factory's, which answers a web page with the web's error page)."""
    for exc_class, handler in HANDLERS:
        app.add_exception_handler(exc_class, lab_error if handler is _lab_error else handler)
