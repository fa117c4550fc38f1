"""``/docs`` and ``/redoc`` with their scripts served from this server, so that they
load nothing from another host.

Swagger UI's and ReDoc's files come from the fastapi-offline package (served under
``/static-offline-docs``). ``/docs`` starts Swagger UI with ``swagger_init.js``: a
browser signed in to the dashboard tries the API out under its session (reads with
the cookie, writes with the session's CSRF token too; service.api.deps). ReDoc's bundle still draws its sidebar logo
from ``cdn.redoc.ly``: the script is served here with that one URL replaced by an
empty inline SVG (a closed lab network never sees a request to the CDN).
"""

from __future__ import annotations

import html
from functools import cache
from pathlib import Path

import fastapi_offline
from fastapi import FastAPI, Request
from fastapi.openapi.docs import get_redoc_html
from fastapi.responses import HTMLResponse, Response

from service.http.security import INLINE_STYLE_CSP

REDOC_JS = Path(fastapi_offline.__file__).resolve().parent / "static" / "redoc.standalone.js"
CDN_LOGO = "https://cdn.redoc.ly/redoc/logo-mini.svg"
EMPTY_SVG = "data:image/svg+xml,%3Csvg xmlns='http://www.w3.org/2000/svg'/%3E"
SCRIPT_URL = "/docs-assets/redoc.standalone.js"
SWAGGER_INIT = Path(__file__).resolve().parent / "swagger_init.js"
SWAGGER_INIT_URL = "/docs-assets/swagger-init.js"
OFFLINE = "/static-offline-docs"
SWAGGER_PAGE = """<!doctype html>
<html lang="en">
<head>
<meta charset="utf-8">
<meta name="viewport" content="width=device-width, initial-scale=1">
<title>{title}</title>
<link rel="stylesheet" href="{root}{offline}/swagger-ui.css">
<link rel="icon" href="{root}/favicon.ico">
</head>
<body data-openapi="{root}{openapi}">
<p id="docs-session" role="status" hidden
   style="margin:0;padding:.6rem 1rem;background:#eaf6ee;font-family:system-ui,sans-serif"></p>
<div id="swagger-ui"></div>
<script src="{root}{offline}/swagger-ui-bundle.js"></script>
<script src="{root}{init}"></script>
</body>
</html>
"""


@cache
def redoc_script() -> bytes:
    return REDOC_JS.read_bytes().replace(CDN_LOGO.encode(), EMPTY_SVG.encode())


def install_swagger(app: FastAPI, path: str = "/docs") -> None:
    @app.get(path, include_in_schema=False)
    async def swagger_html(request: Request) -> HTMLResponse:
        root = request.scope.get("root_path", "")
        page = SWAGGER_PAGE.format(
            title=html.escape(f"{app.title} - Swagger UI"),
            root=root,
            offline=OFFLINE,
            openapi=app.openapi_url,
            init=SWAGGER_INIT_URL,
        )
        return HTMLResponse(page, headers={"Content-Security-Policy": INLINE_STYLE_CSP})

    @app.get(SWAGGER_INIT_URL, include_in_schema=False)
    async def swagger_init() -> Response:
        return Response(SWAGGER_INIT.read_bytes(), media_type="application/javascript")


def install_redoc(app: FastAPI, path: str = "/redoc") -> None:
    @app.get(path, include_in_schema=False)
    async def redoc_html(request: Request) -> HTMLResponse:
        root = request.scope.get("root_path", "")
        page = get_redoc_html(
            openapi_url=f"{root}{app.openapi_url}",
            title=f"{app.title} - ReDoc",
            redoc_js_url=f"{root}{SCRIPT_URL}",
            redoc_favicon_url="data:,",
            with_google_fonts=False,
        )
        # ReDoc inserts its styles and runs a web worker from a blob: URL
        page.headers["Content-Security-Policy"] = INLINE_STYLE_CSP + "; worker-src 'self' blob:"
        return page

    @app.get(SCRIPT_URL, include_in_schema=False)
    async def redoc_js() -> Response:
        return Response(
            redoc_script(),
            media_type="application/javascript",
            headers={"Cache-Control": "public, max-age=86400"},
        )
