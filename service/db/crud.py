"""The DB operations shared by the API, the worker and beat.

Every function takes an open :class:`~sqlalchemy.orm.Session` and never
commits: the caller owns the transaction (``with session_scope() as s:``).
All writes are idempotent where a retry can happen (units redelivered by the
broker, a doubled beat tick, a client retrying a POST).

Lock order, to stay deadlock-free on PostgreSQL: work unit rows, then the
job row.
"""

from __future__ import annotations

import importlib.metadata
import math
import os
import platform
import subprocess
from collections.abc import Iterable, Sequence
from datetime import UTC, datetime, timedelta
from functools import lru_cache
from zoneinfo import ZoneInfo

from croniter import croniter
from sqlalchemy import and_, delete, func, insert, or_, select, update
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session

from svrobs_core.errors import SpecError
from svrobs_core.planning import plan_units, unit_cells
from svrobs_core.records import GROUP_FIELDS, SUMMARY_FIELDS, summarize_columns
from svrobs_core.spec import parse_spec
from svrobs_core.unit_result import UnitResult

from .models import (
    JOB_ACTIVE,
    Job,
    JobTag,
    Result,
    Schedule,
    ScheduleRun,
    Summary,
    WorkUnit,
    utcnow,
)
from .results_store import gamma_key, record_to_row, upsert_results

__all__ = [
    "IdempotencyConflict",
    "JobTooLarge",
    "QuotaExceeded",
    "cancel_job",
    "complete_unit",
    "create_due_schedule_jobs",
    "create_job",
    "fail_unit",
    "gamma_key",
    "heartbeat_unit",
    "latest_due",
    "mark_published",
    "note_unit_error",
    "record_to_row",
    "row_to_record",
    "start_unit",
    "summarize_job",
    "unit_ids_of_job",
    "units_to_publish",
]


class JobTooLarge(SpecError):
    """The spec is valid but has more cells than SVROBS_MAX_JOB_CELLS (HTTP 422)."""


class QuotaExceeded(Exception):
    """The team already has SVROBS_MAX_QUEUED_JOBS_PER_TEAM active jobs (HTTP 429)."""


class IdempotencyConflict(Exception):
    """The Idempotency-Key was used before with a different spec (HTTP 409)."""

    def __init__(self, job: Job):
        super().__init__(f"Idempotency-Key already used for job {job.id} with a different spec")
        self.job = job


def _settings():
    from service.config import get_settings

    return get_settings()


def _now(now: datetime | None = None) -> datetime:
    now = now or utcnow()
    return now if now.tzinfo else now.replace(tzinfo=UTC)


# --------------------------------------------------------------------------- provenance


@lru_cache
def _static_provenance() -> dict:
    try:
        version = importlib.metadata.version("svrobs")
    except importlib.metadata.PackageNotFoundError:  # pragma: no cover
        import svrobs_core

        version = getattr(svrobs_core, "__version__", None)
    commit = os.environ.get("SVROBS_GIT_COMMIT")
    if not commit:
        try:
            here = os.path.dirname(os.path.abspath(__file__))
            out = subprocess.run(
                ["git", "rev-parse", "HEAD"], cwd=here, capture_output=True, text=True, timeout=2
            )
            commit = out.stdout.strip() if out.returncode == 0 else None
        except (OSError, subprocess.SubprocessError):
            commit = None
    import numpy

    return {
        "package": "svrobs",
        "version": version,
        "git_commit": commit or None,
        "python": platform.python_version(),
        "numpy": numpy.__version__,
        "platform": platform.platform(),
    }


def provenance(seed: int) -> dict:
    return {**_static_provenance(), "seed": seed}


# --------------------------------------------------------------------------- jobs


