"""Team-scoped reads of jobs: a page of the team's jobs by status, tag, owner and name,
one job (another team's job is None), the team's owners and tags."""

from __future__ import annotations

from dataclasses import dataclass

from sqlalchemy import func, select
from sqlalchemy.orm import Session, defer, joinedload

from .models import JOB_ACTIVE, Job, JobTag, User


@dataclass(frozen=True)
class JobFilter:
    status: str | None = None
    tag: str | None = None
    owner: str | None = None  # an email, or "me"
    q: str | None = None  # a part of the name, any case

    def params(self) -> dict[str, str]:
        return {k: v for k, v in vars(self).items() if v}


def _where(query, team_id: int, user_id: int | None, f: JobFilter):
    query = query.where(Job.team_id == team_id)
    if f.status:
        query = query.where(Job.status == f.status)
    if f.tag:
        query = query.where(Job.id.in_(select(JobTag.job_id).where(JobTag.tag == f.tag)))
    if f.owner == "me":
        query = query.where(Job.user_id == user_id)
    elif f.owner:
        owners = select(User.id).where(User.email == f.owner.strip().lower())
        query = query.where(Job.user_id.in_(owners.where(User.team_id == team_id)))
    if f.q:
        pattern = "%" + f.q.replace("\\", "\\\\").replace("%", "\\%").replace("_", "\\_") + "%"
        query = query.where(func.lower(Job.name).like(pattern.lower(), escape="\\"))
    return query


def job_page(
    session: Session,
    team_id: int,
    user_id: int | None,
    f: JobFilter,
    *,
    limit: int,
    offset: int,
    with_spec: bool = True,
) -> tuple[list[Job], int]:
    """The team's jobs matching ``f``, newest first, and how many match in all
    (``with_spec=False``: the spec column is not read)."""
    query = _where(select(Job), team_id, user_id, f)
    total = session.scalar(select(func.count()).select_from(query.subquery()))
    options = [joinedload(Job.user)] + ([] if with_spec else [defer(Job.spec)])
    rows = session.scalars(
        query.options(*options).order_by(Job.id.desc()).limit(limit).offset(offset)
    ).all()
    return list(rows), int(total or 0)


def team_job(session: Session, team_id: int, job_id: int) -> Job | None:
    """One of the team's jobs (with its owner), or None."""
    return session.scalar(
        select(Job).where(Job.id == job_id, Job.team_id == team_id).options(joinedload(Job.user))
    )


def team_owners(session: Session, team_id: int) -> list[str]:
    """The emails of the team's users (the owner filter's choices)."""
    return list(
        session.scalars(select(User.email).where(User.team_id == team_id).order_by(User.email))
    )


def team_tags(session: Session, team_id: int) -> list[str]:
    """Every tag used on the team's jobs (the tag filter's choices)."""
    q = select(JobTag.tag).join(Job, Job.id == JobTag.job_id).where(Job.team_id == team_id)
    return list(session.scalars(q.distinct().order_by(JobTag.tag)))


def any_active(jobs: list[Job]) -> bool:
    return any(j.status in JOB_ACTIVE for j in jobs)
