"""Cost model of a dataset job's units (docs/measured.md#workload): the simulated
path's per-operation constants (:mod:`svrobs_core.cost_rates`) applied to the
operations of the measured path, from the dataset's shape."""

from __future__ import annotations

from typing import Any

import numpy as np

from ..array_types import FloatArray, IntArray
from ..cost_rates import (
    BASE_BYTES,
    CELL_COST,
    CELL_TRUTH,
    CVX_SOLVE,
    CVXPY_BYTES,
    DATASET,
    FLOP,
    KEY,
    RECORD_BYTES,
    RECORD_ENTRY_BYTES,
    SLS_VAR_BYTES,
    DataShape,
    UnitCost,
    cell_seconds,
    needs_cvxpy,
    sls_compile_seconds,
    sls_solve_seconds,
)
from ..gains import is_orthogonal
from ..spec import ExperimentSpec
from .data import StateModel
from .spec import data_layout


def need_data(data: DataShape | None) -> DataShape:
    """``data``, which a dataset job's cost needs."""
    if data is None:
        raise ValueError("a dataset job's cost needs its dataset's shape (data=DataShape)")
    return data


def _measured_sizes(
    spec: ExperimentSpec, data: DataShape | None
) -> tuple[StateModel, FloatArray, IntArray]:
    """(model, C, the training rollouts' transitions in the model's state, longest
    first) of a dataset job."""
    data = need_data(data)
    model = StateModel(ny=data.n, m=data.m, lags=spec.measured.lags)
    pool = np.asarray(data.lengths[: len(data.lengths) - spec.measured.holdout], dtype=np.int64)
    steps = np.sort(np.maximum(pool - model.k0, 0))[::-1]
    return model, data_layout(spec, data.n, data.m).C, steps


def measured_fixed_bytes(spec: ExperimentSpec, data: DataShape) -> int:
    """Bytes a worker holds for every unit of a dataset job: the interpreter (with
    cvxpy, and the compiled SLS program, when needed), the dataset's arrays and the
    training pool's regression columns (docs/measured.md#workload)."""
    model, C, steps = _measured_sizes(spec, data)
    n, d, total = model.n, model.n + data.m, int(np.sum(data.lengths))
    arrays = 8 * (data.n * (total + len(data.lengths)) + data.m * total)
    base = BASE_BYTES + (CVXPY_BYTES if needs_cvxpy(spec, bool(is_orthogonal(C))) else 0)
    if spec.has("sls"):
        base += SLS_VAR_BYTES * spec.sls_T_fir * n * (n + C.shape[0])
    return int(base + arrays + 8 * (d + n) * int(steps.sum()))


def measured_unit(spec: ExperimentSpec, unit: dict[str, Any], data: DataShape) -> UnitCost:
    """A dataset job's unit: per N (R repetitions, E cells each, N0 the transitions of
    the N longest training rollouts, an upper bound for every subsample) the regression
    data (copy, Gram, OLS residual) and the stages' per-cell work."""
    model, C, steps = _measured_sizes(spec, data)
    n, m, p, ny = model.n, data.m, C.shape[0], data.n
    d, E = n + m, spec.cells_per_rep
    orth = bool(is_orthogonal(C))
    R = unit["reps"][1] - unit["reps"][0]
    cpu, peak, kept = KEY, 0.0, 0.0
    for N in unit["N"]:
        N0, cells = int(steps[:N].sum()), R * E
        cpu += DATASET + KEY * R + FLOP * R * N0 * (d + ny + 2 * d * (d + ny) + 6 * ny * d)
        cpu += cells * sum(cell_seconds(st, max(n, p)) for st in CELL_COST if spec.has(st))
        if spec.has("cost") or spec.has("sls"):  # K, J* and the norms of each cell's estimate
            cpu += cells * (CELL_TRUTH[0] + CELL_TRUTH[1] * n**3)
        transient = 3 * 8.0 * R * (d + ny) * N0
        if spec.has("gain"):
            transient = max(transient, 3 * 8.0 * cells * n**4)
            if not orth:
                cpu += CVX_SOLVE * cells * (1 + n * p / 50.0)
        if spec.has("sls"):
            cpu += cells * sls_solve_seconds(spec.sls_T_fir, n, p)
        peak = max(peak, kept + transient)
        kept += cells * (RECORD_BYTES + RECORD_ENTRY_BYTES * (2 * n * n + n * m + 2 * n * p))
    if spec.has("sls"):
        cpu += sls_compile_seconds(spec.sls_T_fir, n, p)
    return UnitCost(cpu_seconds=float(cpu), peak_bytes=int(measured_fixed_bytes(spec, data) + peak))
