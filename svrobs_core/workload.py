"""Cost model of a work unit: CPU seconds and peak memory before running it.

``estimate_unit(spec, unit)`` -> :class:`UnitCost`, ``estimate_job(spec)`` ->
:class:`JobCost`: operation counts of the pipeline's stages (docs/science.md sections
1-8, in the order of :mod:`svrobs_core.pipeline`) times per-operation
constants calibrated on the development machine (``bench/workload.py``
prints the estimate against the measured CPU time and peak RSS), and the
bytes of the arrays the pipeline allocates. The model is meant for admission
(refuse work over a limit before it runs) and for planning units under a
memory cap (:func:`svrobs_core.planning.plan_units`): the target accuracy is
a factor of 3, and it is monotone in every size parameter.

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

from dataclasses import dataclass, replace

import numpy as np

from . import planning
from .data_factor import EXT_MAX_WORK
from .errors import SpecError
from .estimators import FALLBACK_CHUNK_BYTES, SVR_COND_LIMIT
from .gains import is_orthogonal
from .measured.data import StateModel
from .measured.runner import plan_measured_units
from .measured.spec import data_layout
from .spec import ExperimentSpec
from .uncertainty import BOOT_CHUNK_BYTES

# -- per-operation constants (seconds), calibrated with bench/workload.py ----
NORMAL = 1.2e-8  # one standard normal draw
FLOP = 5.5e-10  # one flop of the data path (simulation, Gram products, OLS residuals)
KEY = 1.5e-5  # per repetition: seeding its generator, its small solves
CALL = 1.5e-6  # one numpy call in a Python-level loop over time steps
DATASET = 1.5e-3  # per (unit, N): the fixed cost of the stage chain
# per cell of a stage, as c0 + c3 n^3 (+ c6 n^6): the vectorised small-matrix work
CELL_COST = {
    "estimate": (8.0e-6, 0.0, 0.0),  # records' JSON text, rmse
    "bounds": (3.0e-6, 6.5e-9, 0.0),
    "gain": (3.5e-5, 1.5e-7, 1.1e-10),  # Kalman SDA, Newton step (Kronecker LU: n^6)
    "cost": (1.0e-5, 3.0e-7, 0.0),  # exact (doubling) and stationary cost
    "cost_bound": (5.0e-6, 2.5e-8, 0.0),
}
TRUTH = (0.015, 1.9e-5)  # per unit with gain: K, J*, norms of the true system (c0 + c n^3)
MC_DRAW = 1.2e-8  # Monte Carlo: per (row, step, run) and noise entry (draw + plant)
MC_CELL = 2.5e-10  # Monte Carlo: per (cell, step, run) and n (W + n) multiply-add
MC_STEP = 5.0e-6  # Monte Carlo: per step, the Python loop's calls
QR_REP = 1.0e-3  # SVR's QR path: per repetition (the calls of estimators.ridge_qr)
LONG_DOUBLE = 3.0e-8  # SVR's QR path: per long-double multiply-add of the refinement
BOOT_ELEM = 1.0e-9  # bootstrap: one elementwise multiply-add of its simulation
BOOT_SET = 1.0e-4  # bootstrap: per resampled dataset (its generator, draws, quantiles)
BOOT_REFIT = 1.0e-3  # bootstrap: per chunk of datasets and estimator column (the refit call)
CVX_SOLVE = 3.0e-3  # one small cvxpy + Clarabel solve (general-C gain design)
SLS_SOLVE = 1.5e-3  # one SLS solve: fixed part
SLS_VAR = 8.0e-6  # one SLS solve: per scalar variable T_fir n (n + p)
SLS_COMPILE = 1.0e-2  # compiling the SLS program (once per unit): fixed part
SLS_COMPILE_VAR = 6.0e-6  # compiling: per scalar variable

# -- memory (bytes) ------------------------------------------------------------
BASE_BYTES = 50 * 2**20  # interpreter + numpy + scipy + svrobs_core
CVXPY_BYTES = 70 * 2**20  # importing cvxpy + Clarabel
SLS_VAR_BYTES = 3_200  # the compiled SLS program per scalar variable
RECORD_BYTES = 1_000  # per record kept: its JSON text and column values
RECORD_ENTRY_BYTES = 40  # per matrix entry of a record
GRAM_CHUNK_BYTES = 2 * 2**20  # svrobs_core.rollouts.CHUNK_BYTES
MC_BLOCK = 2**17  # svrobs_core.cost_mc: floats per Monte Carlo block
KRON_CHUNK_BYTES = 64 * 2**20  # svrobs_core.norms._CHUNK_BYTES


@dataclass(frozen=True)
class UnitCost:
    """Estimated CPU seconds and peak resident bytes of one work unit."""

    cpu_seconds: float
    peak_bytes: int


@dataclass(frozen=True)
class DataShape:
    """The shape of the dataset a job runs on: n measured channels (states, or
    outputs for the ARX state), m inputs, and T_i, the transitions of each rollout."""

    n: int
    m: int
    lengths: tuple[int, ...]


@dataclass(frozen=True)
class JobCost:
    """Estimated total CPU seconds, the largest unit's peak bytes, the unit count."""

    cpu_seconds: float
    peak_unit_bytes: int
    n_units: int


