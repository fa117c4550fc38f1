"""Web sign-ins kept on the server (table ``sessions``): a signed cookie is a session
only while its row exists and has not expired (docs/security.md#sign-in-and-sessions).

Only the SHA-256 of the cookie's session id is stored. Signing out deletes the row,
so a copied cookie stops working at once; a sign-in also deletes the key's expired
rows. Every function takes an open session and never commits.
"""

from __future__ import annotations

import hashlib
from datetime import datetime

from sqlalchemy import delete, select
from sqlalchemy.orm import Session

from .models import SignIn, as_utc, utcnow


def _hash(session_id: str) -> str:
    return hashlib.sha256(session_id.encode("utf-8")).hexdigest()


def start(session: Session, session_id: str, key_id: int, expires_at: datetime) -> SignIn:
    """Keep a new sign-in of ``key_id`` (and drop the key's expired ones)."""
    now = utcnow()
    session.execute(delete(SignIn).where(SignIn.key_id == key_id, SignIn.expires_at <= now))
    row = SignIn(token_hash=_hash(session_id), key_id=key_id, created_at=now, expires_at=expires_at)
    session.add(row)
    session.flush()
    return row


def is_live(session: Session, session_id: str, key_id: int) -> bool:
    """Whether ``session_id`` is a kept, unexpired sign-in of ``key_id``."""
    expires = session.scalar(
        select(SignIn.expires_at).where(
            SignIn.token_hash == _hash(session_id), SignIn.key_id == key_id
        )
    )
    return expires is not None and as_utc(expires) > utcnow()


def end(session: Session, session_id: str) -> None:
    """Forget the sign-in ``session_id`` (signing out)."""
    session.execute(delete(SignIn).where(SignIn.token_hash == _hash(session_id)))
