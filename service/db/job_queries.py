"""Team-scoped reads of jobs: a page of the team's jobs by status, tag, owner and name,
sorted by one or more columns (a summary field's mean at one N among them), one job
(another team's job is None), the team's owners and tags."""

from __future__ import annotations

from dataclasses import dataclass

from sqlalchemy import Float, cast, func, select
from sqlalchemy.orm import Session, defer, joinedload

from .models import JOB_ACTIVE, Job, JobTag, Summary, User

# The columns a page of jobs sorts by (``-`` first: descending); ``metric``: the
# summary field of JobSort.metric at JobSort.N.
SORT_KEYS = ("id", "name", "status", "cells", "duration", "created", "metric")


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


@dataclass(frozen=True)
class JobSort:
    """``keys``: e.g. ("-duration", "name"); ``metric``, ``N``: the metric column."""

    keys: tuple[str, ...] = ()
    metric: str | None = None
    N: int | None = None


def _pooled(field: str):
    """(the pooled mean of ``field`` over summary rows, the condition that a row has
    data): the groups' means weighted by their counts, i.e. the mean over the cells."""
    stats = Summary.__table__.c.stats
    count = cast(stats[(field, "count")].as_float(), Float)
    mean = cast(stats[(field, "mean")].as_float(), Float)
    return func.sum(count * mean) / func.nullif(func.sum(count), 0.0), mean.is_not(None)


def metric_mean(field: str, n: int):
    """The mean of summary ``field`` over every cell of the query's Job at N = ``n``
    (null without data), as a correlated subquery."""
    value, has_data = _pooled(field)
    return select(value).where(Summary.job_id == Job.id, Summary.N == n, has_data)


def metric_values(session: Session, job_ids: list[int], field: str, n: int) -> dict[int, float]:
    """The mean of summary ``field`` over the cells at N = ``n`` of each job of
    ``job_ids`` that has data (:func:`metric_mean`, one query)."""
    if not job_ids:
        return {}
    value, has_data = _pooled(field)
    rows = session.execute(
        select(Summary.job_id, value)
        .where(Summary.job_id.in_(job_ids), Summary.N == n, has_data)
        .group_by(Summary.job_id)
    ).all()
    return {j: float(v) for j, v in rows if v is not None}


def _order(sort: JobSort) -> list:
    cols = {
        "id": Job.id,
        "name": func.lower(Job.name),
        "status": Job.status,
        "cells": Job.n_cells,
        "duration": Job.timings["run_seconds"].as_float(),
        "created": Job.created_at,
    }
    if sort.metric and sort.N is not None:
        cols["metric"] = metric_mean(sort.metric, sort.N).scalar_subquery()
    out = []
    for key in sort.keys:
        name = key.lstrip("-")
        if name in cols:
            col = cols[name]
            out.append((col.desc() if key.startswith("-") else col.asc()).nulls_last())
    return out + [Job.id.desc()]


def job_page(
    session: Session,
    team_id: int,
    user_id: int | None,
    f: JobFilter,
    *,
    limit: int,
    offset: int,
    with_spec: bool = True,
    sort: JobSort | None = None,
) -> tuple[list[Job], int]:
    """The team's jobs matching ``f``, in the order of ``sort`` (newest first when
    none), and how many match in all (``with_spec=False``: the spec column is not read)."""
    query = _where(select(Job), team_id, user_id, f)
    total = session.scalar(select(func.count()).select_from(query.subquery()))
    options = [joinedload(Job.user)] + ([] if with_spec else [defer(Job.spec)])
    rows = session.scalars(
        query.options(*options).order_by(*_order(sort or JobSort())).limit(limit).offset(offset)
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
