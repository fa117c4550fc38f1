"""Cost model of a work unit: CPU seconds and peak memory before running it.

``estimate_unit(spec, unit)`` -> :class:`UnitCost` (vectorised over the unit's N),
``estimate_job(spec)`` ->
:class:`JobCost`: operation counts of the pipeline's stages (docs/science.md sections
1-8, in the order of :mod:`svrobs_core.pipeline`) times per-operation
constants calibrated on the development machine (``bench/workload.py``
prints the estimate against the measured CPU time and peak RSS), and the
bytes of the arrays the pipeline allocates. The model is meant for admission
(refuse work over a limit before it runs) and for planning units under a
memory cap (:func:`svrobs_core.planning.plan_units`): the target accuracy is
a factor of 3, and it is monotone in every size parameter. Admission itself
(:mod:`svrobs_core.admission`) sums it over the grid's axes in closed form.

``peak_bytes`` is the resident size of a worker process running the unit:
the interpreter with the core imported (cvxpy too when the unit needs it)
plus the unit's largest working set and the records it keeps.

A job on a dataset (``spec.measured``) is costed from the dataset's shape
(:class:`DataShape`: n, m and every rollout's length), passed as ``data=``:
the same per-operation constants applied to the measured path's operations
(docs/measured.md#workload), its units planned by
:func:`svrobs_core.measured.plan_measured_units` under the memory cap.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from . import planning
from .array_types import FloatArray
from .cost_rates import (
    BASE_BYTES,
    BOOT_ELEM,
    BOOT_REFIT,
    BOOT_SET,
    CALL,
    CELL_COST,
    CVX_SOLVE,
    CVXPY_BYTES,
    DATASET,
    FLOP,
    GRAM_CHUNK_BYTES,
    KEY,
    KRON_CHUNK_BYTES,
    LONG_DOUBLE,
    MC_BLOCK,
    MC_CELL,
    MC_DRAW,
    MC_STEP,
    NORMAL,
    QR_REP,
    RECORD_BYTES,
    RECORD_ENTRY_BYTES,
    SLS_VAR_BYTES,
    DataShape,
    JobCost,
    UnitCost,
    cell_seconds,
    needs_cvxpy,
    sls_compile_seconds,
    sls_solve_seconds,
    truth_seconds,
)
from .data_factor import EXT_MAX_WORK
from .errors import SpecError
from .estimators import FALLBACK_CHUNK_BYTES
from .measured.workload import measured_unit, need_data
from .spec import ExperimentSpec
from .system_kinds import (
    Kind,
    SystemKinds,
    SystemTable,
    _dims,
    _ill_conditioned,
    system_dims,
    system_kinds,
    system_table,
)
from .uncertainty import BOOT_CHUNK_BYTES
from .wishart_draws import dataset_columns, dataset_draws


def _floor(x: FloatArray) -> FloatArray:
    """floor of positive x (np.trunc: several times faster than np.floor on arrays)."""
    return np.trunc(x)


def _ceil(x: FloatArray) -> FloatArray:
    """ceil of positive x."""
    t = np.trunc(x)
    return t + (t < x)


def _dataset(
    spec: ExperimentSpec,
    *,
    n: int,
    m: int,
    p: int,
    orth: bool,
    N: list[int] | FloatArray,
    R: int,
    mc_rows: int,
    ill: bool = False,
    ill_data: bool = False,
) -> tuple[FloatArray, FloatArray, float]:
    """(cpu seconds, transient bytes, kept bytes) of each N of ``N`` (an array) in a
    unit with R reps: the first two are arrays over N, the kept bytes the same for
    every N; ``ill_data``: the data are likely ill-conditioned
    (:func:`_ill_conditioned`); ``ill``: SVR's cells take the QR path."""
    N = np.asarray(N, dtype=np.float64)
    T0, E = spec.T0, spec.cells_per_rep
    d, q = n + m, 2 * n + m
    K = T0 - 1 if spec.data == "all" else 1
    N0 = K * N
    cells = R * E
    # data (rollouts.gram_data): draws, simulation and Gram products per sample
    per_rep = 8.0 * N * (q * (T0 + 1) + d * T0)
    chunk = np.maximum(1, np.minimum(R, _floor(GRAM_CHUNK_BYTES / per_rep)))
    cpu = DATASET + KEY * R + CALL * T0 * _ceil(R / chunk)
    data_cpu = NORMAL * R * (m + n) * T0 * N + FLOP * R * N * (2 * n * q * T0 + 2 * (d + n) * d * K)
    cpu = cpu + data_cpu
    mem = chunk * per_rep
    rep_data = 8.0 * (d + n) * N0  # one repetition's Z and F
    kept_data, keeps = 0.0 * N, False
    if any(e in ("ols", "shrunk-ols") for e in spec.estimators):
        # estimators.fit_ols keeps Z, F and forms the residual F - Theta Z
        cpu = cpu + FLOP * R * N0 * (2 * d * d + 6 * n * d)
        kept_data, keeps = R * rep_data, True
        mem = np.maximum(mem, 2 * kept_data)
    if "svr" in spec.estimators:  # the QR path of ill-conditioned cells, one chunk at a time
        chunk_data = np.maximum(rep_data, np.minimum(R * rep_data, FALLBACK_CHUNK_BYTES))
        mem = np.maximum(mem, kept_data + 5 * chunk_data)
        if ill:  # the data again (unless OLS kept them), QR, the long-double residual
            G = len(spec.gamma)
            cpu = (
                cpu
                + (0.0 if keeps else data_cpu)
                + R * (QR_REP + LONG_DOUBLE * N0 * (d + n) * (2 + 2 * G))
            )
    if spec.has("bounds") and spec.bounds_method != "paper":
        # data_factor keeps Z, F and takes an R-only QR of [Z^T F^T] per repetition,
        # again in long double where the data are ill-conditioned (capped per dataset)
        if not keeps:
            kept_data, keeps = R * rep_data, True
            mem = np.maximum(mem, 2 * kept_data)
        work = N0 * (d + n) ** 2
        cpu = cpu + FLOP * R * 2 * work
        if ill_data:
            cpu = cpu + LONG_DOUBLE * R * np.minimum(work, EXT_MAX_WORK)
    if spec.has("bounds") and spec.bounds_method == "bootstrap":
        c_boot, m_boot = _bootstrap(spec, n=n, m=m, N=N, R=R, E=E)
        cpu = cpu + c_boot
        mem = np.maximum(mem, kept_data + m_boot)
    # per-cell work of the stages (small matrices, vectorised over the cells)
    h = max(n, p)
    cpu = cpu + cells * sum(cell_seconds(st, h) for st in CELL_COST if spec.has(st))
    if spec.has("gain"):
        # kalman._stein: all cells' (n^2 x n^2) Kronecker systems at once
        mem = np.maximum(mem, 3 * 8.0 * cells * n**4)
        if not orth:
            cpu = cpu + CVX_SOLVE * cells * (1 + n * p / 50.0)
    if spec.has("cost"):
        cpu = cpu + _monte_carlo_cpu(spec, n=n, m=m, p=p, rows=mc_rows, E=E)
        mem = np.maximum(mem, _monte_carlo_bytes(spec, n=n, m=m, p=p, rows=mc_rows, E=E))
        mem = np.maximum(mem, 3.0 * min(8.0 * cells * n**4, KRON_CHUNK_BYTES))  # stationary Stein
    if spec.has("sls"):
        cpu = cpu + cells * sls_solve_seconds(spec.sls_T_fir, n, p)
    kept = cells * (RECORD_BYTES + RECORD_ENTRY_BYTES * (2 * n * n + n * m + 2 * n * p))
    return cpu, mem, kept


