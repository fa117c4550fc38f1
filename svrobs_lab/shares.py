"""Share links of a job: create, list, revoke (signed in), and open one (no key).

Only the token's hash is stored (:mod:`service.db.shares`); the token is shown once,
when the link is made. An unknown, expired or revoked token is NotFound, like a job
of another team. Who reads through a link is :func:`reader`: the job's team, with no
key, user or admin right. A job has at most SVROBS_MAX_SHARES_PER_JOB live links
(:func:`create`).
"""

from __future__ import annotations

from sqlalchemy.orm import Session

from service.config import Settings
from service.db import shares as store
from service.db.jobs import hold_job
from service.db.models import SHARE_LABEL_MAX, Job, ShareLink
from service.db.quota import lock_team_quota
from svrobs_core.text import NOT_PRINTABLE

from .auth import MAX_ID, Caller
from .datasets.parsed import printable
from .errors import Invalid, NotFound
from .jobs import team_job
from .params import read_number

DEFAULT_DAYS = store.DEFAULT_DAYS
MAX_DAYS = store.MAX_DAYS
MIN_DAYS = store.MIN_DAYS
is_live = store.is_live
LABEL_MAX = SHARE_LABEL_MAX


def share_out(link: ShareLink, url: str | None = None) -> dict:
    return {
        "id": link.id,
        "job_id": link.job_id,
        "created_at": link.created_at,
        "expires_at": link.expires_at,
        "revoked_at": link.revoked_at,
        "label": link.label,
        "live": store.is_live(link),
        "url": url,
    }


def days_of(text: str) -> float:
    """A form's number of days, checked (Invalid in plain words otherwise)."""
    days = read_number("days", text.strip())
    if not MIN_DAYS <= days <= MAX_DAYS:
        raise Invalid(
            f"a link lasts from one hour ({MIN_DAYS:.4f} days) to {MAX_DAYS:g} days, "
            f"not {text.strip()}",
            field="days",
        )
    return days


def create(
    session: Session,
    caller: Caller,
    settings: Settings,
    job_id: int,
    days: float,
    label: str | None = None,
) -> tuple[ShareLink, str]:
    """A link to the caller's job, valid ``days``, named ``label``, committed -> (link,
    token). The label is one line of printable text (shown in lists). Invalid when the
    job already has SVROBS_MAX_SHARES_PER_JOB live links (0: no cap); they are counted
    under the team's quota lock, held until the commit, so concurrent creates are
    counted one after the other."""
    if label is not None and not printable(label):
        raise Invalid(NOT_PRINTABLE, field="label")
    job = team_job(session, caller, job_id)
    if not hold_job(session, job.id):  # deleted since it was read: none to link to
        raise NotFound(f"job {job_id} not found")
    cap = settings.MAX_SHARES_PER_JOB
    if cap:
        lock_team_quota(session, job.team_id)
        live = store.count_live(session, job.id)
        if live >= cap:
            raise Invalid(
                f"job {job.id} has {live} live share links; the limit is {cap} "
                "(SVROBS_MAX_SHARES_PER_JOB): revoke one first"
            )
    link, token = store.create_share(session, job, user_id=caller.user_id, days=days, label=label)
    session.commit()
    return link, token


def job_links(session: Session, caller: Caller, job_id: int) -> list[ShareLink]:
    """The job's links, newest first (their tokens are not kept)."""
    team_job(session, caller, job_id)
    return store.job_shares(session, caller.team_id, job_id)


def revoke(session: Session, caller: Caller, share_id: int) -> ShareLink:
    """Revoke one of the team's links (committed): opening it is NotFound from now on."""
    link = store.team_share(session, caller.team_id, share_id) if share_id <= MAX_ID else None
    if link is None:
        raise NotFound(f"share link {share_id} not found")
    store.revoke_share(link)
    session.commit()
    return link


def open_link(session: Session, token: str) -> tuple[ShareLink, Job]:
    """(the link, its job) of a live token, else NotFound."""
    link = store.open_share(session, token)
    job = session.get(Job, link.job_id) if link is not None else None
    if link is None or job is None or job.team_id != link.team_id:
        raise NotFound("This link does not exist, has expired or was revoked.")
    return link, job


def reader(link: ShareLink) -> Caller:
    """Who reads through a link: the job's team, with no key, user or admin right
    (for the team-scoped lookups only)."""
    return Caller(key_id=0, team_id=link.team_id, user_id=None, is_admin=False)
