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
/api), an application error, a request that failed validation and the framework's
HTTP errors (no such page) are the web's error page instead (``service.app``).
"""

from __future__ import annotations

import json
import logging
from collections.abc import Callable, Mapping
from typing import Any

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from sqlalchemy.exc import DBAPIError, OperationalError
from sqlalchemy.exc import TimeoutError as PoolTimeout
from starlette.exceptions import HTTPException as StarletteHTTPException

from service.http.errors import ErrorHandler, http_problem, status_of, validation_problem
from service.http.security import ALWAYS
from svrobs_core.errors import SpecError
from svrobs_lab.errors import LabError, RateLimited
from svrobs_lab.schemas import ErrorOut

log = logging.getLogger(__name__)


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
    # the security headers here too: an unhandled error's response is made outside every
    # middleware (Starlette's ServerErrorMiddleware), SecurityHeaders included
    return _ErrorJSONResponse(
        {"detail": detail, "field": field, **extra},
        status_code=status,
        headers={**ALWAYS, **(headers or {})},
    )


def lab_error_response(exc: LabError | SpecError) -> JSONResponse:
    """The JSON answer of an application error (or a bad spec)."""
    headers = {"Retry-After": str(exc.retry_after)} if isinstance(exc, RateLimited) else None
    return error_response(status_of(exc), exc.message, exc.field, headers=headers)


async def _lab_error(request: Request, exc: LabError | SpecError) -> JSONResponse:
    return lab_error_response(exc)


async def _validation_error(request: Request, exc: RequestValidationError) -> JSONResponse:
    p = validation_problem(exc, request)
    return error_response(p.status, p.message, p.field, errors=p.errors)


async def _http_error(request: Request, exc: StarletteHTTPException) -> JSONResponse:
    p = http_problem(request, exc)
    return error_response(p.status, p.message, p.field, headers=p.headers)


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


def install_error_handlers(
    app: FastAPI,
    *,
    pages: Mapping[type[Exception], ErrorHandler] | None = None,
    is_api: Callable[[Request], bool] = lambda request: True,
) -> None:
    """Register every mapping above on ``app`` (the only place errors become JSON
    responses). ``pages`` maps an exception class to the handler that answers it on
    a request ``is_api`` says is not the API's (a web page: the web's error page)."""
    for exc_class, handler in HANDLERS:
        page = (pages or {}).get(exc_class)
        app.add_exception_handler(
            exc_class, handler if page is None else _by_path(handler, page, is_api)
        )


def _by_path(api: ErrorHandler, page: ErrorHandler, is_api) -> ErrorHandler:
    async def handle(request: Request, exc: Exception):
        return await (api if is_api(request) else page)(request, exc)

    return handle
