"""The HTTP status of each kind of application error (:mod:`svrobs_lab.errors`), for
the API's JSON answers (:mod:`service.api.errors`) and the web's error pages
(:mod:`service.web.errors`) alike, and the type of their exception handlers."""

from __future__ import annotations

from collections.abc import Awaitable, Callable
from typing import Any

from starlette.requests import Request
from starlette.responses import Response

from svrobs_core.errors import SpecError
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
