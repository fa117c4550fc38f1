"""A dataset job's validation: each estimator's model on the held-out rollouts and
the excitation check of its training data (``svrobs_core.measured.validation_summary``),
computed once per job and stored (docs/datasets.md#validation).

A worker computes it after the first unit of the job it runs (it holds the
arrays then: :func:`store_after_unit`); ``GET /jobs/{id}/validation`` and the job's
page serve the stored copy, computing it first if no unit has run yet
(:func:`job_validation`: one computation per job at a time, bounded per team
with its reports', with no database connection held while it runs). The per-step series (one-step predictions, open-loop
simulations, and the measured values they are compared with) are kept for the
first ``PLOTTED_ROLLOUTS`` held-out rollouts and their first steps, as many as a
plot holds (:func:`summarize`): they are for the plots; every statistic is over all
held-out steps.
"""

from __future__ import annotations

import logging
from contextlib import closing
from typing import Any

from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session

from service.db import validations as store
from service.db.models import Job
from svrobs_core.measured import MeasuredData, StateModel, validation_summary
from svrobs_core.measured.validation import plain
from svrobs_core.parsing import parse_spec
from svrobs_core.planning import estimator_axis

from .auth import Caller
from .datasets.loaded import measured_data
from .datasets.overview import PLOTTED_ROLLOUTS, PLOTTED_STEPS, PLOTTED_VALUES
from .dispatch import SessionFactory
from .errors import NotFound
from .jobs import team_job
from .report_builds import ReportBuilds
from .reports import DEFAULT_BUILDS, JobKey

log = logging.getLogger(__name__)


def summarize(spec_dict: dict, data: MeasuredData) -> dict:
    """What is stored for a dataset job on ``data``: :func:`validation_summary`, with
    its per-step series cut to the first PLOTTED_ROLLOUTS held-out rollouts and their
    first ``steps`` steps (PLOTTED_STEPS, fewer with many channels and models: at most
    PLOTTED_VALUES numbers in all, as a dataset's own plot) and, as ``plots``, those
    rollouts' measured channels in the model's time steps (the simulations' rows; the
    one-step predictions are of rows 1 on)."""
    spec = parse_spec(spec_dict)
    holdout = spec.measured.holdout
    shown = min(holdout, PLOTTED_ROLLOUTS)
    series = max(1, shown) * data.n * (1 + 2 * len(estimator_axis(spec).names))
    steps = max(1, min(PLOTTED_STEPS, PLOTTED_VALUES // series - 1))  # steps + 1 rows
    summary = validation_summary(spec, data, series_rollouts=shown, series_steps=steps)
    first = data.rollouts - holdout
    measured = []  # none held out (holdout 0): nothing to plot
    if shown:
        lifted = StateModel(ny=data.n, m=data.m, lags=spec.measured.lags).lift(
            data.take(range(first, first + shown))
        )
        measured = plain([x[: steps + 1, : data.n] for x in lifted.X])
    summary["plots"] = {
        "rollouts": list(range(first, first + shown)),
        "of": holdout,
        "steps": steps,
        "cut": any(len(x) > steps + 1 for x in lifted.X) if shown else False,
        "channels": list(data.state_names),
        "measured": measured,
        "sample_time": data.sample_time,
    }
    return summary


def store_after_unit(scope, unit_id: int, spec_dict: dict, data: MeasuredData) -> bool:
    """Store the validation of the dataset job of ``unit_id`` unless it is stored;
    ``scope`` is :func:`service.db.session.session_scope`. True when it stored it."""
    with scope(write=False) as s:
        found = store.unit_dataset_job(s, unit_id)
        if found is None or store.stored_validation(s, found[0]) is not None:
            return False
    summary = summarize(spec_dict, data)
    with scope() as s:
        store.store_validation(s, found[0], summary)
    log.info("stored the validation of job %s", found[0])
    return True


def job_validation(
    session: Session,
    caller: Caller,
    job_id: int,
    session_factory: SessionFactory,
    *,
    builds: ReportBuilds | None = None,
) -> dict:
    """The validation of the caller's dataset job: stored, or computed and stored
    (NotFound for another team's job, or one that is not on a dataset). A computation
    is one of the team's builds (``builds``, the app's report builds: concurrent
    requests for the job wait for the one in progress, and a team runs at most
    SVROBS_REPORT_BUILDS_PER_TEAM at once, RateLimited beyond); ``session`` (the
    request's) is closed before it."""
    job = team_job(session, caller, job_id)
    if job.dataset_id is None:
        raise NotFound(f"job {job_id} is not on a dataset: it has no validation")
    head = {"job_id": job.id, "dataset": job.dataset_id}
    summary = store.stored_validation(session, job.id)
    if summary is None:
        key, team = JobKey("validation", job.id, job.created_at), job.team_id
        build = _computation(job, session_factory)
        session.close()  # no connection is held while it is computed or waited for
        builds = builds or DEFAULT_BUILDS
        try:
            summary = builds.get(key, team, "stored", build)
        finally:
            builds.forget(key)  # stored: read from the database from now on
    return {**head, **summary}


def _computation(job: Job, session_factory: SessionFactory):
    """The build of the job's validation: read the dataset in a reading session of its
    own (closed before computing), compute, store through a writing session; one
    stored meanwhile (by a worker) is returned as it is."""
    job_id, dataset_id, spec = job.id, job.dataset_id, dict(job.spec)
    assert dataset_id is not None  # a dataset job

    def compute() -> dict[str, Any]:
        with closing(session_factory(False)) as reader:
            stored = store.stored_validation(reader, job_id)
            if stored is not None:
                return stored
            data = measured_data(reader, dataset_id)
        summary = summarize(spec, data)
        with closing(session_factory(True)) as writer:
            try:
                store.store_validation(writer, job_id, summary)
                writer.commit()
            except IntegrityError:  # the job was deleted meanwhile
                raise NotFound(f"job {job_id} not found") from None
        return summary

    return compute