def create_job(
    session: Session,
    *,
    team_id: int,
    user_id: int | None,
    spec: dict,
    name: str | None = None,
    tags: Iterable[str] = (),
    idempotency_key: str | None = None,
    max_cells: int | None = None,
    max_active_jobs: int | None = None,
    schedule_id: int | None = None,
) -> Job:
    """Validate ``spec`` and insert the job and its work units (not committed).

    Raises :class:`SpecError` (naming the field) for a bad spec,
    :class:`JobTooLarge` over ``max_cells`` (default SVROBS_MAX_JOB_CELLS),
    :class:`QuotaExceeded` when the team has ``max_active_jobs`` queued or
    running jobs (default SVROBS_MAX_QUEUED_JOBS_PER_TEAM; pass 0 to skip),
    :class:`IdempotencyConflict` when the key was used with another spec.
    With an ``idempotency_key`` already used by the team for the same spec,
    returns that job. ``job.was_created`` tells which happened.
    """
    parsed = parse_spec(spec)
    normalised = parsed.to_dict()
    limit = _settings().MAX_JOB_CELLS if max_cells is None else max_cells
    if parsed.n_cells > limit:
        raise JobTooLarge(
            "spec",
            f"the job has {parsed.n_cells} cells; the limit is {limit} (SVROBS_MAX_JOB_CELLS)",
        )
    tags = list(dict.fromkeys(str(t) for t in tags))

    if idempotency_key is not None:
        existing = _job_by_key(session, team_id, idempotency_key)
        if existing is not None:
            return _same_or_conflict(existing, normalised)

    cap = _settings().MAX_QUEUED_JOBS_PER_TEAM if max_active_jobs is None else max_active_jobs
    if cap:
        active = session.scalar(
            select(func.count(Job.id)).where(Job.team_id == team_id, Job.status.in_(JOB_ACTIVE))
        )
        if active >= cap:
            raise QuotaExceeded(
                f"the team has {active} queued or running jobs; the limit is {cap} "
                "(SVROBS_MAX_QUEUED_JOBS_PER_TEAM)"
            )

    units = plan_units(parsed)
    job = Job(
        team_id=team_id,
        user_id=user_id,
        schedule_id=schedule_id,
        name=name,
        tags=tags,
        spec=normalised,
        status="queued",
        progress_done=0,
        progress_total=len(units),
        n_cells=parsed.n_cells,
        provenance=provenance(parsed.seed),
        idempotency_key=idempotency_key,
        timings={},
        created_at=utcnow(),
    )
    try:
        with session.begin_nested():
            session.add(job)
            session.flush()
    except IntegrityError:
        # A concurrent request with the same Idempotency-Key won the insert.
        existing = _job_by_key(session, team_id, idempotency_key) if idempotency_key else None
        if existing is None:
            raise
        return _same_or_conflict(existing, normalised)

    for t in tags:
        session.add(JobTag(job_id=job.id, tag=t))
    if units:
        session.execute(
            insert(WorkUnit),
            [
                {
                    "job_id": job.id,
                    "index": i,
                    "payload": u,
                    "n_cells": unit_cells(parsed, u),
                    "status": "pending",
                    "attempts": 0,
                    "created_at": job.created_at,
                }
                for i, u in enumerate(units)
            ],
        )
    session.flush()
    job.was_created = True
    return job


def _job_by_key(session: Session, team_id: int, key: str) -> Job | None:
    return session.scalar(select(Job).where(Job.team_id == team_id, Job.idempotency_key == key))


def _same_or_conflict(job: Job, normalised: dict) -> Job:
    if job.spec != normalised:
        raise IdempotencyConflict(job)
    job.was_created = False
    return job


def unit_ids_of_job(session: Session, job_id: int, *, pending_only: bool = True) -> list[int]:
    q = select(WorkUnit.id).where(WorkUnit.job_id == job_id).order_by(WorkUnit.index)
    if pending_only:
        q = q.where(WorkUnit.status == "pending")
    return list(session.scalars(q))


