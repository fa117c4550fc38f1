"""Typed exceptions built from the API's JSON error body ``{"detail", "field"}``.

Every error the client raises is a :class:`SvrobsError`; an HTTP error carries the
``status`` code, the offending ``field`` (``None`` when the API names none) and the
``message`` (the API's ``detail``). Transport and configuration problems have
``status`` ``None``. An answer that is not the API's (a redirect, an HTML page where
the API sends data: the URL is not the API's address; a report page without the API's
:data:`REPORT_HEADER`) is a :class:`SvrobsError` itself, with the answer's ``status``.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import httpx


class SvrobsError(Exception):
    """Base class: ``status`` (HTTP code or None), ``field`` and ``message``."""

    def __init__(
        self,
        message: str,
        *,
        status: int | None = None,
        field: str | None = None,
        errors: list[dict[str, Any]] | None = None,
    ):
        super().__init__(message)
        self.message = message
        self.status = status
        self.field = field
        self.errors = errors or []  # every validation error, when the API lists several

    def __str__(self) -> str:
        where = f"{self.field}: " if self.field else ""
        code = f" (HTTP {self.status})" if self.status is not None else ""
        return f"{where}{self.message}{code}"

    def __repr__(self) -> str:
        return (
            f"{type(self).__name__}(status={self.status!r}, field={self.field!r}, "
            f"message={self.message!r})"
        )


class ConfigError(SvrobsError):
    """No API key configured, a key or server URL that cannot be one, or an unreadable
    config file."""


class ConnectionFailed(SvrobsError, ConnectionError):
    """The server could not be reached (or the connection broke mid-response)."""


# what a refused or unresolvable connection most often means: no server there yet
NO_SERVER_HINT = "no server answers there: start one (make run) or set SVROBS_URL"


def unreachable(url: str, exc: Exception) -> ConnectionFailed:
    """``cannot reach URL: <reason>``; with :data:`NO_SERVER_HINT` when the connection
    itself failed (refused, unknown host), not when it timed out or broke."""
    hint = f" ({NO_SERVER_HINT})" if isinstance(exc, httpx.ConnectError) else ""
    return ConnectionFailed(f"cannot reach {url}: {exc}{hint}")


class WaitTimeout(SvrobsError, TimeoutError):
    """:meth:`Client.wait` gave up before the job finished."""


class BadRequest(SvrobsError):
    """HTTP 400."""


class AuthError(SvrobsError):
    """HTTP 401 (missing, unknown, revoked or expired key) or 403."""


class NotFound(SvrobsError):
    """HTTP 404: missing, or another team's (the API does not distinguish)."""


class MethodNotAllowed(SvrobsError):
    """HTTP 405: the server does not offer this operation (an older server)."""


class Conflict(SvrobsError):
    """HTTP 409: e.g. an idempotency key reused with another spec, or cancelling a
    finished job."""


class TooLarge(SvrobsError):
    """HTTP 413: the request body is over the server's limit."""


class ValidationError(SvrobsError):
    """HTTP 422: invalid input; ``field`` names it."""


class RateLimited(SvrobsError):
    """HTTP 429: the key's rate limit, the team's queued-jobs cap, or too many report
    builds, dataset uploads or results streams of the team (or of the server) at once.
    ``retry_after`` is the server's Retry-After in seconds, if it sent one."""

    def __init__(self, message: str, *, retry_after: float | None = None, **kw: Any):
        super().__init__(message, **kw)
        self.retry_after = retry_after


class ServerError(SvrobsError):
    """HTTP 5xx other than 503."""


class Unavailable(ServerError):
    """HTTP 503: the database or the broker is unavailable; retry later."""


_BY_STATUS: dict[int, type[SvrobsError]] = {
    400: BadRequest,
    401: AuthError,
    403: AuthError,
    404: NotFound,
    405: MethodNotAllowed,
    409: Conflict,
    413: TooLarge,
    422: ValidationError,
    429: RateLimited,
    503: Unavailable,
}


def _message(detail: Any) -> str:
    if isinstance(detail, str):
        return detail
    if isinstance(detail, list) and detail and isinstance(detail[0], dict):
        return "; ".join(str(d.get("msg") or d.get("message") or d) for d in detail)
    return "" if detail is None else str(detail)


def _is_html(body: bytes, headers: Mapping[str, str]) -> bool:
    return "html" in headers.get("content-type", "") or body.lstrip()[:1] == b"<"


def _page_text(body: bytes) -> str:
    """The words of an HTML page (no head, scripts or tags), at most 200 characters."""
    import html
    import re

    page = body[:20_000].decode("utf-8", "replace")
    page = re.sub(r"(?is)<(head|script|style)\b.*?</\1\s*>", " ", page)
    words = " ".join(html.unescape(re.sub(r"(?s)<[^>]*>", " ", page)).split())
    return words[:200]


def not_the_api(url: str, status: int, headers: Mapping[str, str]) -> SvrobsError:
    """The error of an answer that is no answer of the API: a redirect, an HTML page or a
    body that is not JSON where the API sends data (``url`` is not the API's address)."""
    if 300 <= status < 400:
        where = headers.get("location")
        what = f"a redirect (HTTP {status})" + (f" to {where}" if where else "")
    elif _is_html(b"", headers):
        what = f"an HTML page (HTTP {status})"
    else:
        kind = headers.get("content-type") or "no content type"
        what = f"HTTP {status} and a body that is not the API's JSON ({kind})"
    return SvrobsError(
        f"{url} is not the svrobs API's address: it answered with {what}", status=status
    )


# The header the API's report page carries (its value: the job's id); a page without
# it is another server's (a proxy's sign-in page, another web app), never saved.
REPORT_HEADER = "X-Svrobs-Report"


def not_a_report(url: str, status: int, headers: Mapping[str, str]) -> SvrobsError:
    """The error of an answer to ``GET /jobs/{id}/report`` without :data:`REPORT_HEADER`:
    its status and content type, and that the server at ``url`` is not svrobs."""
    kind = headers.get("content-type") or "no content type"
    return SvrobsError(
        f"{url} does not look like svrobs: the report request got HTTP {status} ({kind}) "
        f"without the {REPORT_HEADER} header of an svrobs report",
        status=status,
    )


def error_from_response(
    status: int, body: bytes, headers: Mapping[str, str], *, url: str | None = None
) -> SvrobsError:
    """The typed error of an HTTP error response (JSON ``{"detail", "field"}`` when the
    API sent it; the words of an HTML page, e.g. a proxy's, or the start of the body
    otherwise). ``url`` is the server's, named in the message of an HTML page."""
    import json

    field, errors = None, None
    try:
        data = json.loads(body)
    except ValueError:
        data = None
    if isinstance(data, dict) and "detail" in data:
        message = _message(data.get("detail"))
        field = data.get("field") if isinstance(data.get("field"), str) else None
        errors = data.get("errors") if isinstance(data.get("errors"), list) else None
    elif _is_html(body, headers):
        message = (
            f"{url or 'the server'} answered HTTP {status} with an HTML page, not the "
            f"svrobs API's JSON: {_page_text(body)}"
        )
    else:
        message = " ".join(body[:300].decode("utf-8", "replace").split())
    message = message or f"HTTP {status}"
    cls = _BY_STATUS.get(status) or (ServerError if status >= 500 else SvrobsError)
    kw: dict[str, Any] = {"status": status, "field": field, "errors": errors}
    if cls is RateLimited:
        try:
            kw["retry_after"] = float(headers.get("retry-after", ""))
        except (TypeError, ValueError):
            kw["retry_after"] = None
    return cls(message, **kw)