def _dims(spec: ExperimentSpec, si: int) -> tuple[int, int, int, bool]:
    s = spec.systems[si]
    return s.n, s.m, s.p, bool(is_orthogonal(s.C))


def _needs_cvxpy(spec: ExperimentSpec, orth: bool) -> bool:
    return spec.has("sls") or (spec.has("gain") and not orth)


def _cell(stage: str, n: int) -> float:
    c0, c3, c6 = CELL_COST[stage]
    return c0 + c3 * n**3 + c6 * n**6


def _ill_conditioned(spec: ExperimentSpec, si: int) -> bool:
    """Whether SVR's data are likely worse conditioned than estimators.SVR_COND_LIMIT:
    the states of an unstable system grow like rho(A)^T0, so cond(Z Z^T) like
    rho(A)^(2 T0) (a heuristic for the cost, not for the numbers)."""
    rho = float(np.max(np.abs(np.linalg.eigvals(spec.systems[si].A))))
    return rho > 1 and 2 * (spec.T0 - 1) * np.log10(rho) > np.log10(SVR_COND_LIMIT)


def _dataset(
    spec: ExperimentSpec, *, n, m, p, orth, N, R, mc_rows, ill=False, ill_data=False
) -> tuple[float, float, float]:
    """(cpu seconds, transient bytes, kept bytes) of one N of a unit with R reps;
    ``ill_data``: the data are likely ill-conditioned (:func:`_ill_conditioned`);
    ``ill``: SVR's cells take the QR path (:func:`_ill_conditioned`)."""
    T0, E = spec.T0, spec.cells_per_rep
    d, q = n + m, 2 * n + m
    K = T0 - 1 if spec.data == "all" else 1
    N0 = K * N
    cells = R * E
    # data (rollouts.gram_data): draws, simulation and Gram products per sample
    per_rep = 8.0 * N * (q * (T0 + 1) + d * T0)
    chunk = max(1, min(R, int(GRAM_CHUNK_BYTES // per_rep)))
    cpu = DATASET + KEY * R + CALL * T0 * -(-R // chunk)
    data_cpu = NORMAL * R * (m + n) * T0 * N + FLOP * R * N * (2 * n * q * T0 + 2 * (d + n) * d * K)
    cpu += data_cpu
    mem = chunk * per_rep
    rep_data = 8.0 * (d + n) * N0  # one repetition's Z and F
    kept_data = 0.0
    if any(e in ("ols", "shrunk-ols") for e in spec.estimators):
        # estimators.fit_ols keeps Z, F and forms the residual F - Theta Z
        cpu += FLOP * R * N0 * (2 * d * d + 6 * n * d)
        kept_data = R * rep_data
        mem = max(mem, 2 * kept_data)
    if "svr" in spec.estimators:  # the QR path of ill-conditioned cells, one chunk at a time
        chunk_data = max(rep_data, min(R * rep_data, FALLBACK_CHUNK_BYTES))
        mem = max(mem, kept_data + 5 * chunk_data)
        if ill:  # the data again (unless OLS kept them), QR, the long-double residual
            G = len(spec.gamma)
            cpu += (0.0 if kept_data else data_cpu) + R * (
                QR_REP + LONG_DOUBLE * N0 * (d + n) * (2 + G)
            )
    if spec.has("bounds") and spec.bounds_method != "paper":
        # data_factor keeps Z, F and takes an R-only QR of [Z^T F^T] per repetition,
        # again in long double where the data are ill-conditioned (capped per dataset)
        if not kept_data:
            kept_data = R * rep_data
            mem = max(mem, 2 * kept_data)
        work = N0 * (d + n) ** 2
        cpu += FLOP * R * 2 * work
        if ill_data:
            cpu += LONG_DOUBLE * R * min(work, EXT_MAX_WORK)
    if spec.has("bounds") and spec.bounds_method == "bootstrap":
        c_boot, m_boot = _bootstrap(spec, n=n, m=m, N=N, R=R, E=E, N0=N0)
        cpu += c_boot
        mem = max(mem, kept_data + m_boot)
    # per-cell work of the stages (small matrices, vectorised over the cells)
    h = max(n, p)
    cpu += cells * sum(_cell(st, h) for st in CELL_COST if spec.has(st))
    if spec.has("gain"):
        # kalman._stein: all cells' (n^2 x n^2) Kronecker systems at once
        mem = max(mem, 3 * 8.0 * cells * n**4)
        if not orth:
            cpu += CVX_SOLVE * cells * (1 + n * p / 50.0)
    if spec.has("cost"):
        cpu += _monte_carlo_cpu(spec, n=n, m=m, p=p, rows=mc_rows, E=E)
        mem = max(mem, _monte_carlo_bytes(spec, n=n, m=m, p=p, rows=mc_rows, E=E))
        mem = max(mem, 3.0 * min(8.0 * cells * n**4, KRON_CHUNK_BYTES))  # stationary Stein
    if spec.has("sls"):
        cpu += cells * (SLS_SOLVE + SLS_VAR * spec.sls_T_fir * n * (n + p))
    kept = cells * (RECORD_BYTES + RECORD_ENTRY_BYTES * (2 * n * n + n * m + 2 * n * p))
    return cpu, mem, kept


def _bootstrap(spec, *, n, m, N, R, E, N0) -> tuple[float, float]:
    """(cpu, bytes) of uncertainty.bootstrap_box: boot_reps datasets per repetition,
    each simulated for every cell's estimate and refitted by its estimator."""
    T0, d = spec.T0, n + m
    K = N0 // N
    sets = R * spec.boot_reps
    per_set = 8.0 * N * (E * (n * (T0 + 1) + (d + n) * K + m * T0) + (n + m) * T0 + n)
    chunks = -(-sets // max(1, int(BOOT_CHUNK_BYTES // per_set)))
    ols = sum(1 for e in spec.estimators if e != "svr")
    cpu = sets * (
        NORMAL * (m + n) * T0 * N
        + BOOT_ELEM * E * n * (n + m + 1) * T0 * N
        + FLOP * N0 * (E * 2 * d * (d + n) + ols * 6 * n * d)
    )
    cpu += CALL * chunks * T0 * (n + m + 2) + BOOT_SET * sets + BOOT_REFIT * chunks * E
    return cpu, max(per_set, min(sets * per_set, BOOT_CHUNK_BYTES)) * 1.5


def _mc_sizes(spec, *, n, m, p):
    T, runs = spec.horizon, spec.mc_runs
    q = m + n + p
    W = n + q
    return T, runs, q, W, max(1, min(T, MC_BLOCK // (runs * W)))


def _monte_carlo_cpu(spec, *, n, m, p, rows, E) -> float:
    """cost_mc.mc_cost_shared over ``rows`` repetitions of E cells each."""
    if rows == 0:
        return 0.0
    T, runs, q, W, _ = _mc_sizes(spec, n=n, m=m, p=p)
    steps = rows * T * runs
    return steps * (MC_DRAW * q + MC_CELL * E * n * (W + n)) + MC_STEP * T


def _monte_carlo_bytes(spec, *, n, m, p, rows, E) -> float:
    if rows == 0:
        return 0.0
    T, runs, q, W, h = _mc_sizes(spec, n=n, m=m, p=p)
    Xz = rows * W * (h + 1) * runs
    Ev = rows * E * (h + 1) * n * runs
    D = 2 * rows * E * n * h * runs  # the block's inputs and the einsum's product
    acc = 2 * rows * E * n * runs
    draw = 2 * h * runs * q
    return 8.0 * (Xz + Ev + D + acc + draw)


def _measured_sizes(spec: ExperimentSpec, data: DataShape) -> tuple:
    """(model, C, the training rollouts' transitions in the model's state, longest
    first) of a dataset job."""
    if data is None:
        raise ValueError("a dataset job's cost needs its dataset's shape (data=DataShape)")
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
    base = BASE_BYTES + (CVXPY_BYTES if _needs_cvxpy(spec, bool(is_orthogonal(C))) else 0)
    if spec.has("sls"):
        base += SLS_VAR_BYTES * spec.sls_T_fir * n * (n + C.shape[0])
    return int(base + arrays + 8 * (d + n) * int(steps.sum()))


def _measured_unit(spec: ExperimentSpec, unit: dict, data: DataShape) -> UnitCost:
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
        cpu += cells * sum(_cell(st, max(n, p)) for st in CELL_COST if spec.has(st))
        if spec.has("cost") or spec.has("sls"):  # K, J* and the norms of each cell's estimate
            cpu += cells * (TRUTH[0] + TRUTH[1] * n**3)
        transient = 3 * 8.0 * R * (d + ny) * N0
        if spec.has("gain"):
            transient = max(transient, 3 * 8.0 * cells * n**4)
            if not orth:
                cpu += CVX_SOLVE * cells * (1 + n * p / 50.0)
        if spec.has("sls"):
            cpu += cells * (SLS_SOLVE + SLS_VAR * spec.sls_T_fir * n * (n + p))
        peak = max(peak, kept + transient)
        kept += cells * (RECORD_BYTES + RECORD_ENTRY_BYTES * (2 * n * n + n * m + 2 * n * p))
    if spec.has("sls"):
        cpu += SLS_COMPILE + SLS_COMPILE_VAR * spec.sls_T_fir * n * (n + p)
    return UnitCost(cpu_seconds=float(cpu), peak_bytes=int(measured_fixed_bytes(spec, data) + peak))


def estimate_unit(spec: ExperimentSpec, unit: dict, *, data: DataShape | None = None) -> UnitCost:
    """CPU seconds and peak resident bytes of one unit of ``plan_units(spec)`` (of a
    dataset job: of ``plan_measured_units``, with its dataset's shape ``data``)."""
    if spec.measured is not None:
        return _measured_unit(spec, unit, data)
    si = unit["system"]
    n, m, p, orth = _dims(spec, si)
    r0, r1 = unit["reps"]
    R = r1 - r0
    limit = spec.reps if spec.mc_reps is None else spec.mc_reps
    mc_rows = max(0, min(r1, limit) - r0)
    cpu, peak, kept = 0.0, 0.0, 0.0
    ill_data = _ill_conditioned(spec, si)
    ill = "svr" in spec.estimators and ill_data
    for N in unit["N"]:
        c, transient, k = _dataset(
            spec, n=n, m=m, p=p, orth=orth, N=N, R=R, mc_rows=mc_rows, ill=ill, ill_data=ill_data
        )
        cpu += c
        peak = max(peak, kept + transient)
        kept += k
    base = BASE_BYTES
    if spec.has("gain") or spec.has("sls"):
        cpu += TRUTH[0] + TRUTH[1] * n**3
    if _needs_cvxpy(spec, orth):
        base += CVXPY_BYTES
    if spec.has("sls"):
        vars_ = spec.sls_T_fir * n * (n + p)
        cpu += SLS_COMPILE + SLS_COMPILE_VAR * vars_
        base += SLS_VAR_BYTES * vars_
    return UnitCost(cpu_seconds=float(cpu), peak_bytes=int(base + peak))


def plan_under_memory(spec: ExperimentSpec, *, max_unit_bytes: int | None = None) -> list[dict]:
    """:func:`~svrobs_core.planning.plan_units`, with a unit whose estimated peak
    memory (:func:`estimate_unit`) is above ``max_unit_bytes`` split further: first
    into its N values (unless ``reuse_gain``), then by repetitions, down to one
    repetition (which may still be above the cap: the caller compares
    ``estimate_job(spec, units).peak_unit_bytes`` with it). None: no cap. The
    records do not depend on the split."""
    units = planning.plan_units(spec)
    if max_unit_bytes is None:
        return units
    if spec.measured is not None:
        raise ValueError("a dataset job's memory cap: svrobs_core.measured.plan_measured_units")
    return [v for u in units for v in _fit_memory(spec, u, max_unit_bytes)]


def _fit_memory(spec: ExperimentSpec, unit: dict, cap: int, data=None) -> list[dict]:
    """``unit`` split so that each part's estimated peak bytes stay under ``cap``."""
    if estimate_unit(spec, unit, data=data).peak_bytes <= cap:
        return [unit]
    if len(unit["N"]) > 1 and not spec.reuse_gain:
        return [v for N in unit["N"] for v in _fit_memory(spec, {**unit, "N": [N]}, cap, data)]
    r0, r1 = unit["reps"]
    lo, hi = 1, r1 - r0  # the largest chunk of repetitions under the cap, by bisection
    while lo < hi:
        mid = (lo + hi + 1) // 2
        if estimate_unit(spec, {**unit, "reps": [r0, r0 + mid]}, data=data).peak_bytes <= cap:
            lo = mid
        else:
            hi = mid - 1
    return [{**unit, "reps": [s, min(r1, s + lo)]} for s in range(r0, r1, lo)]


def estimate_job(
    spec: ExperimentSpec, units: list[dict] | None = None, *, data: DataShape | None = None
) -> JobCost:
    """Total CPU seconds of ``units`` (default: ``plan_units(spec)``), the largest
    unit's peak bytes and the unit count (``data``: a dataset job's shape)."""
    if units is None:
        units = planning.plan_units(spec)
    seen: dict[tuple, UnitCost] = {}  # units differing only in sigma_w cost the same
    costs = []
    limit = spec.reps if spec.mc_reps is None else spec.mc_reps
    for u in units:
        r0, r1 = u["reps"]
        key = (u["system"], tuple(u["N"]), r1 - r0, max(0, min(r1, limit) - r0))
        if key not in seen:
            seen[key] = estimate_unit(spec, u, data=data)
        costs.append(seen[key])
    return JobCost(
        cpu_seconds=float(sum(c.cpu_seconds for c in costs)),
        peak_unit_bytes=max((c.peak_bytes for c in costs), default=0),
        n_units=len(units),
    )


class WorkloadError(SpecError):
    """A spec over a work or memory limit (the service answers 422, the CLI one line).

    ``field`` names the spec field whose reduction lowers the estimate most;
    ``estimate`` and ``limit`` are CPU seconds (``kind == "cpu"``) or bytes
    (``kind == "memory"``)."""

    def __init__(self, field: str, message: str, *, kind: str, estimate: float, limit: float):
        super().__init__(field, message)
        self.kind = kind
        self.estimate = estimate
        self.limit = limit


def smallest_unit_bytes(spec: ExperimentSpec, *, data: DataShape | None = None) -> int:
    """Peak bytes of the smallest unit the plan can make: one repetition of the
    largest N (all N together under ``reuse_gain``), for the largest system."""
    Ns = list(spec.N) if spec.reuse_gain else [max(spec.N)]
    return max(
        estimate_unit(
            spec, {"system": si, "sigma_w": 0, "N": Ns, "reps": [0, 1]}, data=data
        ).peak_bytes
        for si in range(len(spec.grid_systems))
    )


def _reductions(spec: ExperimentSpec, kind: str) -> dict[str, ExperimentSpec]:
    """The spec with one size field at its smallest, per field (for naming the culprit)."""
    if spec.measured is not None:  # a dataset job: no simulation fields
        out = {
            "N": replace(spec, N=(min(spec.N),)),
            "gamma": replace(spec, gamma=spec.gamma[:1]),
            "sls.T_fir": replace(spec, sls_T_fir=2),
            "estimators": replace(spec, estimators=spec.estimators[:1]),
        }
        if kind == "cpu":
            out["reps"] = replace(spec, reps=1)
        return out
    out = {
        "N": replace(spec, N=(1,)),
        "T0": replace(spec, T0=2),
        "gamma": replace(spec, gamma=spec.gamma[:1]),
        "mc_runs": replace(spec, mc_runs=2),
        "horizon": replace(spec, horizon=1),
        "sls.T_fir": replace(spec, sls_T_fir=2),
        "estimators": replace(spec, estimators=spec.estimators[:1]),
    }
    if spec.bounds_method == "bootstrap":
        out["boot_reps"] = replace(spec, boot_reps=2)
    if kind == "cpu":
        out["reps"] = replace(spec, reps=1, mc_reps=None if spec.mc_reps is None else 1)
        out["sigma_w"] = replace(spec, sigma_w=spec.sigma_w[:1])
        out["systems"] = replace(spec, systems=spec.systems[:1])
    return out


def _plan(spec: ExperimentSpec, max_unit_bytes: int | None, data: DataShape | None) -> list:
    """The units under the memory cap: :func:`plan_under_memory`, or for a dataset job
    :func:`~svrobs_core.measured.plan_measured_units` with what the cap leaves beside
    the bytes every unit holds, a unit still over the cap by this estimate split as
    :func:`plan_under_memory` splits one."""
    if spec.measured is None:
        return plan_under_memory(spec, max_unit_bytes=max_unit_bytes)
    if max_unit_bytes is None:
        return plan_measured_units(spec)
    budget = max(1, max_unit_bytes - measured_fixed_bytes(spec, data))
    units = plan_measured_units(
        spec, lengths=list(data.lengths), n=data.n, m=data.m, max_unit_bytes=budget
    )
    return [v for u in units for v in _fit_memory(spec, u, max_unit_bytes, data)]


def _culprit(spec: ExperimentSpec, kind: str, data: DataShape | None = None) -> str:
    def size(s):
        if kind == "cpu":
            return estimate_job(s, _plan(s, None, data), data=data).cpu_seconds
        return smallest_unit_bytes(s, data=data)

    sizes = {f: size(s) for f, s in _reductions(spec, kind).items()}
    return min(sizes, key=sizes.get)


def admit(
    spec: ExperimentSpec,
    *,
    max_cpu_seconds: float | None = None,
    max_unit_bytes: int | None = None,
    data: DataShape | None = None,
) -> tuple[list[dict], JobCost]:
    """The work units of ``spec`` planned under the memory cap, and their cost,
    or :class:`WorkloadError` if the smallest unit is over ``max_unit_bytes``
    or the job over ``max_cpu_seconds`` (None: no limit). The message gives the
    estimate and the limit; ``field`` the spec field that weighs most. A dataset
    job needs its dataset's shape ``data``."""
    if spec.measured is not None and data is None:
        raise ValueError("a dataset job's admission needs its dataset's shape (data=DataShape)")
    if max_unit_bytes is not None:
        need = smallest_unit_bytes(spec, data=data)
        if need > max_unit_bytes:
            raise WorkloadError(
                _culprit(spec, "memory", data),
                f"one work unit (a single repetition) needs an estimated {need / 2**20:.0f} MB,"
                f" over the limit of {max_unit_bytes / 2**20:.0f} MB",
                kind="memory",
                estimate=need,
                limit=max_unit_bytes,
            )
    floor = spec.n_cells * CELL_COST["estimate"][0]  # every cell builds its record at least
    if max_cpu_seconds is not None and floor > max_cpu_seconds:
        raise WorkloadError(
            "reps" if spec.reps > len(spec.N) else "N",
            f"the job ({spec.n_cells} records) needs an estimated {floor:.0f} CPU seconds or"
            f" more, over the limit of {max_cpu_seconds:.0f} s",
            kind="cpu",
            estimate=floor,
            limit=max_cpu_seconds,
        )
    units = _plan(spec, max_unit_bytes, data)
    job = estimate_job(spec, units, data=data)
    if max_cpu_seconds is not None and job.cpu_seconds > max_cpu_seconds:
        raise WorkloadError(
            _culprit(spec, "cpu", data),
            f"the job needs an estimated {job.cpu_seconds:.0f} CPU seconds,"
            f" over the limit of {max_cpu_seconds:.0f} s",
            kind="cpu",
            estimate=job.cpu_seconds,
            limit=max_cpu_seconds,
        )
    return units, job


__all__ = [
    "DataShape",
    "JobCost",
    "UnitCost",
    "WorkloadError",
    "admit",
    "estimate_job",
    "estimate_unit",
    "plan_under_memory",
    "smallest_unit_bytes",
]