def cancel_job(session: Session, job: Job) -> Job:
    """Pending units -> cancelled and the job -> cancelled (a finished job is left as is).

    Units already running finish and store their results; no new unit starts.
    """
    if job.status not in JOB_ACTIVE:
        return job
    # units first, then the job (the lock order of this module)
    session.execute(
        select(WorkUnit.id)
        .where(WorkUnit.job_id == job.id, WorkUnit.status == "pending")
        .order_by(WorkUnit.id)
        .with_for_update()
    ).all()
    session.execute(
        update(WorkUnit)
        .where(WorkUnit.job_id == job.id, WorkUnit.status == "pending")
        .values(status="cancelled", finished_at=utcnow())
    )
    locked = _lock_job(session, job.id)
    if locked.status in JOB_ACTIVE:
        locked.status = "cancelled"
        locked.finished_at = utcnow()
        _set_timing(locked)
    session.flush()
    return locked


def _set_timing(job: Job) -> None:
    t = dict(job.timings or {})
    if job.started_at and job.created_at:
        t["queue_seconds"] = (job.started_at - job.created_at).total_seconds()
    if job.finished_at and job.started_at:
        t["run_seconds"] = (job.finished_at - job.started_at).total_seconds()
    if job.finished_at and job.created_at:
        t["total_seconds"] = (job.finished_at - job.created_at).total_seconds()
    job.timings = t


# --------------------------------------------------------------------------- units


def _lock_unit(session: Session, unit_id: int) -> WorkUnit | None:
    return session.scalar(
        select(WorkUnit)
        .where(WorkUnit.id == unit_id)
        .with_for_update()
        .execution_options(populate_existing=True)
    )


def _lock_job(session: Session, job_id: int) -> Job:
    # FOR NO KEY UPDATE: inserting results/units takes KEY SHARE locks on the job row
    # (their foreign key); a plain FOR UPDATE would deadlock two finishing units.
    return session.scalar(
        select(Job)
        .where(Job.id == job_id)
        .with_for_update(key_share=True)
        .execution_options(populate_existing=True)
    )


def start_unit(
    session: Session,
    unit_id: int,
    worker_name: str,
    lease_seconds: int,
    *,
    max_attempts: int | None = None,
) -> tuple[dict, dict] | None:
    """Claim a unit for running -> ``(spec_dict, unit_payload)``, or None to skip it.

    None when the unit does not exist, is done/failed/cancelled, or its job is
    finished or cancelled. A unit already ``running`` is claimed again (a
    redelivery after a killed worker; results are upserted so a duplicate run
    is harmless). A unit started ``max_attempts`` times (default
    SVROBS_MAX_UNIT_ATTEMPTS) without finishing is failed, with its job.
    """
    unit = _lock_unit(session, unit_id)
    if unit is None or unit.status in ("done", "failed", "cancelled"):
        return None
    job = _lock_job(session, unit.job_id)
    if job.status not in JOB_ACTIVE:
        if unit.status == "pending":
            unit.status = "cancelled"
        return None
    limit = _settings().MAX_UNIT_ATTEMPTS if max_attempts is None else max_attempts
    if limit and unit.attempts >= limit:
        _fail(
            session,
            unit,
            job,
            f"gave up after {unit.attempts} attempts "
            f"(the worker died or timed out each time); last error: {unit.error or 'none'}",
        )
        return None
    now = utcnow()
    unit.status = "running"
    unit.attempts += 1
    unit.worker = worker_name
    unit.started_at = now
    unit.lease_expires_at = now + timedelta(seconds=lease_seconds)
    if job.status == "queued":
        job.status = "running"
    if job.started_at is None:
        job.started_at = now
    session.flush()
    return job.spec, unit.payload


def heartbeat_unit(session: Session, unit_id: int, lease_seconds: int) -> bool:
    """Extend a running unit's lease; False when it is no longer running."""
    res = session.execute(
        update(WorkUnit)
        .where(WorkUnit.id == unit_id, WorkUnit.status == "running")
        .values(lease_expires_at=utcnow() + timedelta(seconds=lease_seconds))
    )
    return res.rowcount > 0


