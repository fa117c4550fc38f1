"""Application errors on a page: :func:`lab_error_page` maps each
:class:`svrobs_lab.errors.LabError` (and a bad spec, a
:class:`~svrobs_core.errors.SpecError`) to the web UI's error page, once, with the
status of its kind (:mod:`service.http.errors`)."""

from __future__ import annotations

from fastapi import Request
from fastapi.responses import HTMLResponse

from service.http.errors import status_of
from svrobs_core.errors import SpecError
from svrobs_lab.errors import LabError, RateLimited

from .render import WebError, render


def plain(exc: LabError | SpecError) -> str:
    """The error in one line: ``field: message`` for a field, else a sentence."""
    if exc.field:
        return f"{exc.field}: {exc.message}"
    text = exc.message
    return text[:1].upper() + text[1:] + ("" if text.endswith(".") else ".")


def web_error(exc: LabError | SpecError) -> WebError:
    return WebError(status_of(exc), plain(exc))


def lab_error_page(request: Request, exc: LabError | SpecError) -> HTMLResponse:
    """The error page of an application error."""
    error = web_error(exc)
    page = render(request, "error.html", status=error.status, error=error, viewer=None)
    if isinstance(exc, RateLimited):
        page.headers["Retry-After"] = str(exc.retry_after)
    return page
