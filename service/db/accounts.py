"""Accounts: teams, users and API keys (``svrobs admin``, the API's key lookup).

Keys are ``svr_<prefix8>_<secret>``, stored as a sha256 hash with the prefix
indexed. Lookup is by prefix, then a constant-time compare of the hashes; a
revoked or expired key is rejected exactly like an unknown one. None of these
functions commit: the caller owns the transaction.
"""

from __future__ import annotations

import hashlib
import hmac
import secrets
import string
from datetime import datetime, timedelta

from sqlalchemy import select
from sqlalchemy.orm import Session, joinedload

from svrobs_lab.errors import AdminError

from .models import ApiKey, Team, User, utcnow

KEY_SCHEME = "svr"
PREFIX_LEN = 8
_PREFIX_ALPHABET = string.ascii_lowercase + string.digits
_DUMMY_HASH = hashlib.sha256(b"svrobs-no-such-key").hexdigest()


def hash_key(key: str) -> str:
    return hashlib.sha256(key.encode("utf-8")).hexdigest()


def generate_key() -> tuple[str, str]:
    """A new random key -> ``(plaintext, prefix)``."""
    prefix = "".join(secrets.choice(_PREFIX_ALPHABET) for _ in range(PREFIX_LEN))
    secret = secrets.token_urlsafe(32)
    return f"{KEY_SCHEME}_{prefix}_{secret}", prefix


def split_key(key: str) -> str | None:
    """The prefix of a well-formed key, else None."""
    parts = key.split("_", 2)
    if len(parts) != 3 or parts[0] != KEY_SCHEME or len(parts[1]) != PREFIX_LEN or not parts[2]:
        return None
    if any(c not in _PREFIX_ALPHABET for c in parts[1]):
        return None
    return parts[1]


def authenticate(session: Session, key: str, now: datetime | None = None) -> ApiKey | None:
    """The active ApiKey for ``key`` or None (unknown, wrong secret, revoked, expired)."""
    prefix = split_key(key or "")
    row = None
    if prefix is not None:
        row = session.scalar(
            select(ApiKey).where(ApiKey.prefix == prefix).options(joinedload(ApiKey.user))
        )
    ok = hmac.compare_digest(row.key_hash if row is not None else _DUMMY_HASH, hash_key(key or ""))
    if row is None or not ok:
        return None
    now = now or utcnow()
    if row.revoked_at is not None and row.revoked_at <= now:
        return None
    if row.expires_at is not None and row.expires_at <= now:
        return None
    return row


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


def _by_id_or(session: Session, model, key: int | str, column, value, what: str):
    """The ``model`` row with id ``key`` (an int) or ``column == value``; AdminError if none."""
    row = (
        session.get(model, key)
        if isinstance(key, int)
        else session.scalar(select(model).where(column == value))
    )
    if row is None:
        raise AdminError(f"no {what} {key!r}")
    return row


def get_team(session: Session, team: int | str) -> Team:
    return _by_id_or(session, Team, team, Team.name, team, "team")


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
    return _by_id_or(session, User, user, User.email, email, "user")


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


def active_key(session: Session, key_id: int) -> ApiKey | None:
    """The API key row with this id if it is still active (not revoked, not expired)."""
    row = session.scalar(select(ApiKey).where(ApiKey.id == key_id).options(joinedload(ApiKey.user)))
    now = utcnow()
    if row is None or any(t is not None and t <= now for t in (row.revoked_at, row.expires_at)):
        return None
    return row
