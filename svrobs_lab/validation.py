"""A dataset job's validation: each estimator's model on the held-out rollouts and
the excitation check of its training data (``svrobs_core.measured.validation_summary``),
computed once per job and stored (docs/datasets.md#validation).

A worker computes it after the first unit of the job it runs (it holds the
arrays then: :func:`store_after_unit`); ``GET /jobs/{id}/validation`` and the job's
page serve the stored copy, computing it first if no unit has run yet
(:func:`job_validation`). The per-step series (one-step predictions, open-loop
simulations, and the measured values they are compared with) are kept for the
first ``PLOTTED_ROLLOUTS`` held-out rollouts: they are for the plots; every
statistic is over all held-out rollouts.
"""

from __future__ import annotations

import logging

from sqlalchemy.orm import Session

from service.db import validations as store
from svrobs_core.measured import MeasuredData, StateModel, validation_summary
from svrobs_core.measured.validation import plain
from svrobs_core.parsing import parse_spec

from .auth import Caller
from .datasets.loaded import measured_data
from .dispatch import SessionFactory
from .errors import NotFound
from .jobs import team_job

log = logging.getLogger(__name__)

PLOTTED_ROLLOUTS = 5


def summarize(spec_dict: dict, data: MeasuredData) -> dict:
    """What is stored for a dataset job on ``data``: :func:`validation_summary`, with
    its per-step series cut to the first PLOTTED_ROLLOUTS held-out rollouts and, as
    ``plots``, those rollouts' measured channels in the model's time steps (the
    simulations' rows; the one-step predictions are of rows 1 on)."""
    spec = parse_spec(spec_dict)
    summary = validation_summary(spec, data)
    holdout = spec.measured.holdout
    shown = min(holdout, PLOTTED_ROLLOUTS)
    for model in summary["models"]:
        v = model["validation"]
        if v is not None:
            v["predicted"], v["simulated"] = v["predicted"][:shown], v["simulated"][:shown]
    first = data.rollouts - holdout
    lifted = StateModel(ny=data.n, m=data.m, lags=spec.measured.lags).lift(
        data.take(range(first, first + shown))
    )
    summary["plots"] = {
        "rollouts": list(range(first, first + shown)),
        "of": holdout,
        "channels": list(data.state_names),
        "measured": plain([x[:, : data.n] for x in lifted.X]),
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
    session: Session, caller: Caller, job_id: int, session_factory: SessionFactory
) -> dict:
    """The validation of the caller's dataset job: stored, or computed and stored
    (NotFound for another team's job, or one that is not on a dataset)."""
    job = team_job(session, caller, job_id)
    if job.dataset_id is None:
        raise NotFound(f"job {job_id} is not on a dataset: it has no validation")
    head = {"job_id": job.id, "dataset": job.dataset_id}
    summary = store.stored_validation(session, job.id)
    if summary is None:
        summary = summarize(job.spec, measured_data(session, job.dataset_id))
        session.rollback()  # the read is over (SQLite: no snapshot held while writing)
        writer = session_factory(True)
        try:
            store.store_validation(writer, head["job_id"], summary)
            writer.commit()
        finally:
            writer.close()
    return {**head, **summary}
