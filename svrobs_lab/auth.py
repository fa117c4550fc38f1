"""Who calls: an API key's :class:`Caller` (team, user, admin right), found by a
bearer key, a web session's key or a share link, by one rule for every front end.

The web session cookie itself is :mod:`svrobs_lab.sessions`; the share links'
reader is :func:`svrobs_lab.shares.reader`.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

from sqlalchemy.orm import Session

from service.db.accounts import authenticate
from service.db.models import ApiKey

MAX_ID = 2_147_483_647  # ids are 32-bit integers on every dialect


@dataclass(frozen=True)
class Caller:
    key_id: int
    team_id: int
    user_id: int | None
    is_admin: bool


def caller_of_key(key: ApiKey) -> Caller:
    return Caller(
        key_id=key.id,
        team_id=key.team_id,
        user_id=key.user_id,
        is_admin=bool(key.user is not None and key.user.is_admin),
    )


def resolve_caller(
    session: Session,
    find: Callable[[Session], ApiKey | None],
    *,
    reader: Callable[[], Session] | None = None,
) -> Caller | None:
    """The caller of the key ``find`` returns (None: not signed in). With ``reader``
    (a writing request's factory of reading sessions), the key is looked up in a
    short reading session of its own, so that the request's session takes the
    SQLite write lock (BEGIN IMMEDIATE) only when it starts writing."""
    own = reader() if reader is not None else None
    try:
        key = find(own if own is not None else session)
        return None if key is None else caller_of_key(key)
    finally:
        if own is not None:
            own.close()


def bearer_key(token: str) -> Callable[[Session], ApiKey | None]:
    """The ``find`` of :func:`resolve_caller` for a bearer key."""
    return lambda s: authenticate(s, token)