def _bootstrap(
    spec: ExperimentSpec, *, n: int, m: int, N: FloatArray, R: int, E: int
) -> tuple[FloatArray, FloatArray]:
    """(cpu, bytes) of uncertainty.bootstrap_box: boot_reps datasets per repetition,
    each simulated for every cell's estimate and refitted by its estimator."""
    T0, d = spec.T0, n + m
    K = spec.T0 - 1 if spec.data == "all" else 1
    sets = R * spec.boot_reps
    # the simulated columns and random numbers per set (docs/uncertainty.md#how-the-resamples-are-drawn)
    shape: dict[str, Any] = {
        "n": n,
        "m": m,
        "T0": T0,
        "x0_std": spec.x0_std,
        "draws": spec.draws,
    }
    Nc, draws = dataset_columns(N, **shape), dataset_draws(N, **shape)
    per_set = 8.0 * Nc * (E * (n * (T0 + 1) + (d + n) * K + m * T0) + (n + m) * T0 + n)
    chunks = _ceil(sets / np.maximum(1, _floor(BOOT_CHUNK_BYTES / per_set)))
    ols = sum(1 for e in spec.estimators if e != "svr")
    cpu = sets * (
        NORMAL * draws
        + BOOT_ELEM * E * n * (n + m + 1) * T0 * Nc
        + FLOP * K * Nc * (E * 2 * d * (d + n) + ols * 6 * n * d)
    )
    cpu += CALL * chunks * T0 * (n + m + 2) + BOOT_SET * sets + BOOT_REFIT * chunks * E
    return cpu, np.maximum(per_set, np.minimum(sets * per_set, BOOT_CHUNK_BYTES)) * 1.5


