"""``/redoc`` with ReDoc's script served from this server, patched so that it loads
nothing from another host.

Swagger UI (``/docs``) and ReDoc's files come from the fastapi-offline package
(served under ``/static-offline-docs``). ReDoc's bundle still draws its sidebar logo
from ``cdn.redoc.ly``: the script is served here with that one URL replaced by an
empty inline SVG (a closed lab network never sees a request to the CDN).
"""

from __future__ import annotations

from functools import cache
from pathlib import Path

import fastapi_offline
from fastapi import FastAPI, Request
from fastapi.openapi.docs import get_redoc_html
from fastapi.responses import HTMLResponse, Response

REDOC_JS = Path(fastapi_offline.__file__).resolve().parent / "static" / "redoc.standalone.js"
CDN_LOGO = "https://cdn.redoc.ly/redoc/logo-mini.svg"
EMPTY_SVG = "data:image/svg+xml,%3Csvg xmlns='http://www.w3.org/2000/svg'/%3E"
SCRIPT_URL = "/docs-assets/redoc.standalone.js"


@cache
def redoc_script() -> bytes:
    return REDOC_JS.read_bytes().replace(CDN_LOGO.encode(), EMPTY_SVG.encode())


def install_redoc(app: FastAPI, path: str = "/redoc") -> None:
    @app.get(path, include_in_schema=False)
    async def redoc_html(request: Request) -> HTMLResponse:
        root = request.scope.get("root_path", "")
        return get_redoc_html(
            openapi_url=f"{root}{app.openapi_url}",
            title=f"{app.title} - ReDoc",
            redoc_js_url=f"{root}{SCRIPT_URL}",
            redoc_favicon_url="data:,",
            with_google_fonts=False,
        )

    @app.get(SCRIPT_URL, include_in_schema=False)
    async def redoc_js() -> Response:
        return Response(
            redoc_script(),
            media_type="application/javascript",
            headers={"Cache-Control": "public, max-age=86400"},
        )