def row_to_record(row) -> dict:
    """A ``results`` row (ORM object or mapping) -> a section 10 record."""
    from svrobs_core.records import RECORD_FIELDS

    get = row.__getitem__ if hasattr(row, "keys") else (lambda k: getattr(row, k))
    out = {}
    for f in RECORD_FIELDS:
        v = get(f)
        if isinstance(v, float) and not math.isfinite(v):
            v = None
        out[f] = v
    return out


def complete_unit(session: Session, unit_id: int, records: Sequence[dict] | UnitResult) -> None:
    """Upsert the unit's records (and its groups' summaries when it holds every
    repetition of them), mark it done, update progress; finish the job when the DB
    says every unit is done (summarising the stored results if a group has none)."""
    unit = _lock_unit(session, unit_id)
    if unit is None:
        return
    stored = upsert_results(session, unit.job_id, records)
    if stored["system"] and _whole_groups(session, unit):  # every repetition of its groups
        scope = (stored["system"][0], stored["sigma_w"][0], sorted(set(stored["N"])))
        _write_summaries(session, unit.job_id, summarize_columns(stored), scope)
    now = utcnow()
    if unit.status != "done":
        unit.status = "done"
        unit.finished_at = now
        unit.error = None
        unit.lease_expires_at = None
        if unit.started_at:
            unit.error = None
    session.flush()
    job = _lock_job(session, unit.job_id)
    done, total = session.execute(
        select(
            func.count(WorkUnit.id).filter(WorkUnit.status == "done"),
            func.count(WorkUnit.id),
        ).where(WorkUnit.job_id == job.id)
    ).one()
    job.progress_done = int(done)
    job.progress_total = int(total)
    if done == total and job.status in JOB_ACTIVE:
        if _stored_summaries(session, job.id) != _expected_groups(job):  # some unit wrote none
            _write_summaries(session, job.id, summarize_job(session, job.id))
        job.status = "succeeded"
        job.finished_at = now
        if job.started_at is None:
            job.started_at = unit.started_at or now
        _set_timing(job)
    session.flush()


def summarize_job(session: Session, job_id: int) -> list[dict]:
    """``summarize`` of the job's stored results (read as columns, vectorised)."""
    names = GROUP_FIELDS + SUMMARY_FIELDS
    rows = session.execute(
        select(*[Result.__table__.c[f] for f in names]).where(Result.job_id == job_id)
    ).all()
    return summarize_columns(dict(zip(names, zip(*rows))) if rows else {f: () for f in names})


def _whole_groups(session: Session, unit: WorkUnit) -> bool:
    reps = session.scalar(select(Job.spec).where(Job.id == unit.job_id))["reps"]
    return list((unit.payload or {}).get("reps", ())) == [0, reps]


def _stored_summaries(session: Session, job_id: int) -> int:
    return session.scalar(select(func.count(Summary.id)).where(Summary.job_id == job_id))


def _expected_groups(job: Job) -> int:
    spec = parse_spec(job.spec)
    return len(spec.systems) * len(spec.sigma_w) * len(spec.N) * spec.cells_per_rep


def _write_summaries(
    session: Session,
    job_id: int,
    groups: list[dict],
    scope: tuple[str, float, list[int]] | None = None,
) -> None:
    """Replace the stored summaries of a job, or of one unit's groups (``scope`` =
    its system, sigma_w and N values), by ``groups``. A unit that holds every
    repetition of its groups writes them when it completes, so that finishing a job
    reads nothing back; a job with units split by repetitions is summarised from
    its stored results at the end."""
    q = delete(Summary).where(Summary.job_id == job_id)
    if scope is not None:
        system, sigma_w, Ns = scope
        q = q.where(Summary.system == system, Summary.sigma_w == sigma_w, Summary.N.in_(Ns))
    session.execute(q)
    if groups:
        session.execute(
            insert(Summary),
            [
                {
                    "job_id": job_id,
                    **{g: s[g] for g in GROUP_FIELDS},
                    "gamma_key": gamma_key(s["gamma"]),
                    "count": s["count"],
                    "stats": s["stats"],
                }
                for s in groups
            ],
        )


