"""Share links: a read-only link to one job's report and charts.

The link carries a random token (``secrets.token_urlsafe(32)``, 256 bits); only its
SHA-256 is stored, and a lookup compares the digests in constant time
(``hmac.compare_digest``), so neither the table nor the timing gives a token away.
A link lasts at least an hour, expires (default 7 days, at most 90) and can be revoked; an expired or
revoked link finds nothing (the pages answer 404).
"""

from __future__ import annotations

import hashlib
import hmac
import secrets
from datetime import timedelta

from sqlalchemy import func, select
from sqlalchemy.orm import Session

from .models import Job, ShareLink, as_utc, utcnow

DEFAULT_DAYS = 7
MAX_DAYS = 90
MIN_DAYS = 1 / 24  # one hour


def token_hash(token: str) -> str:
    return hashlib.sha256(token.encode("utf-8", "replace")).hexdigest()


def create_share(
    session: Session,
    job: Job,
    *,
    user_id: int | None,
    days: float = DEFAULT_DAYS,
    label: str | None = None,
) -> tuple[ShareLink, str]:
    """A new link to ``job`` valid for ``days``, named ``label`` -> (row, token).
    Flushes, not committed."""
    if not MIN_DAYS <= days <= MAX_DAYS:
        raise ValueError(
            f"must be at least 1 hour ({MIN_DAYS:.4f} days) and at most {MAX_DAYS} days"
        )
    token = secrets.token_urlsafe(32)
    now = utcnow()
    link = ShareLink(
        token_hash=token_hash(token),
        job_id=job.id,
        team_id=job.team_id,
        user_id=user_id,
        created_at=now,
        expires_at=now + timedelta(days=days),
        label=(label or "").strip() or None,
    )
    session.add(link)
    session.flush()
    return link, token


def is_live(link: ShareLink, now=None) -> bool:
    return link.revoked_at is None and as_utc(link.expires_at) > as_utc(now)


def count_live(session: Session, job_id: int) -> int:
    """How many of the job's links are live (:func:`is_live`: not revoked, not expired)."""
    q = select(func.count(ShareLink.id)).where(
        ShareLink.job_id == job_id, ShareLink.revoked_at.is_(None), ShareLink.expires_at > utcnow()
    )
    return int(session.scalar(q) or 0)


def open_share(session: Session, token: str) -> ShareLink | None:
    """The live link of ``token`` (not expired, not revoked), else None."""
    if not token or len(token) > 200:
        return None
    digest = token_hash(token)
    link = session.scalar(select(ShareLink).where(ShareLink.token_hash == digest))
    if link is None or not hmac.compare_digest(link.token_hash, digest) or not is_live(link):
        return None
    return link


def job_shares(session: Session, team_id: int, job_id: int) -> list[ShareLink]:
    """The job's links, newest first (live, expired and revoked)."""
    q = select(ShareLink).where(ShareLink.job_id == job_id, ShareLink.team_id == team_id)
    return list(session.scalars(q.order_by(ShareLink.id.desc())))


def team_share(session: Session, team_id: int, share_id: int) -> ShareLink | None:
    return session.scalar(
        select(ShareLink).where(ShareLink.id == share_id, ShareLink.team_id == team_id)
    )


def revoke_share(link: ShareLink) -> None:
    """Revoke (idempotent: the first revocation time is kept)."""
    if link.revoked_at is None:
        link.revoked_at = utcnow()
