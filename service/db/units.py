"""Work units and summaries: claim (start), heartbeat, complete, fail a unit; the
job's summaries, written when its units complete.

Every function takes an open :class:`~sqlalchemy.orm.Session` and never commits.
All writes are idempotent where a retry can happen (units redelivered by the
broker). Lock order, to stay deadlock-free on PostgreSQL: work unit rows, then
the job row.
"""

from __future__ import annotations

from collections.abc import Sequence
from datetime import timedelta
from typing import Any, cast

from sqlalchemy import CursorResult, delete, func, insert, select, update
from sqlalchemy.orm import Session

from svrobs_core.parsing import parse_spec
from svrobs_core.records import GROUP_FIELDS, SUMMARY_FIELDS, summarize_columns
from svrobs_core.unit_result import UnitResult

from .clock import db_now
from .jobs import lock_job, set_timing
from .models import JOB_ACTIVE, Job, Result, Summary, WorkUnit, utcnow
from .result_blocks import draft_block, signed_zeros, store_block
from .results_store import UnitColumns, gamma_key, unit_columns, upsert_results


def _lock_unit(session: Session, unit_id: int) -> WorkUnit | None:
    return session.scalar(
        select(WorkUnit)
        .where(WorkUnit.id == unit_id)
        .with_for_update()
        .execution_options(populate_existing=True)
    )


def start_unit(
    session: Session,
    unit_id: int,
    worker_name: str,
    lease_seconds: int,
    *,
    max_attempts: int,
) -> tuple[dict, dict] | None:
    """Claim a unit for running -> ``(spec_dict, unit_payload)``, or None to skip it.

    None when the unit does not exist, is done/failed/cancelled, or its job is
    finished or cancelled. A unit already ``running`` is claimed again (a
    redelivery after a killed worker; results are upserted so a duplicate run
    is harmless). A unit started ``max_attempts`` times (SVROBS_MAX_UNIT_ATTEMPTS,
    passed in by the worker; 0: no limit) without finishing is failed, with its job.
    """
    unit = _lock_unit(session, unit_id)
    if unit is None or unit.status in ("done", "failed", "cancelled"):
        return None
    job = lock_job(session, unit.job_id)
    if job.status not in JOB_ACTIVE:
        if unit.status == "pending":
            unit.status = "cancelled"
        return None
    if max_attempts and unit.attempts >= max_attempts:
        _fail(
            session,
            unit,
            job,
            f"gave up after {unit.attempts} attempts "
            f"(the worker died or timed out each time); last error: {unit.error or 'none'}",
        )
        return None
    now = db_now(session)  # leases are compared by other hosts: the DB's clock
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


def expire_leases_of(session: Session, worker_name: str) -> list[int]:
    """End the leases of the units ``worker_name`` holds as ``running`` -> their ids.

    Called by a worker as it starts, before it takes any message: a unit its node name
    still holds was claimed by a process of that name that is gone (stopped or killed
    mid-unit), and the relay re-publishes a running unit whose lease ran out
    (:func:`service.db.outbox.units_to_publish`) instead of after the whole lease."""
    ids = list(
        session.scalars(
            select(WorkUnit.id).where(WorkUnit.status == "running", WorkUnit.worker == worker_name)
        )
    )
    if ids:
        session.execute(
            update(WorkUnit)
            .where(WorkUnit.id.in_(ids), WorkUnit.status == "running")
            # a second ago: expired also to a relay in this transaction (PostgreSQL's
            # now() is the transaction's start)
            .values(lease_expires_at=db_now(session) - timedelta(seconds=1))
        )
    return ids


def unit_status(session: Session, unit_id: int) -> str | None:
    """The unit's status (None if it does not exist): a running unit whose status
    became ``cancelled`` (its job was cancelled or failed) stops."""
    return session.scalar(select(WorkUnit.status).where(WorkUnit.id == unit_id))


def heartbeat_unit(session: Session, unit_id: int, lease_seconds: int) -> bool:
    """Extend a running unit's lease; False when it is no longer running."""
    res = session.execute(
        update(WorkUnit)
        .where(WorkUnit.id == unit_id, WorkUnit.status == "running")
        .values(lease_expires_at=db_now(session) + timedelta(seconds=lease_seconds))
    )
    return cast("CursorResult[Any]", res).rowcount > 0  # an UPDATE's result


