"""FastAPI dependencies: settings, DB sessions, the caller's key/team, rate limit,
the unit publisher. Tests replace ``app.state.session_factory`` and
``app.state.publisher`` (or use ``app.dependency_overrides``)."""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from typing import Annotated

from fastapi import Depends, HTTPException, Request
from sqlalchemy.orm import Session

from service.auth import authenticate
from service.config import Settings

SessionFactory = Callable[..., Session]  # factory(write: bool) -> Session
Publisher = Callable[[Sequence[int]], list[int]]


async def get_settings_dep(request: Request) -> Settings:
    return request.app.state.settings


async def get_session_factory(request: Request) -> SessionFactory:
    return request.app.state.session_factory


def get_db(request: Request) -> Iterator[Session]:
    """One session per request: a writing session for POST/PUT/PATCH/DELETE, a reading
    one (deferred BEGIN on SQLite) otherwise. Routes commit explicitly."""
    write = request.method not in ("GET", "HEAD", "OPTIONS")
    session = request.app.state.session_factory(write)
    try:
        yield session
    except BaseException:
        session.rollback()
        raise
    finally:
        session.close()


async def get_publisher(request: Request) -> Publisher:
    return request.app.state.publisher


@dataclass(frozen=True)
class Caller:
    key_id: int
    team_id: int
    user_id: int | None
    is_admin: bool


def _unauthorized(detail: str) -> HTTPException:
    return HTTPException(401, detail, headers={"WWW-Authenticate": "Bearer"})


def get_caller(request: Request, session: Annotated[Session, Depends(get_db)]) -> Caller:
    header = request.headers.get("authorization", "")
    scheme, _, token = header.partition(" ")
    if scheme.lower() != "bearer" or not token.strip():
        raise _unauthorized("missing API key: send 'Authorization: Bearer <key>'")
    key = authenticate(session, token.strip())
    if key is None:
        raise _unauthorized("invalid, revoked or expired API key")
    caller = Caller(
        key_id=key.id, team_id=key.team_id, user_id=key.user_id,
        is_admin=bool(key.user is not None and key.user.is_admin),
    )
    allowed, retry = request.app.state.rate_limiter.allow(key.id)
    if not allowed:
        raise HTTPException(
            429, "rate limit exceeded for this API key",
            headers={"Retry-After": str(max(1, int(retry + 0.999)))},
        )
    return caller


async def clean_query_text(request: Request) -> None:
    """422 for a query parameter or an Idempotency-Key holding a NUL character (which a
    PostgreSQL text column cannot hold: it would be a 500 there and a silent miss on
    SQLite). Registered on every /api/v1 router."""
    items = list(request.query_params.multi_items())
    key = request.headers.get("idempotency-key")
    for name, value in items + ([("Idempotency-Key", key)] if key is not None else []):
        if "\x00" in name or "\x00" in value:
            exc = HTTPException(422, "must not contain NUL (\\u0000) characters")
            exc.field = name.replace("\x00", "")  # type: ignore[attr-defined]
            raise exc


DB = Annotated[Session, Depends(get_db)]
CurrentCaller = Annotated[Caller, Depends(get_caller)]
SettingsDep = Annotated[Settings, Depends(get_settings_dep)]
PublisherDep = Annotated[Publisher, Depends(get_publisher)]
SessionFactoryDep = Annotated[SessionFactory, Depends(get_session_factory)]
