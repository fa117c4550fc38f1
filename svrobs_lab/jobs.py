"""Jobs: submit (validate, admit, create, then publish), find, list, cancel, delete.

The jobs and their work units are inserted and committed in the caller's
transaction; only then, after the response, are the team's next units sent to the
broker within its fair share (:func:`svrobs_lab.dispatch.dispatch_after_commit`);
the rest follow as its units finish. Nothing is lost if publishing fails: the relay
(beat) publishes units never marked published. Bad specs, the team's quota and a
reused Idempotency-Key raise :mod:`svrobs_lab.errors` (``JobTooLarge``,
``QuotaExceeded``, ``IdempotencyConflict``). Every limit comes from the
:class:`~service.config.Settings` passed in (:func:`limits`).
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, replace

from sqlalchemy.orm import Session

from service.config import Settings
from service.db import job_queries
from service.db.datasets import dataset_shape
from service.db.job_delete import delete_job
from service.db.jobs import admit, cancel_job, create_job
from service.db.models import Job
from svrobs_core.errors import SpecError
from svrobs_core.measured import check_against_data
from svrobs_core.parsing import parse_spec
from svrobs_core.spec import ExperimentSpec
from svrobs_core.workload import DataShape

from .auth import MAX_ID, Caller
from .dispatch import Publisher, SessionFactory, dispatch_after_commit
from .errors import Conflict, NotFound
from .views import job_item, job_out


def limits(settings: Settings) -> dict:
    """The job limits of ``settings``, as the keyword limits of ``create_job``."""
    return {
        "max_cells": settings.MAX_JOB_CELLS,
        "max_cpu_seconds": settings.MAX_JOB_CPU_SECONDS,
        "max_unit_mb": settings.MAX_UNIT_MEMORY_MB,
        "max_stored_mb": settings.MAX_JOB_STORED_MB,
        "max_unit_cpu_seconds": settings.MAX_UNIT_CPU_SECONDS,
        "max_active_jobs": settings.MAX_QUEUED_JOBS_PER_TEAM,
    }


def admit_spec(
    spec: ExperimentSpec,
    settings: Settings,
    *,
    field: str | None = None,
    data: DataShape | None = None,
) -> list:
    """The spec's work units if it is within the job limits of ``settings`` (else
    ``JobTooLarge`` naming the field, under ``field`` if given); a dataset job's with
    its dataset's shape ``data``."""
    lim = limits(settings)
    lim.pop("max_active_jobs")
    return admit(spec, field=field, data=data, **lim)


def _set_aside(spec: ExperimentSpec, field: str) -> ExperimentSpec | None:
    """``spec`` with the field a check against the data refused given a value that
    passes it and changes no other check (N one rollout, no holdout, the default C, no
    input lags where there are no inputs), or None when the other checks depend on it
    (the dataset, the ARX lags, sigma_v)."""
    opts = spec.measured
    assert opts is not None  # a dataset spec
    if field == "N":
        return replace(spec, N=(1,))
    if field == "holdout":
        return replace(spec, measured=replace(opts, holdout=0))
    if field == "C":  # sigma_v = 0's check needs C: it is set aside too
        return replace(spec, measured=replace(opts, C=None, sigma_v=max(opts.sigma_v, 0.1)))
    if field == "state.lags.u" and opts.lags is not None:  # no inputs: q changes nothing
        return replace(spec, measured=replace(opts, lags=(opts.lags[0], 0)))
    return None


def data_errors(session: Session, caller: Caller, spec: dict) -> dict[str, str]:
    """``{field: message}`` of every check of a valid dataset spec against the shape of
    the team's dataset (N and holdout against its rollouts, C's columns, the ARX lags),
    each field checked with those refused before it set aside, so one error does not
    hide another; empty for a simulated spec or a dataset the team does not have
    (submitting says so)."""
    parsed = parse_spec(spec)
    if parsed.measured is None:
        return {}
    shape = dataset_shape(session, parsed.measured.dataset, caller.team_id)
    if shape is None:
        return {}
    found: dict[str, str] = {}
    checked: ExperimentSpec | None = parsed
    while checked is not None:
        try:
            check_against_data(
                checked, shape.n, shape.m, len(shape.lengths), lengths=list(shape.lengths)
            )
            break
        except SpecError as exc:
            field = exc.field or "dataset"
            if field in found:
                break
            found[field] = exc.message
            checked = _set_aside(checked, field)
    return found


