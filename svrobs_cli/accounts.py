"""Teams, users and API keys: what ``svrobs admin``, ``svrobs serve``'s first start and
the tests do to them.

None of these commit: the caller owns the transaction.
"""

from __future__ import annotations

from datetime import datetime, timedelta

from sqlalchemy import select
from sqlalchemy.orm import Session

from service.auth import generate_key, hash_key, split_key
from service.db.models import ApiKey, Team, User, utcnow


class AdminError(ValueError):
    """A bad admin request (unknown team, duplicate name...)."""


def create_team(session: Session, name: str) -> Team:
    name = name.strip()
    if not name:
        raise AdminError("team name must not be empty")
    if session.scalar(select(Team).where(Team.name == name)) is not None:
        raise AdminError(f"team {name!r} already exists")
    team = Team(name=name, created_at=utcnow())
    session.add(team)
    session.flush()
    return team


def _one(session: Session, model, ident: int | str, where, what: str):
    """The row with id ``ident`` (an int) or matching ``where`` (a name), else AdminError."""
    row = session.get(model, ident) if isinstance(ident, int) else session.scalar(where)
    if row is None:
        raise AdminError(f"no {what} {ident!r}")
    return row


def get_team(session: Session, team: int | str) -> Team:
    return _one(session, Team, team, select(Team).where(Team.name == team), "team")


def create_user(session: Session, team: int | str, email: str, *, is_admin: bool = False) -> User:
    t = get_team(session, team)
    email = email.strip().lower()
    if "@" not in email:
        raise AdminError(f"{email!r} is not an email address")
    if session.scalar(select(User).where(User.email == email)) is not None:
        raise AdminError(f"user {email!r} already exists")
    user = User(team_id=t.id, email=email, is_admin=is_admin, created_at=utcnow())
    session.add(user)
    session.flush()
    return user


def get_user(session: Session, user: int | str) -> User:
    email = user if isinstance(user, int) else user.strip().lower()
    return _one(session, User, user, select(User).where(User.email == email), "user")


def create_key(
    session: Session,
    user: int | str,
    *,
    name: str | None = None,
    expires_at: datetime | None = None,
    expires_in_days: float | None = None,
) -> tuple[ApiKey, str]:
    """A new key for ``user`` (id or email) -> ``(row, plaintext)``; the plaintext is
    shown once and never stored."""
    u = get_user(session, user)
    if expires_at is None and expires_in_days is not None:
        expires_at = utcnow() + timedelta(days=expires_in_days)
    plaintext, prefix = generate_key()
    row = ApiKey(
        prefix=prefix,
        key_hash=hash_key(plaintext),
        team_id=u.team_id,
        user_id=u.id,
        name=name,
        created_at=utcnow(),
        expires_at=expires_at,
    )
    session.add(row)
    session.flush()
    return row, plaintext


def revoke_key(session: Session, key_or_prefix: str | int) -> ApiKey:
    """Revoke by key id, prefix, or the full key."""
    if isinstance(key_or_prefix, int):
        row = session.get(ApiKey, key_or_prefix)
    else:
        prefix = split_key(key_or_prefix) or key_or_prefix
        row = session.scalar(select(ApiKey).where(ApiKey.prefix == prefix))
    if row is None:
        raise AdminError(f"no key {key_or_prefix!r}")
    if row.revoked_at is None:
        row.revoked_at = utcnow()
    session.flush()
    return row


def list_keys(session: Session, team: int | str | None = None) -> list[ApiKey]:
    q = select(ApiKey).order_by(ApiKey.id)
    if team is not None:
        q = q.where(ApiKey.team_id == get_team(session, team).id)
    return list(session.scalars(q))
