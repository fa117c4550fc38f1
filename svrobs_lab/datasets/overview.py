"""What the web's dataset pages show (docs/web.md#datasets): a dataset with the jobs
that run on it and the excitation check of all its rollouts, the first rollouts'
series for the plots, and a first spec for a job on it."""

from __future__ import annotations

from sqlalchemy.orm import Session

from service.db import datasets as store
from svrobs_core.measured import excitation
from svrobs_core.measured.validation import plain

from ..auth import Caller
from .catalog import EXCITATION_MAX_VALUES, dataset_view, list_datasets_page, team_dataset
from .loaded import measured_data

PLOTTED_ROLLOUTS = 5
# a plot holds at most this many numbers, and each rollout at most PLOTTED_STEPS steps
PLOTTED_VALUES = 200_000
PLOTTED_STEPS = 2_000


def datasets_page(session: Session, caller: Caller, *, limit: int = 100) -> dict:
    """The team's newest datasets (a page of ``limit``) and how many it has."""
    return list_datasets_page(session, caller, limit=limit, offset=0)


def dataset_overview(session: Session, caller: Caller, dataset_id: int) -> dict:
    """The caller's dataset (NotFound otherwise): its view, the jobs that run on it,
    and the excitation check of the regressors of all its rollouts, as stored at
    upload (made here for a dataset stored before it was; None, with a note, for a
    dataset of more than EXCITATION_MAX_VALUES numbers)."""
    row = team_dataset(session, caller, dataset_id)
    jobs, total = store.jobs_using(session, row.id)
    values = store.array_values(row.n, row.m, row.rollouts, row.samples)
    ex, note = row.excitation, None
    if ex is None and values <= EXCITATION_MAX_VALUES:
        ex = excitation(measured_data(session, row.id)).to_dict()
    elif ex is None:
        note = (
            f"not computed here: {values:,} numbers (more than {EXCITATION_MAX_VALUES:,}); "
            "the validation of a job on this dataset has it for its training rollouts"
        )
    return {
        "dataset": dataset_view(row),
        "jobs": jobs,
        "jobs_total": total,
        "excitation": ex,
        "excitation_note": note,
    }


def plot_data(session: Session, caller: Caller, dataset_id: int) -> dict:
    """The first PLOTTED_ROLLOUTS rollouts of the caller's dataset for a plot, each cut
    to its first ``steps`` steps (PLOTTED_STEPS, fewer with many channels: at most
    PLOTTED_VALUES numbers in all): X_i and U_i as lists, the channel names and the
    sample time."""
    row = team_dataset(session, caller, dataset_id)
    steps = max(1, min(PLOTTED_STEPS, PLOTTED_VALUES // (PLOTTED_ROLLOUTS * (row.n + row.m))))
    X, U = store.load_rollouts(session, row.id, PLOTTED_ROLLOUTS, max_steps=steps)
    return {
        "id": row.id,
        "rollouts": row.rollouts,
        "shown": len(X),
        "steps": steps,
        "cut": any(t > steps for t in row.lengths[:PLOTTED_ROLLOUTS]),
        "sample_time": row.sample_time,
        "state_names": list(row.state_names),
        "input_names": list(row.input_names),
        "X": plain(X),
        "U": plain(U),
    }


def starter_spec(session: Session, caller: Caller, dataset_id: int) -> dict:
    """A first job on the caller's dataset (NotFound otherwise): a fifth held out for
    validation (at least one when there are two or more), a learning curve over a
    quarter, half and all of the rest, OLS and SVR, σ_w estimated, the certified
    gain (docs/measured.md#spec)."""
    rollouts = team_dataset(session, caller, dataset_id).rollouts
    holdout = max(1, rollouts // 5) if rollouts >= 2 else 0
    pool = rollouts - holdout
    return {
        "dataset": dataset_id,
        "N": sorted({max(1, pool // 4), max(1, pool // 2), pool}),
        "holdout": holdout,
        "reps": 5,
        "sigma_w": "estimate",
        "estimators": ["ols", "svr"],
        "gamma": [0.05],
        "stages": ["estimate", "bounds", "gain"],
        "seed": 0,
    }