@dataclass(frozen=True)
class JobRequest:
    """One job to create: a spec (docs/spec.md#spec-fields) and its labels."""

    spec: dict
    name: str | None = None
    tags: Iterable[str] = ()
    idempotency_key: str | None = None
    schedule_id: int | None = None  # a job a schedule made


class Submission:
    """The submit-and-publish step of one request, for the caller, under ``settings``.
    ``later(fn, *args)`` runs ``fn`` once the response is sent (FastAPI's background
    tasks)."""

    def __init__(
        self,
        *,
        session: Session,
        caller: Caller,
        settings: Settings,
        publisher: Publisher,
        session_factory: SessionFactory,
        later: Callable[..., None],
    ):
        self.session, self.caller, self.settings = session, caller, settings
        self.publisher, self.session_factory = publisher, session_factory
        self.later = later

    def submit(self, requests: Sequence[JobRequest]) -> list[dict]:
        """Create the jobs (or find them by Idempotency-Key), commit, and schedule the
        publishing of the new ones' units after the response; returns the jobs' bodies."""
        session, caller = self.session, self.caller
        bodies, created_any = [], False
        for r in requests:
            job, created = create_job(
                session,
                team_id=caller.team_id,
                user_id=caller.user_id,
                spec=r.spec,
                name=r.name,
                tags=r.tags,
                idempotency_key=r.idempotency_key,
                schedule_id=r.schedule_id,
                git_commit=self.settings.GIT_COMMIT,
                **limits(self.settings),
            )
            created_any |= created
            bodies.append(job_out(job))  # flushed: ids and defaults are set; no read-back
        session.commit()
        session.close()  # end this request's transaction before publishing
        if created_any:
            self.dispatch_after_response()
        return bodies

    def dispatch_after_response(self) -> None:
        """Publish the team's next units (its fair share) once the response is sent
        (after a submission, or a cancel that freed the team's slots). The request's
        session must be closed first (SQLite: its write lock)."""
        self.later(
            dispatch_after_commit,
            self.settings,
            self.publisher,
            self.session_factory,
            self.caller.team_id,
        )


def team_job(session: Session, caller: Caller, job_id: int) -> Job:
    """The caller's job, or NotFound (another team's job is indistinguishable from none;
    so is an id no job can have, which the database would refuse)."""
    job = job_queries.team_job(session, caller.team_id, job_id) if 1 <= job_id <= MAX_ID else None
    if job is None:
        raise NotFound(f"job {job_id} not found")
    return job


def list_jobs(
    session: Session, caller: Caller, f: job_queries.JobFilter, *, limit: int, offset: int
) -> dict:
    """One page of the team's jobs matching ``f``, newest first, as ``GET /jobs`` lists
    them (a compact ``spec_summary`` instead of the spec), with the total."""
    rows, total = job_queries.job_page(
        session, caller.team_id, caller.user_id, f, limit=limit, offset=offset, with_spec=False
    )
    return {"items": [job_item(j) for j in rows], "total": total, "limit": limit, "offset": offset}


def cancel(submission: Submission, job_id: int) -> dict:
    """Cancel a queued or running job (Conflict for a finished one); the team's freed
    slots go to its other jobs after the response. -> the job's body."""
    session, caller = submission.session, submission.caller
    job = team_job(session, caller, job_id)
    if job.status in ("succeeded", "failed"):
        raise Conflict(f"job {job_id} already {job.status}")
    cancel_job(session, job)
    session.commit()
    out = job_out(team_job(session, caller, job_id))
    session.close()  # end the transaction (SQLite's write lock) before publishing
    submission.dispatch_after_response()
    return out


def delete(session: Session, caller: Caller, job_id: int) -> None:
    """Delete a finished or cancelled job with everything stored for it (JobActive
    while it is queued or running), committed."""
    delete_job(session, team_job(session, caller, job_id))
    session.commit()