def _cells_label(job: Job, unit: WorkUnit) -> str:
    p = unit.payload or {}
    systems = (job.spec or {}).get("systems", [])
    sigmas = (job.spec or {}).get("sigma_w", [])
    try:
        s = systems[p["system"]]
        system = s if isinstance(s, str) else s.get("name", f"#{p['system']}")
    except (IndexError, KeyError, TypeError):
        system = p.get("system")
    try:
        sigma = sigmas[p["sigma_w"]]
    except (IndexError, KeyError, TypeError):
        sigma = p.get("sigma_w")
    r0, r1 = (p.get("reps") or [None, None])[:2]
    return (
        f"unit {unit.index} (system={system}, sigma_w={sigma}, N={p.get('N')}, "
        f"reps {r0}..{None if r1 is None else r1 - 1})"
    )


def _fail(session: Session, unit: WorkUnit, job: Job, error: str) -> None:
    now = utcnow()
    unit.status = "failed"
    unit.error = error
    unit.finished_at = now
    unit.lease_expires_at = None
    if job.status in JOB_ACTIVE:
        job.status = "failed"
        job.error = f"{_cells_label(job, unit)} failed: {error}"
        job.finished_at = now
        _set_timing(job)
        # units locked by a starting worker are skipped (no deadlock): start_unit sees the
        # failed job and cancels its unit itself
        pending = (
            select(WorkUnit.id)
            .where(WorkUnit.job_id == job.id, WorkUnit.status == "pending")
            .with_for_update(skip_locked=True)
        )
        ids = list(session.scalars(pending))
        if ids:
            session.execute(
                update(WorkUnit)
                .where(WorkUnit.id.in_(ids), WorkUnit.status == "pending")
                .values(status="cancelled", finished_at=now)
            )
    session.flush()


def note_unit_error(session: Session, unit_id: int, error: str) -> None:
    """Record why a running unit's attempt ended without a result (its worker process
    was lost); the unit stays claimable, and a later "gave up" failure quotes it."""
    session.execute(
        update(WorkUnit)
        .where(WorkUnit.id == unit_id, WorkUnit.status == "running")
        .values(error=error)
    )


def fail_unit(session: Session, unit_id: int, error: str, final: bool) -> None:
    """Record a unit's error. ``final`` -> the unit and its job fail (the job's error
    names the unit's cells); otherwise the unit goes back to pending for a retry."""
    unit = _lock_unit(session, unit_id)
    if unit is None or unit.status in ("done", "failed", "cancelled"):
        return
    job = _lock_job(session, unit.job_id)
    if final:
        _fail(session, unit, job, error)
        return
    unit.status = "pending"
    unit.error = error
    unit.lease_expires_at = None
    session.flush()


# --------------------------------------------------------------------------- relay


def units_to_publish(
    session: Session,
    limit: int = 500,
    *,
    now: datetime | None = None,
    retry_seconds: int | None = None,
    lost_before: datetime | None = None,
) -> list[int]:
    """Units of active jobs that need (re)publishing: pending and never published, or
    published more than ``retry_seconds`` (SVROBS_PUBLISH_RETRY_SECONDS) ago without
    starting, or published before ``lost_before`` (when the broker's current data
    began: a Redis restarted without persistence has lost those messages; see
    :func:`service.broker.broker_epoch`), or running with an expired lease (the
    worker died)."""
    now = _now(now)
    retry = _settings().PUBLISH_RETRY_SECONDS if retry_seconds is None else retry_seconds
    stale = now - timedelta(seconds=retry)
    if lost_before is not None:
        stale = max(stale, min(_now(lost_before), now))
    q = (
        select(WorkUnit.id)
        .join(Job, Job.id == WorkUnit.job_id)
        .where(
            Job.status.in_(JOB_ACTIVE),
            or_(
                and_(
                    WorkUnit.status == "pending",
                    or_(WorkUnit.published_at.is_(None), WorkUnit.published_at < stale),
                ),
                and_(WorkUnit.status == "running", WorkUnit.lease_expires_at < now),
            ),
        )
        .order_by(WorkUnit.id)
        .limit(limit)
    )
    return list(session.scalars(q))


