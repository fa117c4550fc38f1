"""The FastAPI application: ``app`` for uvicorn, ``create_app(settings)`` for tests.

Errors become JSON responses in one place, :mod:`service.api.errors` (never a
traceback).
"""

from __future__ import annotations

from fastapi import Depends, FastAPI
from fastapi_offline import FastAPIOffline

from service.api.deps import clean_query_text
from service.api.docs import install_redoc
from service.api.errors import error_response, install_error_handlers
from service.api.query_params import reject_unknown_query
from service.api.ratelimit import RateLimiter
from service.broker import BrokerPublisher
from service.config import Settings, get_settings
from service.logging_config import configure_logging
from service.web import mount_web

API_PREFIX = "/api/v1"


class BodyLimitMiddleware:
    """413 for a request body over ``max_bytes`` (declared Content-Length or streamed)."""

    def __init__(self, app, max_bytes: int):
        self.app = app
        self.max_bytes = max_bytes

    async def __call__(self, scope, receive, send):
        if scope["type"] != "http" or scope["method"] in ("GET", "HEAD", "OPTIONS", "DELETE"):
            return await self.app(scope, receive, send)
        if scope["path"] == API_PREFIX + "/datasets":  # streamed, under its own limit
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


def create_app(settings: Settings | None = None) -> FastAPI:
    settings = settings or get_settings()
    configure_logging(settings)
    # /docs and /redoc with Swagger UI's and ReDoc's files served from the
    # fastapi-offline package under /static-offline-docs (closed lab networks)
    app: FastAPI = FastAPIOffline(
        title="svrobs",
        version="0.1.0",
        description=(
            "SVR-based observer design experiments as a service: submit a SPEC section 10 "
            "spec, watch its progress, query, compare and schedule results. "
            "Authenticate with `Authorization: Bearer <api key>`."
        ),
        openapi_url="/openapi.json",
        docs_url="/docs",
        redoc_url=None,  # service.api.docs: ReDoc's script without its CDN logo
        favicon_url="data:,",
        swagger_ui_parameters={"validatorUrl": None, "persistAuthorization": True},
    )
    install_redoc(app)
    app.state.settings = settings
    app.state.session_factory = _default_session_factory(settings)
    # the app's Celery app, made on first use; tests replace the publisher
    app.state.broker = BrokerPublisher(lambda: app.state.settings)
    app.state.publisher = app.state.broker
    app.state.rate_limiter = RateLimiter(settings.RATE_LIMIT_PER_MINUTE)

    install_error_handlers(app)

    from service.api.routes import health, jobs, presets, reports, results, schedules, shares
    from service.api.routes.datasets import router as datasets_router

    query_rules = [Depends(clean_query_text), Depends(reject_unknown_query)]
    app.include_router(health.router, dependencies=query_rules[1:])
    for module in (jobs, results, presets, reports, schedules, shares):
        app.include_router(module.router, prefix=API_PREFIX, dependencies=query_rules)
    app.include_router(datasets_router, prefix=API_PREFIX, dependencies=query_rules)
    app.add_middleware(BodyLimitMiddleware, max_bytes=settings.MAX_BODY_BYTES)
    mount_web(app)  # the web UI's pages under /
    return app


def __getattr__(name: str):
    # `app` is built on first access so that importing this module never reads the env
    if name == "app":
        global app
        app = create_app()
        return app
    raise AttributeError(name)
