"""Every error the API answers, mapped to a response once (``install_error_handlers``).

The body is always JSON ``{"detail": ..., "field": ...}``: 422 for a bad spec or
body (naming the field), 409 for an Idempotency-Key reused with another spec or for
deleting a job that is queued or running (``JobActive``; on a web page, the web
UI's error page: ``app.state.error_page``), 429
over the team's job quota, 413 for a body over SVROBS_MAX_BODY_BYTES, 503 when
the database is unreachable. Anything else is a bug: it is logged with its
traceback and answered 500 ``{"detail": "internal error"}``, with no internals.
"""

from __future__ import annotations

import json
import logging
from typing import Any

from fastapi import FastAPI, HTTPException, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from sqlalchemy.exc import DBAPIError, OperationalError
from sqlalchemy.exc import TimeoutError as PoolTimeout
from starlette.exceptions import HTTPException as StarletteHTTPException

from service.api.schemas import ErrorOut
from service.db.datasets import DatasetInUse
from service.db.errors import IdempotencyConflict, QuotaExceeded
from service.db.job_delete import JobActive
from svrobs_core.errors import SpecError

log = logging.getLogger(__name__)

BODY_PARSE_ERROR = "There was an error parsing the body"  # fastapi.routing's 400 detail


def error_docs(*statuses: int) -> dict:
    """The OpenAPI ``responses`` of a route for these error statuses."""
    return {s: {"model": ErrorOut} for s in statuses}


ERRORS = error_docs(401, 404, 422, 429, 503)
BODY_ERRORS = {**ERRORS, **error_docs(413)}  # routes with a body: SVROBS_MAX_BODY_BYTES


class FieldHTTPException(HTTPException):
    """An HTTP error naming the request field it is about."""

    def __init__(self, status: int, detail, field: str | None = None, headers=None):
        super().__init__(status, detail, headers=headers)
        self.field = field


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
    status: int, detail: Any, field: str | None = None, headers: dict | None = None, **extra
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


async def _spec_error(request: Request, exc: SpecError):
    return error_response(422, exc.message, exc.field)


async def _quota_exceeded(request: Request, exc: QuotaExceeded):
    return error_response(429, str(exc))


async def _idempotency_conflict(request: Request, exc: IdempotencyConflict):
    return error_response(409, str(exc), "Idempotency-Key")


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


def plain_errors(errors: list[dict]) -> list[dict]:
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


async def _job_active(request: Request, exc: JobActive):
    page = getattr(request.app.state, "error_page", None)
    if page is not None and not request.url.path.startswith("/api/"):
        return page(request, 409, f"{str(exc).capitalize()}.")
    return error_response(409, str(exc))


async def _validation_error(request: Request, exc: RequestValidationError):
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


async def _http_error(request: Request, exc: StarletteHTTPException):
    field = getattr(exc, "field", None)  # a FieldHTTPException names one
    if exc.status_code == 400 and exc.detail == BODY_PARSE_ERROR:
        # FastAPI's 400 for a body it cannot decode (not UTF-8, nested too deep):
        # a bad body is a 422 naming the body, like malformed JSON.
        return error_response(422, "the request body is not valid JSON (UTF-8)", "body")
    return error_response(exc.status_code, exc.detail, field, headers=exc.headers)


async def _db_down(request: Request, exc: OperationalError):
    log.warning("database unavailable: %s", exc.orig if hasattr(exc, "orig") else exc)
    return error_response(503, "database unavailable; retry later", headers={"Retry-After": "5"})


async def _db_busy(request: Request, exc: PoolTimeout):
    log.warning("no database connection free: %s", exc)
    return error_response(503, "database busy; retry later", headers={"Retry-After": "1"})


async def _db_error(request: Request, exc: DBAPIError):
    if exc.connection_invalidated:
        return error_response(
            503, "database connection lost; retry later", headers={"Retry-After": "5"}
        )
    log.error("database error on %s %s", request.method, request.url.path, exc_info=exc)
    return error_response(500, "internal database error")


async def _internal(request: Request, exc: Exception):
    log.error("unhandled error on %s %s", request.method, request.url.path, exc_info=exc)
    return error_response(500, "internal error")


HANDLERS = (
    (SpecError, _spec_error),
    (QuotaExceeded, _quota_exceeded),
    (IdempotencyConflict, _idempotency_conflict),
    (JobActive, _job_active),
    (DatasetInUse, _job_active),  # a 409 with its message, as for an active job
    (RequestValidationError, _validation_error),
    (StarletteHTTPException, _http_error),
    (OperationalError, _db_down),
    (PoolTimeout, _db_busy),
    (DBAPIError, _db_error),
    (Exception, _internal),
)


def install_error_handlers(app: FastAPI) -> None:
    """Register every mapping above on ``app`` (the only place errors become responses)."""
    for exc_class, handler in HANDLERS:
        app.add_exception_handler(exc_class, handler)
