"""The one FastAPI application: the REST API (:mod:`service.api`) and the web UI
(:mod:`service.web`) mounted side by side. ``app`` for uvicorn
(``uvicorn service.app:app``), ``create_app(settings)`` for tests.

The app's state is set here, for both: the settings, the DB session factory, the
unit publisher (the app's Celery app, made on first use; tests replace it), the
rate limiter, the throttle of failed authentications, the report builds; the
security headers of every response (:mod:`service.http.security`). An application error
(:class:`svrobs_lab.errors.LabError`), a request that failed validation, the
framework's HTTP errors (no such path) and the server's own (the database down, a bug)
are each answered once: JSON under /api and for the health routes
(:mod:`service.api.errors`), the web's error page elsewhere (:mod:`service.web.errors`);
nothing becomes a traceback.
"""

from __future__ import annotations

from collections.abc import AsyncIterator
from contextlib import asynccontextmanager

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi_offline import FastAPIOffline
from sqlalchemy.exc import DBAPIError, OperationalError
from sqlalchemy.exc import TimeoutError as PoolTimeout
from starlette.exceptions import HTTPException as StarletteHTTPException

from service.api.errors import error_response, install_error_handlers
from service.api.mount import API_PREFIX, mount_api
from service.api.ratelimit import RateLimiter
from service.broker import BrokerPublisher
from service.config import Settings, get_settings
from service.http.auth_throttle import AuthThrottle
from service.http.body_limit import BodyLimitMiddleware
from service.http.errors import ErrorHandler
from service.http.query_text import EmptyFieldsAbsent
from service.http.security import SecurityHeaders
from service.logging_config import configure_logging
from service.web import mount_web
from service.web.errors import (
    error_page,
    http_error_page,
    lab_error_page,
    server_error_page,
    validation_error_page,
)
from svrobs_core.errors import SpecError
from svrobs_lab import figure_pool
from svrobs_lab.datasets.upload_slots import UploadSlots
from svrobs_lab.errors import LabError
from svrobs_lab.report_builds import ReportBuilds

# the errors a web page answers with the web's error page (the API: JSON)
PAGE_ERRORS: dict[type[Exception], ErrorHandler] = {
    LabError: lab_error_page,
    SpecError: lab_error_page,
    RequestValidationError: validation_error_page,
    StarletteHTTPException: http_error_page,
    OperationalError: server_error_page,
    PoolTimeout: server_error_page,
    DBAPIError: server_error_page,
    Exception: server_error_page,
}


def _default_session_factory(settings: Settings):
    from service.db.session import get_sessionmaker

    # made now, not on the first request: creating an engine imports its dialect, and
    # sessions are opened on the event loop (see service.http.deps.get_db)
    makers = {
        write: get_sessionmaker(settings.DATABASE_URL, write=write) for write in (True, False)
    }

    def factory(write: bool = True):
        return makers[write]()

    return factory


def _is_api_path(path: str) -> bool:
    return path.startswith(API_PREFIX + "/") or path in ("/healthz", "/readyz")


def _is_api(request: Request) -> bool:
    return _is_api_path(request.url.path)


def _refuse(scope: dict, status: int, message: str):
    """A request refused before it reached a route: JSON for the API, else the page."""
    if _is_api_path(scope["path"]):
        return error_response(status, message)
    return error_page(Request(scope), status, message)


def _is_page_path(path: str) -> bool:
    return not _is_api_path(path)


@asynccontextmanager
async def _lifespan(app: FastAPI) -> AsyncIterator[None]:
    yield
    # the report figures' helpers stopped and their pool freed now: uvicorn ends the
    # process by its stop signal once this is done, without the exit handlers that
    # would free it (svrobs_lab.figure_pool)
    figure_pool.close()


def create_app(settings: Settings | None = None) -> FastAPI:
    settings = settings or get_settings()
    configure_logging(settings)
    # /docs and /redoc with Swagger UI's and ReDoc's files served from the
    # fastapi-offline package under /static-offline-docs (closed lab networks)
    app: FastAPI = FastAPIOffline(
        title="svrobs",
        version="0.1.0",
        description=(
            "SVR-based observer design experiments as a service: submit a spec "
            "(docs/spec.md#spec-fields), watch its progress, query, compare and schedule results. "
            "Authenticate with `Authorization: Bearer <api key>`."
        ),
        openapi_url="/openapi.json",
        docs_url=None,  # service.api.docs: Swagger UI under the web session
        redoc_url=None,  # service.api.docs: ReDoc's script without its CDN logo
        favicon_url="data:,",
        lifespan=_lifespan,
    )
    app.state.settings = settings
    figure_pool.configure(settings.REPORT_RENDER_PROCESSES)
    app.state.session_factory = _default_session_factory(settings)
    app.state.broker = BrokerPublisher(lambda: app.state.settings)
    app.state.publisher = app.state.broker
    app.state.rate_limiter = RateLimiter(settings.RATE_LIMIT_PER_MINUTE)
    app.state.auth_throttle = AuthThrottle(settings.AUTH_FAILURES_PER_MINUTE)
    app.state.report_builds = ReportBuilds(
        per_team=settings.REPORT_BUILDS_PER_TEAM,
        waiters_per_team=settings.REPORT_WAITERS_PER_TEAM,
    )
    app.state.upload_slots = UploadSlots(
        per_team=settings.UPLOADS_PER_TEAM, at_once=settings.UPLOADS_AT_ONCE
    )
    # a body over SVROBS_MAX_BODY_BYTES: 413 before any route (service.http.body_limit)
    app.add_middleware(BodyLimitMiddleware, max_bytes=settings.MAX_BODY_BYTES, respond=_refuse)
    # nosniff, Referrer-Policy and (HTML) the CSP on every response (service.http.security)
    app.add_middleware(SecurityHeaders)
    # a page's query: a form's empty field (``at=``) is no value
    app.add_middleware(EmptyFieldsAbsent, applies=_is_page_path)

    install_error_handlers(app, pages=PAGE_ERRORS, is_api=_is_api)
    mount_api(app)  # /api/v1, /healthz, /readyz, /docs
    mount_web(app)  # the web UI's pages under /
    return app


app: FastAPI  # declared only: __getattr__ builds it on first access


def __getattr__(name: str):
    # `app` is built on first access so that importing this module never reads the env
    if name == "app":
        global app
        app = create_app()
        return app
    raise AttributeError(name)
