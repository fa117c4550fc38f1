"""Errors on a page, each mapped to the web UI's error page once, with the status the
API gives the same error (:mod:`service.http.errors`): an application error
(:class:`svrobs_lab.errors.LabError`, a bad spec: :class:`~svrobs_core.errors.SpecError`)
by its kind (:func:`lab_error_page`), a query FastAPI refused (a page number that is not
a number, a missing cell coordinate) as a 422 naming each parameter
(:func:`validation_error_page`), and the framework's HTTP errors, such as no such page,
by their status (:func:`http_error_page`); an error of the server itself (the database
down or busy, a bug) is a 503 or 500 page in plain words, its cause in the log only
(:func:`server_error_page`)."""

from __future__ import annotations

import logging
from collections.abc import Mapping
from http import HTTPStatus

from fastapi import Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import HTMLResponse
from sqlalchemy.exc import DBAPIError, OperationalError
from sqlalchemy.exc import TimeoutError as PoolTimeout
from starlette.exceptions import HTTPException as StarletteHTTPException

from service.http.errors import http_problem, status_of, validation_problem
from svrobs_core.errors import SpecError
from svrobs_lab.errors import LabError, RateLimited

from .render import WebError, render

log = logging.getLogger(__name__)


def sentence(text: str) -> str:
    """``text`` with a capital first letter and a full stop."""
    return text[:1].upper() + text[1:] + ("" if text.endswith(".") else ".")


def plain(exc: LabError | SpecError) -> str:
    """The error in one line: ``field: message`` for a field, else a sentence."""
    return f"{exc.field}: {exc.message}" if exc.field else sentence(exc.message)


def field_message(error: Mapping) -> str:
    """One of pydantic's errors of a form field in the words of the spec's own errors:
    "must be at most 100 characters long", not "String should have at most 100
    characters"; a validator's own message without pydantic's "Value error, "."""
    kind, ctx = error.get("type"), error.get("ctx") or {}
    if kind == "string_too_long":
        return f"must be at most {ctx['max_length']} characters long"
    if kind == "string_too_short":
        n = ctx.get("min_length", 1)
        return "must not be empty" if n == 1 else f"must be at least {n} characters long"
    if kind == "too_long":
        return f"must have at most {ctx['max_length']} entries ({ctx['actual_length']} given)"
    if kind == "value_error" and ctx.get("error"):
        return str(ctx["error"])
    return _clause(error.get("msg"))


def web_error(exc: LabError | SpecError) -> WebError:
    return WebError(status_of(exc), plain(exc))


def _page(request: Request, error: WebError, headers: Mapping[str, str] | None = None):
    page = render(request, "error.html", status=error.status, error=error, viewer=None)
    page.headers.update(headers or {})
    return page


def error_page(request: Request, status: int, message: str) -> HTMLResponse:
    """The page of an error found before any route (a body over the size limit)."""
    return _page(request, WebError(status, sentence(message)))


async def lab_error_page(request: Request, exc: LabError | SpecError) -> HTMLResponse:
    """The error page of an application error."""
    retry = {"Retry-After": str(exc.retry_after)} if isinstance(exc, RateLimited) else None
    return _page(request, web_error(exc), retry)


async def validation_error_page(request: Request, exc: RequestValidationError) -> HTMLResponse:
    """The 422 page of a query (or form) FastAPI refused: every parameter it names, each
    as ``name: what is wrong``."""
    problem = validation_problem(exc, request)
    each = [f"{e['field'] or 'request'}: {_clause(e['message'])}" for e in problem.errors]
    return _page(request, WebError(422, "; ".join(each) or sentence(problem.message)))


def _clause(message) -> str:
    """pydantic's message as the clause after a field's name ("must be …", "field
    required")."""
    text = str(message or "invalid value")
    return text[:1].lower() + text[1:]


async def http_error_page(request: Request, exc: StarletteHTTPException) -> HTMLResponse:
    """The page of the framework's HTTP error: 404 for a path with no page, 405 for a
    method a page does not take, 422 for a form body it cannot parse."""
    problem = http_problem(request, exc)
    if problem.status == 404 and problem.message == HTTPStatus.NOT_FOUND.phrase:
        message = f"There is no page at {request.url.path}."
    elif problem.field:
        message = f"{problem.field}: {problem.message}"
    else:
        message = sentence(str(problem.message))
    return _page(request, WebError(problem.status, message), problem.headers)


async def server_error_page(request: Request, exc: Exception) -> HTMLResponse:
    """The page of an error of the server, with the API's statuses: 503 while the
    database is down, busy or lost its connection (retry later), else 500. The cause
    goes to the log, never to the page."""
    if isinstance(exc, PoolTimeout):
        log.warning("no database connection free: %s", exc)
        error, retry = WebError(503, "The database is busy. Try again in a moment."), "1"
    elif isinstance(exc, OperationalError) or (
        isinstance(exc, DBAPIError) and exc.connection_invalidated
    ):
        log.warning("database unavailable: %s", getattr(exc, "orig", None) or exc)
        message = "The database is unavailable. Try again in a few seconds."
        error, retry = WebError(503, message), "5"
    else:
        log.error("unhandled error on %s %s", request.method, request.url.path, exc_info=exc)
        message = "Something went wrong on the server (it is logged). Reload the page to try again."
        return _page(request, WebError(500, message))
    return _page(request, error, {"Retry-After": retry})
