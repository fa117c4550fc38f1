"""Jobs: create (validate, check the quota and the Idempotency-Key, plan the units),
cancel, look up their units.

Every function takes an open :class:`~sqlalchemy.orm.Session` and never commits:
the caller owns the transaction (``with session_scope(url) as s:``). Lock order, to
stay deadlock-free on PostgreSQL: work unit rows, then the job row.
"""

from __future__ import annotations

from collections.abc import Iterable

from sqlalchemy import func, insert, select, update
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session

from svrobs_core import admission, workload
from svrobs_core.parsing import parse_spec
from svrobs_core.planning import unit_cells
from svrobs_core.spec import ExperimentSpec
from svrobs_lab.errors import (
    DatasetNotFound,
    IdempotencyConflict,
    JobTooLarge,
    NotFound,
    QuotaExceeded,
)

from .datasets import dataset_shape, spec_data
from .models import JOB_ACTIVE, Job, JobTag, Schedule, WorkUnit, utcnow
from .provenance import provenance
from .quota import lock_team_quota


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
    max_cpu_seconds: float | None = None,
    max_unit_mb: int | None = None,
    max_active_jobs: int | None = None,
    schedule_id: int | None = None,
    max_stored_mb: float | None = None,
    max_unit_cpu_seconds: float | None = None,
    git_commit: str | None = None,
) -> tuple[Job, bool]:
    """Validate ``spec`` and insert the job and its work units (not committed).

    Raises :class:`SpecError` (naming the field) for a bad spec,
    :class:`JobTooLarge` over ``max_cells`` or over the work limits of :func:`admit`,
    :class:`QuotaExceeded` when the team has ``max_active_jobs`` queued or
    running jobs (counted under the team's quota lock, held until the caller's
    transaction ends: :func:`service.db.quota.lock_team_quota`). Each limit is passed in by the application layer
    (``svrobs_lab.jobs.limits``); None or 0: no limit. ``git_commit`` (SVROBS_GIT_COMMIT;
    None: the checkout's) goes into the job's provenance (:mod:`service.db.provenance`).
    :class:`IdempotencyConflict` when the key was used with another spec, name or tags,
    :class:`~svrobs_lab.errors.NotFound` (422 naming ``dataset``) when the spec's
    ``dataset`` is not one of the team's (the job is linked to it: ``jobs.dataset_id``),
    also when it is deleted between that check and the insert.
    With an ``idempotency_key`` already used by the team for the same spec, name and tags,
    returns that job. Returns ``(job, created)``; ``created`` is False for that job.
    """
    parsed = parse_spec(spec)
    normalised = parsed.to_dict()
    # the team's dataset, checked against the spec (DatasetNotFound / SpecError: 422)
    dataset_id, data = spec_data(session, team_id, parsed)
    units = admit(
        parsed,
        max_cells=max_cells,
        max_cpu_seconds=max_cpu_seconds,
        max_unit_mb=max_unit_mb,
        max_stored_mb=max_stored_mb,
        max_unit_cpu_seconds=max_unit_cpu_seconds,
        data=data,
    )
    tags = list(dict.fromkeys(str(t) for t in tags))

    if idempotency_key is not None:
        existing = _job_by_key(session, team_id, idempotency_key)
        if existing is not None:
            return _same_or_conflict(existing, normalised, name, tags)

    cap = max_active_jobs
    if cap:
        lock_team_quota(session, team_id)  # count-then-insert: one at a time per team
        active = session.execute(
            select(func.count(Job.id)).where(Job.team_id == team_id, Job.status.in_(JOB_ACTIVE))
        ).scalar_one()
        if active >= cap:
            raise QuotaExceeded(
                f"the team has {active} queued or running jobs; the limit is {cap} "
                "(SVROBS_MAX_QUEUED_JOBS_PER_TEAM)"
            )

    job = Job(
        team_id=team_id,
        user_id=user_id,
        schedule_id=schedule_id,
        name=name,
        tags=tags,
        spec=normalised,
        spec_summary=spec_summary(normalised, parsed.n_cells),
        dataset_id=dataset_id,
        status="queued",
        progress_done=0,
        progress_total=len(units),
        n_cells=parsed.n_cells,
        provenance=provenance(parsed.seed, git_commit),
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
        if existing is not None:
            return _same_or_conflict(existing, normalised, name, tags)
        # The dataset, found above, was deleted before the insert (the foreign key refused).
        if dataset_id is not None and dataset_shape(session, dataset_id, team_id) is None:
            raise DatasetNotFound(dataset_id) from None
        # The schedule of a run made now was deleted before the insert.
        if schedule_id is not None and not _schedule_exists(session, schedule_id):
            raise NotFound(f"schedule {schedule_id} not found") from None
        raise

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
    return job, True


# the setting of each limit of svrobs_core.admission (WorkloadError.kind)
LIMIT_SETTINGS = {
    "cells": "SVROBS_MAX_JOB_CELLS",
    "stored": "SVROBS_MAX_JOB_STORED_MB",
    "cpu": "SVROBS_MAX_JOB_CPU_SECONDS",
    "unit_cpu": "SVROBS_MAX_UNIT_CPU_SECONDS",
    "memory": "SVROBS_MAX_UNIT_MEMORY_MB",
}


def admit(
    spec: ExperimentSpec,
    *,
    field: str | None = None,
    max_cells: int | None = None,
    max_cpu_seconds: float | None = None,
    max_unit_mb: float | None = None,
    max_stored_mb: float | None = None,
    max_unit_cpu_seconds: float | None = None,
    data: workload.DataShape | None = None,
) -> list[dict]:
    """The spec's work units, planned to stay under SVROBS_MAX_UNIT_MEMORY_MB and
    SVROBS_MAX_UNIT_CPU_SECONDS, if the job is admissible
    (:func:`svrobs_core.admission.admit`, docs/deploy.md#admission; a dataset job with
    its dataset's shape ``data``: :func:`service.db.datasets.spec_data`).

    Raises :class:`JobTooLarge` naming the spec field that weighs most (under
    ``field`` if given: ``spec_template.mc_runs``; the message gives the estimate,
    the limit and its setting) when the job has more cells than SVROBS_MAX_JOB_CELLS
    or would store more than SVROBS_MAX_JOB_STORED_MB (checked first, from the axis
    lengths), when its estimated CPU time is over SVROBS_MAX_JOB_CPU_SECONDS, or when
    a unit split down to one repetition is over a per-unit cap. None or 0: no limit.
    """
    mb, smb = max_unit_mb or None, max_stored_mb or None
    try:
        units, _cost = admission.admit(
            spec,
            max_cells=max_cells or None,
            max_stored_bytes=None if smb is None else smb * 2**20,
            max_cpu_seconds=max_cpu_seconds or None,
            max_unit_bytes=None if mb is None else int(mb * 2**20),
            max_unit_seconds=max_unit_cpu_seconds or None,
            data=data,
        )
    except workload.WorkloadError as exc:
        if exc.kind == "cells":  # the grid as a whole
            where = field or "spec"
        else:
            where = f"{field}.{exc.field}" if field else exc.field
        raise JobTooLarge(where, f"{exc.message} ({LIMIT_SETTINGS[exc.kind]})") from None
    return units


def _job_by_key(session: Session, team_id: int, key: str) -> Job | None:
    return session.scalar(select(Job).where(Job.team_id == team_id, Job.idempotency_key == key))


def _same_or_conflict(job: Job, normalised: dict, name, tags: list[str]) -> tuple[Job, bool]:
    """The job of a reused Idempotency-Key if the request is the same (spec, name and
    the set of tags), else IdempotencyConflict naming what differs."""
    if job.spec != normalised:
        raise IdempotencyConflict(job, "spec")
    if (job.name or None) != (name or None):
        raise IdempotencyConflict(job, "name")
    if set(job.tags or ()) != set(tags):
        raise IdempotencyConflict(job, "tags")
    return job, False


def unit_ids_of_job(session: Session, job_id: int, *, pending_only: bool = True) -> list[int]:
    q = select(WorkUnit.id).where(WorkUnit.job_id == job_id).order_by(WorkUnit.index)
    if pending_only:
        q = q.where(WorkUnit.status == "pending")
    return list(session.scalars(q))


def cancel_job(session: Session, job: Job) -> Job:
    """Pending and running units -> cancelled, and the job -> cancelled (a finished job
    is left as is). No new unit starts; a running unit sees its status and stops
    within SVROBS_CANCEL_CHECK_SECONDS (``worker.tasks``), storing nothing. The job
    keeps the cells of the units done before (``cells_done``)."""
    if job.status not in JOB_ACTIVE:
        return job
    # units first, then the job (the lock order of this module)
    live = WorkUnit.status.in_(("pending", "running"))
    session.execute(
        select(WorkUnit.id)
        .where(WorkUnit.job_id == job.id, live)
        .order_by(WorkUnit.id)
        .with_for_update()
    ).all()
    session.execute(
        update(WorkUnit)
        .where(WorkUnit.job_id == job.id, live)
        .values(status="cancelled", finished_at=utcnow(), lease_expires_at=None)
    )
    locked = lock_job(session, job.id)
    if locked.status in JOB_ACTIVE:
        locked.status = "cancelled"
        locked.finished_at = utcnow()
        set_timing(locked)
    session.flush()
    return locked


def set_timing(job: Job) -> None:
    """Queue, run and total seconds from the job's timestamps."""
    t = dict(job.timings or {})
    if job.started_at and job.created_at:
        t["queue_seconds"] = (job.started_at - job.created_at).total_seconds()
    if job.finished_at and job.started_at:
        t["run_seconds"] = (job.finished_at - job.started_at).total_seconds()
    if job.finished_at and job.created_at:
        t["total_seconds"] = (job.finished_at - job.created_at).total_seconds()
    job.timings = t


def _schedule_exists(session: Session, schedule_id: int) -> bool:
    """Whether the schedule is in the database now (not the session's copy of it)."""
    return session.scalar(select(Schedule.id).where(Schedule.id == schedule_id)) is not None


def hold_job(session: Session, job_id: int) -> bool:
    """Whether the job still exists, its row held (FOR KEY SHARE) until the commit: a
    row referring to it can be inserted, and a delete waits for the commit."""
    held = session.scalar(
        select(Job.id).where(Job.id == job_id).with_for_update(read=True, key_share=True)
    )
    return held is not None


def lock_job(session: Session, job_id: int) -> Job:
    """The job row, locked FOR NO KEY UPDATE and re-read."""
    # FOR NO KEY UPDATE: inserting results/units takes KEY SHARE locks on the job row
    # (their foreign key); a plain FOR UPDATE would deadlock two finishing units.
    job = session.scalar(
        select(Job)
        .where(Job.id == job_id)
        .with_for_update(key_share=True)
        .execution_options(populate_existing=True)
    )
    # the callers hold the job or one of its units (locked first: deleting a job
    # locks its units, so a locked unit's job exists)
    assert job is not None, f"no job {job_id}"
    return job


def spec_summary(spec: dict, n_cells: int) -> dict:
    """A normalised spec in a few hundred bytes, whatever its grid sizes: system
    names (a dataset job's: ``dataset-ID``), the size of each grid axis (and the N
    range), estimators, stages, cells."""
    Ns = spec.get("N") or []
    if "dataset" in spec:  # one system (the dataset) and one sigma_w (a level or "estimate")
        systems, sizes = [f"dataset-{spec['dataset']}"], {"sigma_w": 1}
    else:
        systems = [s if isinstance(s, str) else s.get("name", "custom") for s in spec["systems"]]
        sizes = {"sigma_w": len(spec.get("sigma_w") or [])}
    return {
        "systems": systems,
        "grid": sizes
        | {k: len(spec.get(k) or []) for k in ("N", "gamma")}
        | {"reps": spec.get("reps")},
        "N_range": [min(Ns), max(Ns)] if Ns else None,
        "estimators": list(spec.get("estimators") or []),
        "stages": list(spec.get("stages") or []),
        "n_cells": n_cells,
    }
