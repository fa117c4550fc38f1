"""FastAPI dependencies of both HTTP front ends: settings, DB sessions, the unit
publisher, the broker check, the caller of a request and its rate limit, the
throttle of failed authentications, the report builds, a submission. Tests replace ``app.state.session_factory`` and ``app.state.publisher``,
and override :func:`get_broker_check` with ``app.dependency_overrides``."""

from __future__ import annotations

from collections.abc import AsyncIterator, Callable
from typing import Annotated

import anyio
from fastapi import BackgroundTasks, Depends, Request
from sqlalchemy.orm import Session

from service.config import Settings
from service.db.models import ApiKey
from service.http.auth_throttle import client_address
from svrobs_lab.auth import Caller, resolve_caller
from svrobs_lab.dispatch import Publisher, SessionFactory
from svrobs_lab.errors import RateLimited
from svrobs_lab.jobs import Submission
from svrobs_lab.report_builds import ReportBuilds

BrokerCheck = Callable[[], None]  # raises when the broker does not answer


async def get_settings_dep(request: Request) -> Settings:
    return request.app.state.settings


async def get_session_factory(request: Request) -> SessionFactory:
    return request.app.state.session_factory


def is_write(request: Request) -> bool:
    return request.method not in ("GET", "HEAD", "OPTIONS")


async def get_db(request: Request) -> AsyncIterator[Session]:
    """One session per request: a writing session for POST/PUT/PATCH/DELETE, a reading
    one (deferred BEGIN on SQLite) otherwise. Routes commit explicitly. Making a
    session does no I/O (it connects lazily, in the route's thread), so only the
    close (a ROLLBACK) is sent to the threadpool: one hop per request, not two."""
    session = request.app.state.session_factory(is_write(request))
    try:
        yield session
    finally:
        # close() rolls back what is uncommitted. Outside the shared threadpool limit
        # (a new limiter per call, as FastAPI runs a dependency's exit): requests
        # waiting in the threadpool for a pooled connection must never keep a
        # finished request from giving its own back.
        await anyio.to_thread.run_sync(session.close, limiter=anyio.CapacityLimiter(1))


async def get_publisher(request: Request) -> Publisher:
    return request.app.state.publisher


async def get_broker_check(request: Request) -> BrokerCheck:
    """Raises unless the broker of the app's Celery app answers (``/readyz``)."""
    from service.broker import check_broker

    broker, timeout = request.app.state.broker, request.app.state.settings.BROKER_TIMEOUT
    return lambda: check_broker(broker.get_celery(), timeout=timeout)


def caller_of(
    request: Request, session: Session, find: Callable[[Session], ApiKey | None]
) -> Caller | None:
    """The caller of the key ``find(session)`` returns (None: not signed in); a writing
    request looks the key up in a reading session of its own
    (:func:`svrobs_lab.auth.resolve_caller`)."""
    reader = (lambda: request.app.state.session_factory(False)) if is_write(request) else None
    return resolve_caller(session, find, reader=reader)


def rate_limit(request: Request, caller: Caller) -> None:
    """RateLimited over the key's SVROBS_RATE_LIMIT_PER_MINUTE."""
    allowed, retry = request.app.state.rate_limiter.allow(caller.key_id)
    if not allowed:
        raise RateLimited(
            "rate limit exceeded for this API key", retry_after=max(1, int(retry + 0.999))
        )


def check_auth_throttle(request: Request) -> None:
    """RateLimited while the client's address has used up its failed authentications
    (:mod:`service.http.auth_throttle`)."""
    request.app.state.auth_throttle.check(client_address(request))


def auth_failed(request: Request) -> None:
    """Count a failed authentication (a bad key) of the client's address."""
    request.app.state.auth_throttle.failed(client_address(request))


async def get_report_builds(request: Request) -> ReportBuilds:
    return request.app.state.report_builds


def submission_of(
    request: Request, session: Session, caller: Caller, background: BackgroundTasks
) -> Submission:
    """The caller's :class:`~svrobs_lab.jobs.Submission` in this request; publishing
    runs after the response (FastAPI's background tasks)."""
    return Submission(
        session=session,
        caller=caller,
        settings=request.app.state.settings,
        publisher=request.app.state.publisher,
        session_factory=request.app.state.session_factory,
        later=background.add_task,
    )


DB = Annotated[Session, Depends(get_db)]
SettingsDep = Annotated[Settings, Depends(get_settings_dep)]
PublisherDep = Annotated[Publisher, Depends(get_publisher)]
BrokerCheckDep = Annotated[BrokerCheck, Depends(get_broker_check)]
SessionFactoryDep = Annotated[SessionFactory, Depends(get_session_factory)]
ReportBuildsDep = Annotated[ReportBuilds, Depends(get_report_builds)]
