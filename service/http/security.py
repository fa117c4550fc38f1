"""The security headers of every response (docs/security.md#security-headers), set once
for the whole app by :class:`SecurityHeaders`, an ASGI middleware
(``service.app.create_app`` adds it).

Every response gets ``X-Content-Type-Options: nosniff`` and
``Referrer-Policy: same-origin``; every HTML response the dashboard's
Content-Security-Policy (:data:`CSP`: scripts, styles, images and requests from
this server only, no framing) unless its route set one. The report pages and the
API docs set :data:`INLINE_STYLE_CSP`: the same policy, with the inline
stylesheet a self-contained report carries allowed (still no inline script).

A download names its file with :func:`attachment`, whatever the name holds.
"""

from __future__ import annotations

import re
from urllib.parse import quote

from svrobs_core.text import UNPRINTABLE

CSP = (
    "default-src 'self'; script-src 'self'; style-src 'self'; img-src 'self' data:; "
    "connect-src 'self'; font-src 'self'; object-src 'none'; base-uri 'none'; "
    "form-action 'self'; frame-ancestors 'none'"
)
INLINE_STYLE_CSP = CSP.replace("style-src 'self';", "style-src 'self' 'unsafe-inline';")
ALWAYS = {"x-content-type-options": "nosniff", "referrer-policy": "same-origin"}
CSP_HEADER = "content-security-policy"


class SecurityHeaders:
    """Adds :data:`ALWAYS` to every HTTP response and :data:`CSP` to HTML ones, where
    the route did not set them."""

    def __init__(self, app):
        self.app = app

    async def __call__(self, scope, receive, send):
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return

        async def send_with_headers(message):
            if message["type"] == "http.response.start":
                headers = list(message.get("headers", []))
                have = {k.decode("latin-1").lower(): v for k, v in headers}
                extra = {k: v for k, v in ALWAYS.items() if k not in have}
                ctype = have.get("content-type", b"").decode("latin-1").lower()
                if ctype.startswith("text/html") and CSP_HEADER not in have:
                    extra[CSP_HEADER] = CSP
                if extra:
                    headers += [(k.encode(), v.encode()) for k, v in extra.items()]
                    message = {**message, "headers": headers}
            await send(message)

        await self.app(scope, receive, send_with_headers)


_PATH_SEPARATORS = re.compile(r"[/\\]")  # a file name holds no folder
# the characters of the ASCII fallback (no quote, backslash, comma, semicolon or %)
_NOT_FALLBACK = re.compile(r"[^A-Za-z0-9 ._()+=@-]")


def attachment(filename: str) -> str:
    """The ``Content-Disposition`` of a download saved as ``filename`` (a user's name:
    any text). RFC 6266: ``filename*`` holds the name in UTF-8, percent-encoded (RFC
    5987), and ``filename`` an ASCII fallback for older clients. The characters a name
    may not hold (svrobs_core.text: CR and LF, so no header can be split) and path
    separators become ``_``; leading and trailing dots and spaces go (no ``..``); an
    empty name is ``download`` (docs/security.md#names-in-downloads-and-pages)."""
    name = _PATH_SEPARATORS.sub("_", UNPRINTABLE.sub("_", filename)).strip(". ") or "download"
    fallback = _NOT_FALLBACK.sub("_", name)
    return f"attachment; filename=\"{fallback}\"; filename*=UTF-8''{quote(name, safe='')}"
