"""Application errors on a page: :func:`lab_error_page` maps each
:class:`svrobs_lab.errors.LabError` kind (and a bad spec, a
:class:`~svrobs_core.errors.SpecError`) to the web UI's error page, once."""

from __future__ import annotations

from fastapi import Request
from fastapi.responses import HTMLResponse

from svrobs_core.errors import SpecError
from svrobs_lab.errors import LabError

from .render import WebError, render

STATUS = {
    "invalid": 422,
    "not_found": 404,
    "conflict": 409,
    "gone": 410,
    "forbidden": 403,
    "quota": 429,
    "too_large": 413,
}


def plain(exc: LabError | SpecError) -> str:
    """The error in one line: ``field: message`` for a field, else a sentence."""
    if exc.field:
        return f"{exc.field}: {exc.message}"
    text = exc.message
    return text[:1].upper() + text[1:] + ("" if text.endswith(".") else ".")


def web_error(exc: LabError | SpecError) -> WebError:
    status = STATUS.get(exc.kind, 400) if isinstance(exc, LabError) else 422
    return WebError(status, plain(exc))


def lab_error_page(request: Request, exc: LabError | SpecError) -> HTMLResponse:
    """The error page of an application error."""
    error = web_error(exc)
    return render(request, "error.html", status=error.status, error=error, viewer=None)
