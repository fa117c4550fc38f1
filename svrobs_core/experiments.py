"""Grid -> work units -> section 10 records (SPEC sections 1-10).

``plan_units(spec)`` splits the grid into JSON-able work units (all
repetitions and gammas of one system, sigma_w and N; all N at once when
``reuse_gain`` couples them); ``run_unit(spec, unit)`` is the one pure
function a worker calls; ``run_spec`` runs every unit in process.
Records do not depend on how the grid is split (SPEC section 1).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Iterator

import numpy as np

from . import bounds as _bounds
from . import estimators as _est
from .records import empty_record, json_value
from .rollouts import MC_STREAM, collect, rng_for, seed_key
from .spec import STAGES, ExperimentSpec

MAX_CELLS_PER_UNIT = 20_000


def plan_units(spec: ExperimentSpec, max_cells: int = MAX_CELLS_PER_UNIT) -> list[dict]:
    """Work units ``{"system", "sigma_w", "N": [...], "reps": [start, stop]}``."""
    n_groups = [list(spec.N)] if spec.reuse_gain else [[N] for N in spec.N]
    units = []
    for si in range(len(spec.systems)):
        for wi in range(len(spec.sigma_w)):
            for Ns in n_groups:
                per_rep = spec.cells_per_rep * len(Ns)
                chunk = max(1, min(spec.reps, max_cells // per_rep))
                for r0 in range(0, spec.reps, chunk):
                    units.append(
                        {"system": si, "sigma_w": wi, "N": sorted(Ns),
                         "reps": [r0, min(spec.reps, r0 + chunk)]}
                    )
    return units


@dataclass
class _Axis:
    """The estimator axis E of one dataset: (estimator name, gamma or None)."""

    names: list[str]
    gammas: list[float | None]

    @property
    def gamma_array(self) -> np.ndarray:  # 0 for ols: the bounds use gamma = 0
        return np.array([0.0 if g is None else g for g in self.gammas])


def _estimator_axis(spec: ExperimentSpec) -> _Axis:
    names, gammas = [], []
    for e in spec.estimators:
        if e == "ols":
            names.append(e)
            gammas.append(None)
        else:
            names += [e] * len(spec.gamma)
            gammas += list(spec.gamma)
    return _Axis(names, gammas)


def _estimate(spec: ExperimentSpec, Z, F, axis: _Axis) -> np.ndarray:
    """Theta for every (rep, estimator/gamma): (R, E, n, d); SPEC section 2."""
    parts = []
    theta_ols = None
    for e in spec.estimators:
        if e == "ols":
            theta_ols = _est.fit_ols(Z, F) if theta_ols is None else theta_ols
            parts.append(theta_ols[:, None])
        elif e == "svr":
            parts.append(_est.fit_svr(Z, F, spec.gamma, spec.loss_scale))
        else:  # shrunk-ols
            theta_ols = _est.fit_ols(Z, F) if theta_ols is None else theta_ols
            parts.append(_est.shrunk_ols(theta_ols, spec.gamma))
    return np.concatenate(parts, axis=1)


def _rmse(X, X_true) -> np.ndarray:
    return np.sqrt(np.mean((X - X_true) ** 2, axis=(-2, -1)))


class _Notes:
    """Per-cell reasons for null fields, shape (R, E)."""

    def __init__(self, shape):
        self.items = np.empty(shape, dtype=object)
        for idx in np.ndindex(shape):
            self.items[idx] = []

    def add(self, mask, text: str):
        for idx in zip(*np.nonzero(np.broadcast_to(mask, self.items.shape))):
            if text not in self.items[idx]:
                self.items[idx].append(text)


def _run_dataset(spec, si, wi, N, reps, axis, prev_gain=None):
    """All stages for one (system, sigma_w, N) and a range of reps -> (fields, notes, gain)."""
    system = spec.systems[si]
    sigma_w = spec.sigma_w[wi]
    n, m = system.n, system.m
    keys = [seed_key(si, wi, N, r) for r in reps]
    Z, F = collect(system, sigma_w, N, spec.T0, spec.seed, keys, spec.data, spec.x0_std)
    N0 = Z.shape[-1]
    theta = _estimate(spec, Z, F, axis)
    A_hat, B_hat = theta[..., :n], theta[..., n:]
    R, E = theta.shape[:2]
    out: dict[str, np.ndarray] = {
        "A_hat": A_hat, "B_hat": B_hat,
        "rmse_A": _rmse(A_hat, system.A), "rmse_B": _rmse(B_hat, system.B),
    }
    notes = _Notes((R, E))
    skipped = [st for st in STAGES if not spec.has(st)]
    if skipped:
        notes.add(True, "stages not run: " + ", ".join(skipped))
    gamma = axis.gamma_array
    stages = _run_stages(spec, system, sigma_w, N, N0, keys, A_hat, B_hat, gamma, axis,
                         out, notes, prev_gain)
    return out, notes, N0, stages


def _run_stages(spec, system, sigma_w, N, N0, keys, A_hat, B_hat, gamma, axis, out, notes,
                prev_gain):
    if not spec.has("bounds"):
        return None
    rad = _bounds.radii(
        n=system.n, m=system.m, N=N, N0=N0, T0=spec.T0, sigma_u=system.sigma_u,
        sigma_w=sigma_w, gamma=gamma, M=spec.M, delta=spec.delta,
    )
    b = _bounds.evaluate_bounds(A_hat, B_hat, gamma, rad, system.A, system.B)
    R, E = A_hat.shape[:2]
    shape = (R, E)
    out.update({
        "H_A": np.broadcast_to(rad.H_A, shape), "H_B": np.broadcast_to(rad.H_B, shape),
        "r_A": np.broadcast_to(rad.r_A, shape), "r_B": np.broadcast_to(rad.r_B, shape),
        "eps_A": b.eps_A, "eps_B": b.eps_B,
        "coverage_A": b.coverage_A, "coverage_B": b.coverage_B,
        "thm1_holds_A": b.thm1_holds_A, "thm1_holds_B": b.thm1_holds_B,
        "rho_upper_bound": b.rho_upper_bound, "stable_certified": b.stable_certified,
    })
    if not spec.has("gain"):
        return None
    from . import gains as _gains
    from .observer_pipeline import design, run_observer_stages

    designed, k_hat_reasons = design(spec, system, sigma_w, A_hat, gamma, rad)
    if k_hat_reasons is not None:
        from .observer_pipeline import _reason_notes

        _reason_notes(notes, k_hat_reasons, "K_hat")
    state = (designed.L, A_hat, np.broadcast_to(rad.r_A, shape))
    if prev_gain is not None:  # reuse_gain: keep the previous L while certified (SPEC 4)
        L_prev, A_prev, r_prev = prev_gain
        reuse = _gains.reuse_gains(
            np.stack([L_prev, designed.L]), np.stack([A_prev, A_hat]), gamma,
            np.stack([r_prev, state[2]]), system.C)
        designed = _gains.GainResult(L=reuse.L[1], g_L=reuse.g_L[1],
                                     certified=reuse.certified[1], feasible=None)
        notes.add(reuse.reused[1], "gain: reused from the previous N")
        state = (reuse.L[1], A_hat, state[2])
    run_observer_stages(spec, system, sigma_w, keys, A_hat, B_hat, gamma, rad, b, axis,
                        out, notes, designed)
    return state


_CELL_FIELDS = (
    "A_hat", "B_hat", "rmse_A", "rmse_B", "H_A", "H_B", "r_A", "r_B", "eps_A", "eps_B",
    "coverage_A", "coverage_B", "thm1_holds_A", "thm1_holds_B", "rho_upper_bound",
    "stable_certified", "L", "g_L", "certified", "rho_true", "K", "J_exact", "J_stationary",
    "J_mc", "J_mc_se", "J_star", "cost_ratio", "J_bound", "delta_J", "J_opt", "J_opt_bound",
    "sls_status",
)


def _as_lists(arr) -> list:
    """An (R, E, ...) field -> nested Python lists, NaN/inf -> None (one pass per field)."""
    arr = np.asarray(arr)
    if arr.dtype == object or arr.dtype == bool:
        return arr.tolist()
    arr = arr.astype(float, copy=False)
    finite = np.isfinite(arr)
    cell_ok = finite.reshape(finite.shape[:2] + (-1,)).all(axis=-1)
    out = np.where(finite, arr, 0.0).tolist()
    for ri, ei in zip(*np.nonzero(~cell_ok)):
        out[ri][ei] = json_value(arr[ri, ei])
    return out


def _records(spec, si, wi, N, N0, reps, axis, fields, notes) -> list[dict]:
    system = spec.systems[si]
    present = {f: _as_lists(fields[f]) for f in _CELL_FIELDS if fields.get(f) is not None}
    sigma_w = spec.sigma_w[wi]
    recs = []
    for ri, rep in enumerate(reps):
        key = list(seed_key(si, wi, N, rep))
        for ei, (name, g) in enumerate(zip(axis.names, axis.gammas)):
            rec = empty_record()
            rec.update(system=system.name, sigma_w=sigma_w, N=N, N0=N0, estimator=name,
                       gamma=g, rep=rep, seed_key=list(key))
            for f, values in present.items():
                rec[f] = values[ri][ei]
            cell_notes = notes.items[ri, ei]
            rec["notes"] = "; ".join(cell_notes) if cell_notes else None
            recs.append(rec)
    return recs


def run_unit(spec: ExperimentSpec, unit: dict) -> list[dict]:
    """Run one work unit of ``plan_units`` -> its section 10 records."""
    si, wi = unit["system"], unit["sigma_w"]
    reps = list(range(*unit["reps"]))
    axis = _estimator_axis(spec)
    recs = []
    prev_gain = None
    for N in sorted(unit["N"]):
        fields, notes, N0, gain = _run_dataset(spec, si, wi, N, reps, axis, prev_gain)
        if spec.reuse_gain:
            prev_gain = gain
        recs += _records(spec, si, wi, N, N0, reps, axis, fields, notes)
    return recs


def run_spec(
    spec: ExperimentSpec,
    progress: Callable[[int, int], None] | None = None,
    units: list[dict] | None = None,
    n_jobs: int = 1,
) -> Iterator[list[dict]]:
    """Run every unit in process, yielding each unit's records in unit order.

    ``n_jobs > 1`` runs units in that many worker processes (scikit-learn's
    convention); the records are the same to the bit either way.
    """
    units = plan_units(spec) if units is None else units
    if n_jobs > 1 and len(units) > 1:
        yield from _run_parallel(spec, units, progress, n_jobs)
        return
    for i, unit in enumerate(units):
        yield run_unit(spec, unit)
        if progress is not None:
            progress(i + 1, len(units))


def _run_parallel(spec, units, progress, n_jobs):
    import multiprocessing as mp
    from concurrent.futures import ProcessPoolExecutor

    ctx = mp.get_context("fork") if "fork" in mp.get_all_start_methods() else None
    with ProcessPoolExecutor(max_workers=n_jobs, mp_context=ctx) as pool:
        for i, batch in enumerate(pool.map(run_unit, [spec] * len(units), units, chunksize=4)):
            yield batch
            if progress is not None:
                progress(i + 1, len(units))
