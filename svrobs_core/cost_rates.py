"""The cost model's per-operation constants and its records (:mod:`svrobs_core.workload`).

The constants are CPU seconds per operation and bytes per array, calibrated on
the development machine with ``bench/workload.py``
(docs/performance.md#the-service-against-the-core); :class:`UnitCost`,
:class:`DataShape` and :class:`JobCost` are what the model takes and returns.
"""

from __future__ import annotations

from dataclasses import dataclass

from .spec import ExperimentSpec

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
# per unit with gain: K, J*, norms of the true system (c0 + c1 n + c3 n^3)
TRUTH = (0.05, 0.0104, 1.6e-5)
CELL_TRUTH = (0.015, 1.9e-5)  # a dataset job: the same per cell's estimate (c0 + c3 n^3)
MC_DRAW = 1.2e-8  # Monte Carlo: per (row, step, run) and noise entry (draw + plant)
MC_CELL = 2.5e-10  # Monte Carlo: per (cell, step, run) and n (W + n) multiply-add
MC_STEP = 5.0e-6  # Monte Carlo: per step, the Python loop's calls
QR_REP = 1.0e-3  # SVR's QR path: per repetition (the calls of estimators.ridge_qr)
LONG_DOUBLE = 3.0e-8  # SVR's QR path: per long-double multiply-add of the refinement
BOOT_ELEM = 1.0e-9  # bootstrap: one elementwise multiply-add of its simulation
BOOT_SET = 1.0e-4  # bootstrap: per resampled dataset (its generator, draws, quantiles)
BOOT_REFIT = 1.0e-3  # bootstrap: per chunk of datasets and estimator column (the refit call)
CVX_SOLVE = 3.0e-3  # one small cvxpy + Clarabel solve (general-C gain design)
# SLS (bench/cost_model.py): T_fir n (n + p) scalar variables, each row of the
# affine constraint coupling n of them: solve and compile grow as T_fir n^2 (n + p)
SLS_SOLVE = 6.0e-3  # one SLS solve: fixed part
SLS_VAR = 3.2e-6  # one SLS solve: per scalar variable and state
SLS_COMPILE = 1.0e-2  # compiling the SLS program (once per unit): fixed part
SLS_COMPILE_VAR = 1.2e-5  # compiling: per scalar variable and state

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


def needs_cvxpy(spec: ExperimentSpec, orth: bool) -> bool:
    """Whether a unit imports cvxpy: SLS, or the gain design for a general C."""
    return spec.has("sls") or (spec.has("gain") and not orth)


def cell_seconds(stage: str, n: int) -> float:
    """CPU seconds of one cell of ``stage`` for an n-state system."""
    c0, c3, c6 = CELL_COST[stage]
    return c0 + c3 * n**3 + c6 * n**6


def truth_seconds(n: int) -> float:
    """K, J* and the norms of one n-state system (the true system's, once per unit)."""
    return TRUTH[0] + TRUTH[1] * n + TRUTH[2] * n**3


def sls_solve_seconds(T_fir: int, n: int, p: int) -> float:
    """One SLS solve (:mod:`svrobs_core.sls`) of a cell, for an n-state, p-output system."""
    return SLS_SOLVE + SLS_VAR * T_fir * n * (n + p) * n


def sls_compile_seconds(T_fir: int, n: int, p: int) -> float:
    """Compiling the SLS program, once per unit."""
    return SLS_COMPILE + SLS_COMPILE_VAR * T_fir * n * (n + p) * n
