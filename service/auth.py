"""API keys: ``svr_<prefix8>_<secret>``, stored as a sha256 hash with the prefix indexed.

Lookup is by prefix, then a constant-time compare of the hashes; a revoked or
expired key is rejected exactly like an unknown one.
"""

from __future__ import annotations

import hashlib
import hmac
import secrets
import string
from datetime import datetime

from sqlalchemy import select
from sqlalchemy.orm import Session, joinedload

from service.db.models import ApiKey, utcnow

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