def _mc_sizes(spec: ExperimentSpec, *, n: int, m: int, p: int) -> tuple[int, int, int, int, int]:
    T, runs = spec.horizon, spec.mc_runs
    q = m + n + p
    W = n + q
    return T, runs, q, W, max(1, min(T, MC_BLOCK // (runs * W)))


def _monte_carlo_cpu(spec: ExperimentSpec, *, n: int, m: int, p: int, rows: int, E: int) -> float:
    """cost_mc.mc_cost_shared over ``rows`` repetitions of E cells each."""
    if rows == 0:
        return 0.0
    T, runs, q, W, _ = _mc_sizes(spec, n=n, m=m, p=p)
    steps = rows * T * runs
    return steps * (MC_DRAW * q + MC_CELL * E * n * (W + n)) + MC_STEP * T


def _monte_carlo_bytes(spec: ExperimentSpec, *, n: int, m: int, p: int, rows: int, E: int) -> float:
    if rows == 0:
        return 0.0
    T, runs, q, W, h = _mc_sizes(spec, n=n, m=m, p=p)
    Xz = rows * W * (h + 1) * runs
    Ev = rows * E * (h + 1) * n * runs
    D = 2 * rows * E * n * h * runs  # the block's inputs and the einsum's product
    acc = 2 * rows * E * n * runs
    draw = 2 * h * runs * q
    return 8.0 * (Xz + Ev + D + acc + draw)


def estimate_unit(
    spec: ExperimentSpec,
    unit: dict[str, Any],
    *,
    data: DataShape | None = None,
    kinds: SystemKinds | None = None,
) -> UnitCost:
    """CPU seconds and peak resident bytes of one unit of ``plan_units(spec)`` (of a
    dataset job: of ``plan_measured_units``, with its dataset's shape ``data``);
    ``kinds``: :func:`system_kinds` of the spec, if already made."""
    if spec.measured is not None:
        return measured_unit(spec, unit, need_data(data))
    si = unit["system"]
    if kinds is None:
        n, m, p, orth = _dims(spec, si)
        ill_data = _ill_conditioned(spec, si)
    else:
        n, m, p, orth, ill_data = kinds.kind(si)
    return _unit_cost(spec, unit, (n, m, p, orth, ill_data))


def _unit_cost(spec: ExperimentSpec, unit: dict[str, Any], kind: Kind) -> UnitCost:
    """:func:`estimate_unit` of a simulated job's unit whose system is of ``kind``."""
    n, m, p, orth, ill_data = kind
    r0, r1 = unit["reps"]
    R = r1 - r0
    limit = spec.reps if spec.mc_reps is None else spec.mc_reps
    mc_rows = max(0, min(r1, limit) - r0)
    ill = "svr" in spec.estimators and ill_data
    c, transient, kept = _dataset(
        spec, n=n, m=m, p=p, orth=orth, N=unit["N"], R=R, mc_rows=mc_rows, ill=ill,
        ill_data=ill_data,
    )  # fmt: skip
    cpu = float(np.sum(c)) + unit_fixed_seconds(spec, n=n, p=p)
    # the records of the unit's earlier N are kept while the next one runs
    peak = float(np.max(np.arange(len(unit["N"])) * kept + transient))
    return UnitCost(
        cpu_seconds=cpu, peak_bytes=int(unit_base_bytes(spec, n=n, p=p, orth=orth) + peak)
    )


def unit_fixed_seconds(spec: ExperimentSpec, *, n: int, p: int) -> float:
    """CPU seconds of a (simulated) unit beside its N: the true system's K, J* and
    norms, and compiling the SLS program."""
    cpu = 0.0
    if spec.has("gain") or spec.has("sls"):
        cpu += truth_seconds(n)
    if spec.has("sls"):
        cpu += sls_compile_seconds(spec.sls_T_fir, n, p)
    return cpu


def unit_base_bytes(spec: ExperimentSpec, *, n: int, p: int, orth: bool) -> float:
    """Bytes of a worker process before its unit's arrays: the interpreter, cvxpy
    when needed, the compiled SLS program."""
    base = BASE_BYTES
    if needs_cvxpy(spec, orth):
        base += CVXPY_BYTES
    if spec.has("sls"):
        base += SLS_VAR_BYTES * spec.sls_T_fir * n * (n + p)
    return base


# estimates by (system's kind, or the system; N, first and last repetition)
_Memo = dict[tuple[int, tuple[int, ...], int, int], UnitCost]


def plan_under_memory(
    spec: ExperimentSpec,
    *,
    max_unit_bytes: int | None = None,
    max_unit_seconds: float | None = None,
    kinds: SystemKinds | None = None,
) -> list[dict[str, Any]]:
    """:func:`~svrobs_core.planning.plan_units`, with a unit whose estimated peak
    memory (:func:`estimate_unit`) is above ``max_unit_bytes``, or whose CPU seconds
    are above ``max_unit_seconds``, split further: first into its N values (unless
    ``reuse_gain``), then by repetitions, down to one repetition (which may still be
    above a cap: :func:`svrobs_core.admission.admit` refuses it). None: no cap. The
    records do not depend on the split. ``kinds``: :func:`system_kinds` of the spec,
    if already made."""
    units = planning.plan_units(spec)
    if max_unit_bytes is None and max_unit_seconds is None:
        return units
    if spec.measured is not None:
        raise ValueError("a dataset job's memory cap: svrobs_core.measured.plan_measured_units")
    memo: _Memo = {}
    kinds = system_kinds(spec) if kinds is None else kinds
    return [
        v for u in units for v in _fit(spec, u, max_unit_bytes, max_unit_seconds, None, memo, kinds)
    ]


def _fits(
    spec: ExperimentSpec,
    unit: dict[str, Any],
    mem_cap: float | None,
    cpu_cap: float | None,
    data: DataShape | None,
    memo: _Memo,
    kinds: SystemKinds | None = None,
) -> bool:
    r0, r1 = unit["reps"]
    si = unit["system"] if kinds is None else int(kinds.of[unit["system"]])
    key = (si, tuple(unit["N"]), r0, r1)  # units differing in sigma_w or system alone
    if key not in memo:
        memo[key] = estimate_unit(spec, unit, data=data, kinds=kinds)
    cost = memo[key]
    return (mem_cap is None or cost.peak_bytes <= mem_cap) and (
        cpu_cap is None or cost.cpu_seconds <= cpu_cap
    )


def _fit(
    spec: ExperimentSpec,
    unit: dict[str, Any],
    mem_cap: float | None,
    cpu_cap: float | None,
    data: DataShape | None = None,
    memo: _Memo | None = None,
    kinds: SystemKinds | None = None,
) -> list[dict[str, Any]]:
    """``unit`` split so that each part's estimated peak bytes stay under ``mem_cap``
    and its CPU seconds under ``cpu_cap`` (None: no cap); ``kinds``: the simulated
    spec's :func:`system_kinds`."""
    memo = {} if memo is None else memo
    if _fits(spec, unit, mem_cap, cpu_cap, data, memo, kinds):
        return [unit]
    if len(unit["N"]) > 1 and not spec.reuse_gain:
        return [
            v
            for N in unit["N"]
            for v in _fit(spec, {**unit, "N": [N]}, mem_cap, cpu_cap, data, memo, kinds)
        ]
    r0, r1 = unit["reps"]
    lo, hi = 1, r1 - r0  # the largest chunk of repetitions under the caps, by bisection
    while lo < hi:
        mid = (lo + hi + 1) // 2
        if _fits(spec, {**unit, "reps": [r0, r0 + mid]}, mem_cap, cpu_cap, data, memo, kinds):
            lo = mid
        else:
            hi = mid - 1
    return [{**unit, "reps": [s, min(r1, s + lo)]} for s in range(r0, r1, lo)]


def estimate_job(
    spec: ExperimentSpec,
    units: list[dict[str, Any]] | None = None,
    *,
    data: DataShape | None = None,
    kinds: SystemKinds | None = None,
) -> JobCost:
    """Total CPU seconds of ``units`` (default: ``plan_units(spec)``), the largest
    unit's peak bytes and the unit count (``data``: a dataset job's shape; ``kinds``:
    a simulated job's :func:`system_kinds`, if already made)."""
    if units is None:
        units = planning.plan_units(spec)
    if kinds is None and spec.measured is None:
        kinds = system_kinds(spec)
    seen: dict[
        tuple[int, tuple[int, ...], int, int], UnitCost
    ] = {}  # units differing only in sigma_w, or in systems of one kind, cost the same
    costs = []
    limit = spec.reps if spec.mc_reps is None else spec.mc_reps
    for u in units:
        r0, r1 = u["reps"]
        si = u["system"] if kinds is None else int(kinds.of[u["system"]])
        key = (si, tuple(u["N"]), r1 - r0, max(0, min(r1, limit) - r0))
        if key not in seen:
            seen[key] = estimate_unit(spec, u, data=data, kinds=kinds)
        costs.append(seen[key])
    return JobCost(
        cpu_seconds=float(sum(c.cpu_seconds for c in costs)),
        peak_unit_bytes=max((c.peak_bytes for c in costs), default=0),
        n_units=len(units),
    )


class WorkloadError(SpecError):
    """A spec over a work or memory limit (the service answers 422, the CLI one line).

    ``field`` names the spec field whose reduction lowers the estimate most;
    ``estimate`` and ``limit`` are the job's CPU seconds (``kind == "cpu"``), one
    unit's CPU seconds (``"unit_cpu"``) or peak bytes (``"memory"``), the job's cells
    (``"cells"``) or stored bytes (``"stored"``): :mod:`svrobs_core.admission`."""

    def __init__(self, field: str, message: str, *, kind: str, estimate: float, limit: float):
        super().__init__(field, message)
        self.kind = kind
        self.estimate = estimate
        self.limit = limit


__all__ = [
    "DataShape",
    "JobCost",
    "SystemKinds",
    "SystemTable",
    "UnitCost",
    "WorkloadError",
    "estimate_job",
    "estimate_unit",
    "plan_under_memory",
    "system_dims",
    "system_kinds",
    "system_table",
]
