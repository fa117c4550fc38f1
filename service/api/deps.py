"""FastAPI dependencies: settings, DB sessions, the caller's key/team, rate limit,
the unit publisher, the broker check, the caller's job. Tests replace
``app.state.session_factory`` and ``app.state.publisher``, and override
:func:`get_broker_check` with ``app.dependency_overrides``."""

from __future__ import annotations

from collections.abc import AsyncIterator, Callable, Sequence
from dataclasses import dataclass
from typing import Annotated

import anyio
from fastapi import Depends, HTTPException, Path, Request
from sqlalchemy import select
from sqlalchemy.orm import Session, joinedload

from service.api.errors import FieldHTTPException
from service.config import Settings
from service.db.accounts import authenticate
from service.db.models import ApiKey, Job
from service.web.session import session_key

SessionFactory = Callable[..., Session]  # factory(write: bool) -> Session
Publisher = Callable[[Sequence[int]], list[int]]
BrokerCheck = Callable[[], None]  # raises when the broker does not answer

MAX_ID = 2_147_483_647  # ids are 32-bit integers on every dialect
JobId = Annotated[int, Path(ge=1, le=MAX_ID, description="a job id of the caller's team")]


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


@dataclass(frozen=True)
class Caller:
    key_id: int
    team_id: int
    user_id: int | None
    is_admin: bool


def _unauthorized(detail: str) -> HTTPException:
    return HTTPException(401, detail, headers={"WWW-Authenticate": "Bearer"})


def caller_of(request: Request, session: Session, find: Callable[[Session], ApiKey | None]):
    """The caller of the key ``find(session)`` returns (None: not signed in). A writing
    request looks the key up in a short reading session of its own, so that its own
    session takes the SQLite write lock (BEGIN IMMEDIATE) only when the route starts
    writing, not for the key lookup."""
    own = None
    if is_write(request):
        session = own = request.app.state.session_factory(False)
    try:
        key = find(session)
        if key is None:
            return None
        return Caller(
            key_id=key.id,
            team_id=key.team_id,
            user_id=key.user_id,
            is_admin=bool(key.user is not None and key.user.is_admin),
        )
    finally:
        if own is not None:
            own.close()


def rate_limit(request: Request, caller: Caller) -> None:
    allowed, retry = request.app.state.rate_limiter.allow(caller.key_id)
    if not allowed:
        raise HTTPException(
            429,
            "rate limit exceeded for this API key",
            headers={"Retry-After": str(max(1, int(retry + 0.999)))},
        )


def get_caller(request: Request, session: Annotated[Session, Depends(get_db)]) -> Caller:
    """The bearer key's caller. A reading request (GET) without an Authorization
    header may instead carry the web UI's session cookie (service.web.session), so
    that a signed-in browser opens reports and downloads; writes need the key."""
    header = request.headers.get("authorization", "")
    scheme, _, token = header.partition(" ")
    if not header and not is_write(request):
        caller = caller_of(request, session, lambda s: session_key(request, s))
        if caller is None:
            raise _unauthorized("missing API key: send 'Authorization: Bearer <key>'")
    elif scheme.lower() != "bearer" or not token.strip():
        raise _unauthorized("missing API key: send 'Authorization: Bearer <key>'")
    else:
        caller = caller_of(request, session, lambda s: authenticate(s, token.strip()))
        if caller is None:
            raise _unauthorized("invalid, revoked or expired API key")
    rate_limit(request, caller)
    return caller


async def clean_query_text(request: Request) -> None:
    """422 for a query parameter or an Idempotency-Key holding a NUL character (which a
    PostgreSQL text column cannot hold: it would be a 500 there and a silent miss on
    SQLite). Registered on every /api/v1 router."""
    items = list(request.query_params.multi_items())
    key = request.headers.get("idempotency-key")
    for name, value in items + ([("Idempotency-Key", key)] if key is not None else []):
        if "\x00" in name or "\x00" in value:
            raise FieldHTTPException(
                422, "must not contain NUL (\\u0000) characters", name.replace("\x00", "")
            )


def team_job(session: Session, team_id: int, job_id: int) -> Job:
    """The caller's job, or 404 (another team's job is indistinguishable from none)."""
    q = select(Job).where(Job.id == job_id, Job.team_id == team_id)
    job = session.scalar(q.options(joinedload(Job.user)))  # one query with the owner
    if job is None:
        raise HTTPException(404, f"job {job_id} not found")
    return job


DB = Annotated[Session, Depends(get_db)]
CurrentCaller = Annotated[Caller, Depends(get_caller)]
SettingsDep = Annotated[Settings, Depends(get_settings_dep)]
PublisherDep = Annotated[Publisher, Depends(get_publisher)]
BrokerCheckDep = Annotated[BrokerCheck, Depends(get_broker_check)]
SessionFactoryDep = Annotated[SessionFactory, Depends(get_session_factory)]
