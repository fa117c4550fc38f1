"""Work units of a grid and the estimator axis of a dataset
(docs/science.md#12-multi-rollout-collection, docs/spec.md#grid-size).

``plan_units(spec)`` splits the grid into JSON-able work units; the records
do not depend on how the grid is split (docs/science.md#14-randomness-and-reproducibility).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from .array_types import FloatArray
from .spec import ExperimentSpec

MAX_CELLS_PER_UNIT = 20_000
TARGET_CELLS_PER_UNIT = 2_000  # ~0.1-1 s of work: amortises a worker's per-unit cost


def plan_units(
    spec: ExperimentSpec,
    *,
    max_cells: int = MAX_CELLS_PER_UNIT,
    target_cells: int = TARGET_CELLS_PER_UNIT,
) -> list[dict[str, Any]]:
    """Work units ``{"system", "sigma_w", "N": [...], "reps": [start, stop]}``.

    Consecutive N values of one (system, sigma_w) are packed into a unit
    while it stays within ``target_cells`` (all N at once when ``reuse_gain``
    couples them); a single N over ``max_cells`` is split by repetitions.
    :func:`svrobs_core.workload.plan_under_memory` splits them further under a
    memory cap. The records do not depend on the split.
    """
    return _plan(spec, max_cells=max_cells, target_cells=target_cells)


def _plan(spec: ExperimentSpec, *, max_cells: int, target_cells: int) -> list[dict[str, Any]]:
    per_N = spec.cells_per_rep * spec.reps
    n_groups: list[list[int]]
    if spec.reuse_gain:
        n_groups = [list(spec.N)]
    else:
        n_groups = []
        group: list[int] = []
        for N in sorted(spec.N):
            if group and per_N * (len(group) + 1) > target_cells:
                n_groups.append(group)
                group = []
            group.append(N)
        n_groups.append(group)
    blocks: list[tuple[list[int], int, int]] = []  # the units of one (system, sigma_w)
    for Ns in n_groups:
        chunk = max(1, min(spec.reps, max_cells // (spec.cells_per_rep * len(Ns))))
        blocks += [(Ns, r0, min(spec.reps, r0 + chunk)) for r0 in range(0, spec.reps, chunk)]
    return [
        {"system": si, "sigma_w": wi, "N": list(Ns), "reps": [r0, r1]}
        for si, wi in _pairs(spec)
        for Ns, r0, r1 in blocks
    ]


def _pairs(spec: ExperimentSpec) -> list[tuple[int, int]]:
    """The (system, sigma_w) indices of the grid; a dataset job has the one pair (0, 0)."""
    if spec.measured is not None:
        return [(0, 0)]
    return [(si, wi) for si in range(len(spec.systems)) for wi in range(len(spec.sigma_w))]


def unit_cells(spec: ExperimentSpec, unit: dict[str, Any]) -> int:
    """The number of records (cells) a work unit of :func:`plan_units` gives."""
    r0: int
    r1: int
    r0, r1 = unit["reps"]
    return len(unit["N"]) * (r1 - r0) * spec.cells_per_rep


@dataclass
class EstimatorAxis:
    """The estimator axis E of one dataset: (estimator name, gamma or None)."""

    names: list[str]
    gammas: list[float | None]

    @property
    def gamma_array(self) -> FloatArray:  # 0 for ols: the bounds use gamma = 0
        return np.array([0.0 if g is None else g for g in self.gammas])


def estimator_axis(spec: ExperimentSpec) -> EstimatorAxis:
    """The (estimator, gamma) columns of every dataset: OLS once, the others per gamma."""
    names: list[str] = []
    gammas: list[float | None] = []
    for e in spec.estimators:
        if e == "ols":
            names.append(e)
            gammas.append(None)
        else:
            names += [e] * len(spec.gamma)
            gammas += list(spec.gamma)
    return EstimatorAxis(names, gammas)
