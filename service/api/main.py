"""The FastAPI application: ``app`` for uvicorn, ``create_app(settings)`` for tests.

Errors are always JSON ``{"detail": ..., "field": ...}``: 422 for a bad spec or
body (naming the field), 413 for a body over SVROBS_MAX_BODY_BYTES, 401/404/
409/429 as usual, 503 when the database is unreachable (never a traceback).
"""

from __future__ import annotations

import json
import logging
from typing import Any

from fastapi import Depends, FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from sqlalchemy.exc import DBAPIError, OperationalError
from sqlalchemy.exc import TimeoutError as PoolTimeout
from starlette.exceptions import HTTPException as StarletteHTTPException

from service.api.deps import clean_query_text
from service.api.ratelimit import RateLimiter
from service.config import Settings, get_settings
from svrobs_core.errors import SpecError

log = logging.getLogger(__name__)

API_PREFIX = "/api/v1"
BODY_PARSE_ERROR = "There was an error parsing the body"  # fastapi.routing's 400 detail


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
    status: int, detail: Any, field: str | None = None, headers: dict | None = None, **extra
) -> JSONResponse:
    return _ErrorJSONResponse(
        {"detail": detail, "field": field, **extra}, status_code=status, headers=headers
    )


def _loc_to_field(loc) -> str | None:
    parts = [p for p in loc if p not in ("body", "query", "path", "header")]
    out = ""
    for p in parts:
        if isinstance(p, int):
            out += f"[{p}]"
        else:
            out += f".{p}" if out else str(p)
    return out or None


class BodyLimitMiddleware:
    """413 for a request body over ``max_bytes`` (declared Content-Length or streamed)."""

    def __init__(self, app, max_bytes: int):
        self.app = app
        self.max_bytes = max_bytes

    async def __call__(self, scope, receive, send):
        if scope["type"] != "http" or scope["method"] in ("GET", "HEAD", "OPTIONS", "DELETE"):
            return await self.app(scope, receive, send)
        too_big = error_response(
            413, f"request body over {self.max_bytes} bytes (SVROBS_MAX_BODY_BYTES)"
        )
        for name, value in scope.get("headers", []):
            if name == b"content-length":
                try:
                    if int(value) > self.max_bytes:
                        return await too_big(scope, receive, send)
                except ValueError:
                    return await error_response(400, "bad Content-Length")(scope, receive, send)
        # Read (at most max_bytes + 1) and replay, so a lying or absent length is caught too.
        chunks, size, more = [], 0, True
        while more:
            message = await receive()
            if message["type"] == "http.disconnect":
                return
            body = message.get("body", b"")
            size += len(body)
            if size > self.max_bytes:
                return await too_big(scope, receive, send)
            chunks.append(body)
            more = message.get("more_body", False)
        data = b"".join(chunks)
        sent = False

        async def replay():
            nonlocal sent
            if not sent:
                sent = True
                return {"type": "http.request", "body": data, "more_body": False}
            return await receive()

        await self.app(scope, replay, send)


def _default_session_factory(settings: Settings):
    from service.db.session import get_sessionmaker

    # made now, not on the first request: creating an engine imports its dialect, and
    # sessions are opened on the event loop (see deps.get_db)
    makers = {
        write: get_sessionmaker(settings.DATABASE_URL, write=write) for write in (True, False)
    }

    def factory(write: bool = True):
        return makers[write]()

    return factory


def _default_publisher(app: FastAPI):
    from service.broker import BrokerPublisher

    return BrokerPublisher(lambda: app.state.settings)


def create_app(settings: Settings | None = None) -> FastAPI:
    settings = settings or get_settings()
    app = FastAPI(
        title="svrobs",
        version="0.1.0",
        description=(
            "SVR-based observer design experiments as a service: submit a SPEC section 10 "
            "spec, watch its progress, query, compare and schedule results. "
            "Authenticate with `Authorization: Bearer <api key>`."
        ),
        openapi_url="/openapi.json",
        docs_url="/docs",
        redoc_url="/redoc",
    )
    app.state.settings = settings
    app.state.session_factory = _default_session_factory(settings)
    app.state.publisher = _default_publisher(app)
    app.state.rate_limiter = RateLimiter(settings.RATE_LIMIT_PER_MINUTE)

    @app.exception_handler(SpecError)
    async def _spec_error(request: Request, exc: SpecError):
        return error_response(422, exc.message, exc.field)

    @app.exception_handler(RequestValidationError)
    async def _validation_error(request: Request, exc: RequestValidationError):
        errors = exc.errors()
        first = errors[0] if errors else {}
        field = _loc_to_field(first.get("loc", ()))
        msg = first.get("msg", "invalid request")
        if first.get("type") == "extra_forbidden":
            msg = "unknown field"
        clean = [
            {
                "field": _loc_to_field(e.get("loc", ())),
                "message": e.get("msg"),
                "type": e.get("type"),
            }
            for e in errors
        ]
        return error_response(422, msg, field, errors=clean)

    @app.exception_handler(StarletteHTTPException)
    async def _http_error(request: Request, exc: StarletteHTTPException):
        field = getattr(exc, "field", None)
        if exc.status_code == 400 and exc.detail == BODY_PARSE_ERROR:
            # FastAPI's 400 for a body it cannot decode (not UTF-8, nested too deep):
            # a bad body is a 422 naming the body, like malformed JSON.
            return error_response(422, "the request body is not valid JSON (UTF-8)", "body")
        return error_response(exc.status_code, exc.detail, field, headers=exc.headers)

    @app.exception_handler(OperationalError)
    async def _db_down(request: Request, exc: OperationalError):
        log.warning("database unavailable: %s", exc.orig if hasattr(exc, "orig") else exc)
        return error_response(
            503, "database unavailable; retry later", headers={"Retry-After": "5"}
        )

    @app.exception_handler(PoolTimeout)
    async def _db_busy(request: Request, exc: PoolTimeout):
        log.warning("no database connection free: %s", exc)
        return error_response(503, "database busy; retry later", headers={"Retry-After": "1"})

    @app.exception_handler(DBAPIError)
    async def _db_error(request: Request, exc: DBAPIError):
        if exc.connection_invalidated:
            return error_response(
                503, "database connection lost; retry later", headers={"Retry-After": "5"}
            )
        log.exception("database error")
        return error_response(500, "internal database error")

    @app.exception_handler(Exception)
    async def _internal(request: Request, exc: Exception):
        log.exception("unhandled error")
        return error_response(500, "internal server error")

    from service.api.routes import health, jobs, presets, reports, results, schedules

    app.include_router(health.router)
    for module in (jobs, results, presets, reports, schedules):
        app.include_router(
            module.router, prefix=API_PREFIX, dependencies=[Depends(clean_query_text)]
        )
    app.add_middleware(BodyLimitMiddleware, max_bytes=settings.MAX_BODY_BYTES)
    return app


def __getattr__(name: str):
    # `app` is built on first access so that importing this module never reads the env
    if name == "app":
        global app
        app = create_app()
        return app
    raise AttributeError(name)
