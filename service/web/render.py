"""Templates, the pages' security headers and the web UI's error pages.

Every page is sent with a Content-Security-Policy that allows scripts, styles,
images and requests from this server only: no page can load anything from another
host, even by mistake.
"""

from __future__ import annotations

import json
from datetime import UTC, datetime
from html import escape
from pathlib import Path
from urllib.parse import quote, urlsplit
from zoneinfo import ZoneInfo, ZoneInfoNotFoundError

from fastapi import Request
from fastapi.responses import HTMLResponse, RedirectResponse, Response
from jinja2 import Environment, FileSystemLoader, select_autoescape

from service.http.security import CSP, INLINE_STYLE_CSP
from service.web import fields
from svrobs_core.report.columns import fmt_num

HERE = Path(__file__).resolve().parent
TEMPLATES = HERE / "templates"
STATIC = HERE / "static"

PAGE_HEADERS = {
    "Content-Security-Policy": CSP,
    "X-Content-Type-Options": "nosniff",
    "Referrer-Policy": "same-origin",
    "Cache-Control": "no-store",
}


def _when(value: datetime | None) -> str:
    return value.strftime("%Y-%m-%d %H:%M:%S UTC") if value else "–"


def _in_zone(value: datetime | None, zone: str) -> str:
    """A time in a schedule's own time zone, with UTC beside it."""
    if value is None:
        return "–"
    try:
        local = value.astimezone(ZoneInfo(zone))
    except (ZoneInfoNotFoundError, ValueError):
        return _when(value)
    if local.utcoffset() == value.utcoffset():
        return _when(value)
    return f"{local:%Y-%m-%d %H:%M} {zone} ({value.astimezone(UTC):%H:%M} UTC)"


def _seconds(value) -> str:
    if value is None:
        return "–"
    value = float(value)
    return f"{value:.2f} s" if value < 120 else f"{value / 60:.1f} min"


env = Environment(
    loader=FileSystemLoader(TEMPLATES),
    autoescape=select_autoescape(["html"]),
    trim_blocks=True,
    lstrip_blocks=True,
)
env.filters["when"] = _when
env.filters["num"] = lambda v, digits=4: fmt_num(v, digits)
env.filters["seconds"] = _seconds
env.filters["in_zone"] = _in_zone
env.filters["pretty"] = lambda v: json.dumps(v, indent=2, sort_keys=False, allow_nan=False)
env.filters["tojson_attr"] = lambda v: json.dumps(v, separators=(",", ":"))
env.filters["label"] = fields.label
env.filters["field_title"] = fields.title
env.filters["coord"] = lambda v, field: fields.coordinate(field, v)  # "estimate" or None
env.globals["glossary_json"] = json.dumps(fields.as_json(), separators=(",", ":"))
env.globals["utcnow"] = lambda: datetime.now(UTC)


def with_back_link(report_html: str, href: str, text: str) -> str:
    """A stored report page with a link back to the dashboard at its top and the
    report in the page's ``<main>`` landmark (the report itself is built once and
    knows nothing of where it is shown)."""
    link = f'<p><a href="{escape(href)}" id="back-link">{escape(text)}</a></p>'
    head, sep, rest = report_html.partition("<body>")
    if not sep:
        return link + report_html
    body, end, tail = rest.rpartition("</body>")
    if not end:
        body, tail = rest, ""
    return f'{head}{sep}{link}<main id="main">{body}</main>{end}{tail}'


# a stored report carries its stylesheet inline (service.http.security)
REPORT_HEADERS = {**PAGE_HEADERS, "Content-Security-Policy": INLINE_STYLE_CSP}


def render(request: Request, template: str, status: int = 200, **context) -> HTMLResponse:
    """A page (or an htmx partial) from ``templates/``, with the security headers.
    ``viewer`` (service.web.deps.Viewer) in the context fills the header bar."""
    html = env.get_template(template).render(request=request, **context)
    return HTMLResponse(html, status_code=status, headers=PAGE_HEADERS)


class WebError(Exception):
    """An error page: 403 (CSRF), 404 (not this team's, or missing), 409, 410, 413, 422, 429,
    500, 503."""

    def __init__(self, status: int, message: str, *, title: str | None = None):
        super().__init__(message)
        self.status = status
        self.message = message
        self.title = title or {
            403: "Forbidden",
            404: "Not found",
            409: "Conflict",
            410: "Gone",
            413: "Too large",
            422: "Invalid input",
            429: "Too many requests",
            500: "Server error",
            503: "Service unavailable",
        }.get(status, "Error")


class SignInRequired(Exception):
    """No valid session: pages redirect to /login, htmx requests get HX-Redirect."""


def login_url(request: Request) -> str:
    """/login, coming back to this page (for htmx, the page it was polling from)."""
    current = request.headers.get("hx-current-url")
    if current:
        parts = urlsplit(current)
        path = parts.path + (f"?{parts.query}" if parts.query else "")
    else:
        path = request.url.path + (f"?{request.url.query}" if request.url.query else "")
    return "/login" if path in ("/", "/login") else f"/login?next={quote(path, safe='')}"


async def web_error_page(request: Request, exc: WebError) -> Response:
    return render(request, "error.html", status=exc.status, error=exc, viewer=None)


async def sign_in_redirect(request: Request, exc: SignInRequired) -> Response:
    if request.headers.get("hx-request"):
        return Response(status_code=401, headers={"HX-Redirect": login_url(request)})
    return RedirectResponse(login_url(request), status_code=303)


def safe_next(target: str | None) -> str:
    """Only a path on this server (no scheme, no host, no ``//``) is followed."""
    if (
        not target
        or not target.startswith("/")
        or target.startswith("//")
        or any(c == "\\" or c.isspace() or not c.isprintable() for c in target)
    ):
        return "/jobs"  # browsers drop tabs and newlines: "/\t/host" would be "//host"
    return target