def mark_published(
    session: Session, unit_ids: Sequence[int], *, now: datetime | None = None
) -> None:
    """Record that the units were sent to the broker (running units whose lease
    expired go back to pending)."""
    if not unit_ids:
        return
    now = _now(now)
    ids = list(unit_ids)
    for i in range(0, len(ids), 1000):
        chunk = ids[i : i + 1000]
        session.execute(
            update(WorkUnit)
            .where(
                WorkUnit.id.in_(chunk),
                WorkUnit.status == "running",
                WorkUnit.lease_expires_at < now,
            )
            .values(status="pending", lease_expires_at=None)
        )
        session.execute(
            update(WorkUnit)
            .where(WorkUnit.id.in_(chunk), WorkUnit.status == "pending")
            .values(published_at=now)
        )


# --------------------------------------------------------------------------- schedules


def latest_due(cron: str, tz: str, now: datetime) -> datetime:
    """The latest time <= ``now`` matched by ``cron`` in time zone ``tz`` (as UTC)."""
    zone = ZoneInfo(tz)
    local = _now(now).astimezone(zone)
    # croniter's get_prev excludes an exact match, so start just after `now`
    it = croniter(cron, local + timedelta(seconds=1))
    due = it.get_prev(datetime)
    if due.tzinfo is None:
        due = due.replace(tzinfo=zone)
    return due.astimezone(UTC).replace(microsecond=0)


def create_due_schedule_jobs(session: Session, now: datetime) -> list[Job]:
    """Create one job per enabled schedule whose latest due time (<= now, not before
    the schedule was created) has no run yet. A ScheduleRun row is inserted on the
    unique (schedule, due_at) first and the job is made only by the inserter, so a
    doubled or restarted tick never runs one sweep twice. Not committed."""
    now = _now(now)
    dialect = session.get_bind().dialect.name
    if dialect == "postgresql":
        from sqlalchemy.dialects.postgresql import insert as dialect_insert
    else:
        from sqlalchemy.dialects.sqlite import insert as dialect_insert

    jobs: list[Job] = []
    schedules = session.scalars(
        select(Schedule).where(Schedule.enabled.is_(True)).order_by(Schedule.id)
    ).all()
    for sched in schedules:
        try:
            due = latest_due(sched.cron, sched.timezone, now)
        except Exception:  # an invalid cron in the DB must not stop the others
            continue
        created = sched.created_at.replace(microsecond=0) if sched.created_at else None
        if created is not None and due < created:
            continue
        run_id = session.execute(
            dialect_insert(ScheduleRun)
            .values(schedule_id=sched.id, due_at=due, created_at=utcnow())
            .on_conflict_do_nothing(index_elements=["schedule_id", "due_at"])
            .returning(ScheduleRun.id)
        ).scalar()
        if run_id is None:
            continue  # another tick already took this due time
        run = session.get(ScheduleRun, run_id)
        stamp = due.strftime("%Y-%m-%dT%H:%M:%SZ")
        try:
            with session.begin_nested():
                job = create_job(
                    session,
                    team_id=sched.team_id,
                    user_id=sched.user_id,
                    spec=sched.spec_template,
                    name=f"{sched.name} @ {stamp}",
                    tags=list(sched.tags or []) + [f"schedule:{sched.name}"],
                    idempotency_key=f"schedule:{sched.id}:{stamp}",
                    max_active_jobs=0,
                    schedule_id=sched.id,
                )
        except (SpecError, IdempotencyConflict) as exc:
            run.error = str(exc)
            continue
        run.job_id = job.id
        if getattr(job, "was_created", False):
            jobs.append(job)
    session.flush()
    return jobs
