"""Work units of a dataset job -> records (docs/measured.md).

``run_measured_unit(spec, unit, data)`` is the pure function a worker calls
for one unit of :func:`plan_measured_units` (the units have the shape of
:func:`svrobs_core.planning.plan_units`'); it returns a :class:`UnitResult`
that the store takes as it takes a simulated unit's. ``run_datasets`` runs
the chain on several datasets at once, one per repetition.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace
from typing import Any

import numpy as np

from ..array_types import Array, IntArray
from ..notes import Notes
from ..planning import MAX_CELLS_PER_UNIT, TARGET_CELLS_PER_UNIT, estimator_axis, plan_units
from ..seeding import seed_key
from ..spec import ExperimentSpec
from ..threads import blas_single_thread
from ..unit_result import Dataset, UnitResult
from .cells import Observer, run_cells
from .data import MeasuredData, StateModel, Transitions, rep_rollouts
from .spec import check_against_data


def _sigma_u(spec: ExperimentSpec, train: MeasuredData) -> float:
    """The spec's sigma_u, else the RMS of the training pool's inputs (1 when m = 0)."""
    if spec.measured.sigma_u is not None:
        sigma_u: float = spec.measured.sigma_u
        return sigma_u
    if train.m == 0:
        return 1.0
    u = np.concatenate(train.U, axis=0)
    with np.errstate(over="ignore"):  # inputs beyond 1e154: their cells say so
        return float(np.sqrt(np.mean(u * u)))


class _Job:
    """What every unit of a dataset job derives from the spec and the data."""

    def __init__(self, spec: ExperimentSpec, data: MeasuredData):
        layout = check_against_data(spec, data.n, data.m, data.rollouts, lengths=data.lengths)
        self.spec, self.layout = spec, layout
        self.train, _ = data.split(spec.measured.holdout)
        self.model = StateModel(ny=data.n, m=data.m, lags=spec.measured.lags)
        self.observer = Observer(
            C=layout.C, sigma_u=_sigma_u(spec, self.train), sigma_v=spec.measured.sigma_v
        )
        self.axis = estimator_axis(spec)

    def dataset(
        self, pool: Transitions, subsets: Sequence[IntArray], *, N: int, reps: list[int]
    ) -> Dataset:
        """The Dataset of one N over ``reps``: the chain once per distinct sample
        count (once in all when the rollouts have equal lengths)."""
        R, E = len(reps), len(self.axis.names)
        N0 = np.array([pool.samples(s) for s in subsets])
        notes = Notes((R, E))
        fields: dict[str, Array | None] = {}
        for n0 in np.unique(N0):
            rows = np.flatnonzero(N0 == n0)
            Z, F = pool.batch([subsets[int(i)] for i in rows], rows=self.model.estimated)
            part, part_notes = run_cells(
                self.spec,
                Z=Z,
                F=F,
                model=self.model,
                N=N,
                keys=[seed_key(0, 0, N, reps[i]) for i in rows],
                axis=self.axis,
                observer=self.observer,
            )
            if rows.size == R:
                fields, notes = part, part_notes
                break
            notes.embed(part_notes, rows)
            _merge(fields, part, rows, R)
        same = np.all(N0 == N0[0])
        return Dataset(N=int(N), N0=int(N0[0]) if same else N0, fields=fields, note_entries=notes)

    def result(self, reps: list[int], datasets: list[Dataset]) -> UnitResult:
        return UnitResult(
            system=self.layout.system,
            system_idx=0,
            sigma_w=self.layout.sigma_w,
            sigma_w_idx=0,
            reps=reps,
            axis=self.axis,
            datasets=datasets,
            n_reps=self.spec.reps,
        )


def _merge(
    fields: dict[str, Array | None], part: dict[str, Array | None], rows: IntArray, R: int
) -> None:
    """Write the rows ``rows`` of every field of ``part`` into ``fields`` (R, E, ...)."""
    for f, v in part.items():
        if v is None:  # a field without a value (coverage: no true system)
            fields[f] = None
            continue
        v = np.asarray(v)
        have = fields.get(f)
        if have is None:
            dtype = object if v.dtype in (object, bool) else v.dtype
            have = fields[f] = np.full(
                (R,) + v.shape[1:], None if dtype is object else np.nan, dtype
            )
        elif v.dtype == object and have.dtype != object:
            have = fields[f] = have.astype(object)
        have[rows] = v


def run_measured_unit(spec: ExperimentSpec, unit: dict[str, Any], data: MeasuredData) -> UnitResult:
    """Run one work unit of a dataset job on its data -> its records (a UnitResult).

    ``data``: the whole dataset (training pool and held-out rollouts); the
    unit's repetitions of each N use the rollouts of
    :func:`svrobs_core.measured.data.rep_rollouts`."""
    job = _Job(spec, data)
    reps = list(range(*unit["reps"]))
    pool = Transitions(job.model.lift(job.train))
    datasets = []
    with blas_single_thread():
        for N in sorted(unit["N"]):
            subsets = rep_rollouts(spec.seed, N, reps, job.train.rollouts)
            datasets.append(job.dataset(pool, subsets, N=N, reps=reps))
    return job.result(reps, datasets)


def run_datasets(spec: ExperimentSpec, datasets: Sequence[MeasuredData]) -> UnitResult:
    """The chain on several datasets of N rollouts each, dataset r as repetition r
    (vectorised over them; the spec's holdout and N are not used: N is the
    datasets' rollout count, all of them used)."""
    first = datasets[0]
    N = first.rollouts
    if any(d.rollouts != N for d in datasets):
        raise ValueError("every dataset must have the same number of rollouts")
    spec = replace(spec, N=(N,), measured=replace(spec.measured, holdout=0))
    job = _Job(spec, first)
    joined = MeasuredData(
        X=[x for d in datasets for x in d.X], U=[u for d in datasets for u in d.U]
    )
    pool = Transitions(job.model.lift(joined))
    reps = list(range(len(datasets)))
    subsets = [np.arange(r * N, (r + 1) * N) for r in reps]
    with blas_single_thread():
        ds = job.dataset(pool, subsets, N=N, reps=reps)
    return job.result(reps, [ds])


def plan_measured_units(
    spec: ExperimentSpec,
    *,
    lengths: Sequence[int] | None = None,
    n: int | None = None,
    m: int | None = None,
    max_cells: int = MAX_CELLS_PER_UNIT,
    target_cells: int = TARGET_CELLS_PER_UNIT,
    max_unit_bytes: int | None = None,
) -> list[dict[str, Any]]:
    """The work units of a dataset job (the shape of :func:`plan_units`').

    ``max_unit_bytes`` (with the dataset's ``lengths``, ``n``, ``m``): units
    are split by repetitions so that the regression data of a unit's largest
    N stay under it (the data of N rollouts, held for a chunk of repetitions:
    about 8 (3 d + 2 n) N0 bytes per repetition, d = n + m of the model's state)."""
    units = plan_units(spec, max_cells=max_cells, target_cells=target_cells)
    if max_unit_bytes is None:
        return units
    if lengths is None or n is None or m is None:
        raise ValueError("max_unit_bytes needs the dataset's lengths, n and m")
    model = StateModel(ny=n, m=m, lags=spec.measured.lags)
    pool = len(lengths) - spec.measured.holdout
    longest = np.sort(np.asarray(lengths[:pool], dtype=np.int64) - model.k0)[::-1]
    d = model.n + m
    out = []
    for u in units:
        N0 = int(longest[: max(u["N"])].sum())
        per_rep = 8 * (3 * d + 2 * model.n) * max(N0, 1)
        chunk = max(1, int(max_unit_bytes // per_rep))
        r0, r1 = u["reps"]
        out += [{**u, "reps": [s, min(r1, s + chunk)]} for s in range(r0, r1, chunk)]
    return out