def complete_unit(session: Session, unit_id: int, records: Sequence[dict] | UnitResult) -> bool:
    """Upsert the unit's records (and its groups' summaries when it holds every
    repetition of them), mark it done, update progress; finish the job when the DB
    says every unit is done (summarising the stored results if a group has none).
    False (nothing stored) when the unit was cancelled or failed meanwhile. A
    :class:`UnitResult`'s rows and summaries are computed before the first statement
    (:func:`~service.db.results_store.unit_columns`), so that on SQLite the write
    lock is held only for the statements."""
    # the CPU work first: on SQLite the first statement takes the one write lock
    groups = None
    draft = None
    to_store: Sequence[dict] | UnitResult | UnitColumns = records
    if isinstance(records, UnitResult):
        to_store = unit_columns(records)
        arrays = records.summary_columns()  # the summary fields as floats
        summary = {f: arrays[f] for f in SUMMARY_FIELDS}
        draft = draft_block(to_store.columns, signed_zeros=signed_zeros(session), arrays=summary)
        if to_store.whole_groups:  # from the unit's arrays, not its stored values
            groups = summarize_columns(arrays)
    unit = _lock_unit(session, unit_id)
    if unit is None or unit.status in ("cancelled", "failed"):
        return False  # cancelled while it ran (its job cancelled or failed)
    stored = upsert_results(session, unit.job_id, to_store)
    if stored["system"]:  # the report's copy of them (a unit stored again: replaced)
        store_block(session, unit.job_id, unit_id, stored, draft=draft)
    whole = to_store.whole_groups if isinstance(to_store, UnitColumns) else None
    if whole is None and stored["system"]:  # not known from the result: the job's spec
        whole = _whole_groups(session, unit)
    if stored["system"] and whole:  # every repetition of its groups
        scope = (stored["system"][0], stored["sigma_w"][0], sorted(set(stored["N"])))
        if groups is None:
            groups = summarize_columns(stored)
        _write_summaries(session, unit.job_id, groups, scope)
    now = utcnow()
    if unit.status != "done":
        unit.status = "done"
        unit.finished_at = now
        unit.error = None
        unit.lease_expires_at = None
        if unit.started_at:
            unit.error = None
    session.flush()
    job = lock_job(session, unit.job_id)
    done, total, cells = session.execute(
        select(
            func.count(WorkUnit.id).filter(WorkUnit.status == "done"),
            func.count(WorkUnit.id),
            func.coalesce(func.sum(WorkUnit.n_cells).filter(WorkUnit.status == "done"), 0),
        ).where(WorkUnit.job_id == job.id)
    ).one()
    job.progress_done = int(done)
    job.progress_total = int(total)
    job.cells_done = int(cells)
    if done == total and job.status in JOB_ACTIVE:
        if _stored_summaries(session, job.id) != _expected_groups(job):  # some unit wrote none
            _write_summaries(session, job.id, summarize_job(session, job.id))
        job.status = "succeeded"
        job.finished_at = now
        if job.started_at is None:
            job.started_at = unit.started_at or now
        set_timing(job)
    session.flush()
    return True


def summarize_job(session: Session, job_id: int) -> list[dict]:
    """``summarize`` of the job's stored results (read as columns, vectorised)."""
    names = GROUP_FIELDS + SUMMARY_FIELDS
    rows = session.execute(
        select(*[Result.__table__.c[f] for f in names]).where(Result.job_id == job_id)
    ).all()
    return summarize_columns(dict(zip(names, zip(*rows))) if rows else {f: () for f in names})


def _whole_groups(session: Session, unit: WorkUnit) -> bool:
    spec = session.scalar(select(Job.spec).where(Job.id == unit.job_id))
    assert spec is not None  # the job of a locked unit exists
    reps = spec["reps"]
    return list((unit.payload or {}).get("reps", ())) == [0, reps]


def _stored_summaries(session: Session, job_id: int) -> int:
    return session.execute(
        select(func.count(Summary.id)).where(Summary.job_id == job_id)
    ).scalar_one()


def _expected_groups(job: Job) -> int:
    spec = parse_spec(job.spec)
    return spec.n_cells // spec.reps  # one group per (system, sigma_w, N, estimator, gamma)


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
    if groups:  # a Core executemany (the ORM's bulk insert costs ~1 ms per group)
        session.execute(
            insert(Summary.__table__),
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
    system, sigma = _unit_pair(job.spec or {}, p)
    r0, r1 = (p.get("reps") or [None, None])[:2]
    return (
        f"unit {unit.index} (system={system}, sigma_w={sigma}, N={p.get('N')}, "
        f"reps {r0}..{None if r1 is None else r1 - 1})"
    )


def _unit_pair(spec: dict, p: dict) -> tuple:
    """The (system, sigma_w) a unit's payload points at in the job's spec (a dataset
    job has one: its dataset and its sigma_w)."""
    if "dataset" in spec:
        return f"dataset-{spec['dataset']}", spec.get("sigma_w")
    systems, sigmas = spec.get("systems", []), spec.get("sigma_w", [])
    try:
        s = systems[p["system"]]
        system = s if isinstance(s, str) else s.get("name", f"#{p['system']}")
    except (IndexError, KeyError, TypeError):
        system = p.get("system")
    try:
        sigma = sigmas[p["sigma_w"]]
    except (IndexError, KeyError, TypeError):
        sigma = p.get("sigma_w")
    return system, sigma


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
        set_timing(job)
        # the job's other units are cancelled (running ones stop: units.unit_status);
        # units locked by a starting worker are skipped (no deadlock): start_unit sees the
        # failed job and cancels its unit itself
        others = (
            select(WorkUnit.id)
            .where(WorkUnit.job_id == job.id, WorkUnit.status.in_(("pending", "running")))
            .with_for_update(skip_locked=True)
        )
        ids = list(session.scalars(others))
        if ids:
            session.execute(
                update(WorkUnit)
                .where(WorkUnit.id.in_(ids), WorkUnit.status.in_(("pending", "running")))
                .values(status="cancelled", finished_at=now, lease_expires_at=None)
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
    job = lock_job(session, unit.job_id)
    if final:
        _fail(session, unit, job, error)
        return
    unit.status = "pending"
    unit.error = error
    unit.lease_expires_at = None
    session.flush()
