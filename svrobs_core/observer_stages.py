"""The observer stages of a dataset: gain, cost, cost_bound, sls (docs/science.md sections 4-8).

What depends only on the true system (K, J*, its transfer-matrix norms) is
computed once and cached (:func:`truth`). Called by :mod:`svrobs_core.pipeline`
after the estimates and their bounds.
"""

from __future__ import annotations

import time
from functools import lru_cache
from typing import Any

import numpy as np

from . import bounds as _bounds
from . import cost as _cost
from . import cost_bound as _cb
from . import cost_check as _check
from . import cost_mc as _mc
from . import gains as _gains
from . import kalman as _kalman
from .array_types import Array, FloatArray
from .bounds import BoundsResult
from .cost_bound import TrueSystemNorms
from .gains import GainResult
from .norms import spectral_radius, stability_radius
from .seeding import MC_STREAM, generators
from .stage_cells import Cells, StageCells, SystemT
from .systems import SystemSpec

Truth = tuple[FloatArray, float, TrueSystemNorms, Any]  # K, J*, norms, the reasons (None: none)
J_EXACT_NOT_FINITE = "J_exact: not finite (the cost leaves the double range)"


@lru_cache(maxsize=64)
def _truth_cached(
    matrices: tuple[bytes, bytes, bytes],
    shapes: tuple[tuple[int, ...], tuple[int, ...], tuple[int, ...]],
    sigmas: tuple[float, float, float],
    horizon: int,
) -> Truth:
    A, B, C = (np.frombuffer(x).reshape(s) for x, s in zip(matrices, shapes))
    sigma_u, sigma_w, sigma_v = sigmas
    kal = _kalman.kalman_predictor(A, C, sigma_w, sigma_v)
    K = kal.K
    noise = dict(sigma_u=sigma_u, sigma_w=sigma_w, sigma_v=sigma_v)
    J, bad = checked_j_star(A[None], B[None], K[None], C, horizon=horizon, **noise)
    J_star = np.nan if bad[0] else float(J[0])
    norms = _cb.true_system_norms(A, B, C, K)
    reason: Any = kal.reasons() if not kal.ok else None
    if bad[0]:
        lost = f"J_star: {_check.REASON_ROUNDING}"
        reason = lost if reason is None else f"{reason}; {lost}"
    return K, J_star, norms, reason


def checked_j_star(
    A: FloatArray, B: FloatArray, K: FloatArray, C: FloatArray, *, horizon: int, **noise: Any
) -> tuple[FloatArray, Array]:
    """(J*, bad): the exact cost of the model (A, B) with its gain K, each cell, and
    where a second evaluation does not confirm it (docs/science.md#64-j-and-the-cost-ratio)."""
    J, err = _cost.exact_cost(A, B, A, B, L=K, C=C, **noise, horizon=horizon, return_error=True)
    bad, _ = _check.unconfirmed(
        A, B, A, B, L=K, C=C, **noise, horizon=horizon, J=J, err=err,
        J_stat=np.full(J.shape, np.nan),
    )  # fmt: skip
    return J, bad


def truth(system: SystemSpec, sigma_w: float, horizon: int) -> Truth:
    """K, J*, TrueSystemNorms and Kalman failure reason of the true system (cached)."""
    A, B, C = system.A, system.B, system.C
    return _truth_cached(
        (A.tobytes(), B.tobytes(), C.tobytes()),
        (A.shape, B.shape, C.shape),
        (system.sigma_u, float(sigma_w), system.sigma_v),
        horizon,
    )


def design(
    c: StageCells[SystemT, Any], gamma: FloatArray, radius: FloatArray, *, matrix: bool = False
) -> tuple[GainResult, Array | None]:
    """The designed gain of every cell (before the reuse policy): GainResult, K-hat notes.

    Centre (1+gamma) A_hat (gamma = 0: A_hat itself); ``radius`` is r_A per
    estimator (E,) or, with ``matrix``, the radius matrices R_A (R, E, n, n)."""
    system = c.system
    g = gamma[None, :]
    scaled = (1.0 + g)[..., None, None] * c.A_hat
    kal = _kalman.kalman_predictor(scaled, system.C, c.sigma_w, system.sigma_v)
    res = _gains.design_gain(
        c.A_hat,
        g,
        None if matrix else radius[None, :],
        C=system.C,
        K_hat=kal.K,
        margin=c.spec.margin,
        R_A=radius if matrix else None,
    )
    return res, (None if kal.ok.all() else kal.reasons())


def observer_stages(c: Cells, b: BoundsResult, designed: GainResult) -> None:
    """Fill gain/cost/bound/sls fields for one dataset; ``designed`` is the
    (possibly reused) GainResult the caller chose for this N."""
    spec, system, out, notes = c.spec, c.system, c.out, c.notes
    A, B, C = system.A, system.B, system.C
    A_hat, B_hat = c.A_hat, c.B_hat
    R, E = c.shape
    K, J_star, norms, k_reason = truth(system, c.sigma_w, spec.horizon)
    if k_reason is not None:
        notes.add(True, f"true system: {k_reason}")
    L = designed.L
    defined = np.isfinite(designed.g_L)
    notes.add(~defined, "certified: undefined (no finite gain L or radius r_A)")
    out["L"], out["g_L"] = L, designed.g_L
    out["certified"] = _bounds.nullable(designed.certified, defined)
    out["K"] = np.broadcast_to(K, (R, E) + K.shape)
    rho_F = stability_radius(A_hat - L @ C)  # decides; not a field
    out["rho_true"] = spectral_radius(A - L @ C)
    if designed.feasible is not None:
        notes.add(
            ~designed.feasible & np.isfinite(designed.g_L),
            "gain: margin not reachable, L minimises g(L)",
        )
    if not spec.has("cost"):
        return
    c.stage = "cost"
    noise = dict(sigma_u=system.sigma_u, sigma_w=c.sigma_w, sigma_v=system.sigma_v)
    J, J_err = _cost.exact_cost(
        A, B, A_hat, B_hat, L=L, C=C, **noise, horizon=spec.horizon, return_error=True
    )
    J_stat, stat_reason = _cost.stationary_cost(
        A, B, A_hat, B_hat, L=L, C=C, **noise, rho_F=rho_F, return_reason=True
    )
    # a huge (finite) estimate can take the cost beyond the doubles
    notes.add(defined & ~np.isfinite(J), J_EXACT_NOT_FINITE)
    notes.add_reasons(stat_reason, "J_stationary")
    bad_J, bad_stat = _check.unconfirmed(
        A, B, A_hat, B_hat, L=L, C=C, **noise, horizon=spec.horizon, J=J, err=J_err,
        J_stat=J_stat, rho=np.fmax(stability_radius(A), rho_F),
    )  # fmt: skip
    notes.add(bad_J, f"J_exact: {_check.REASON_ROUNDING}")
    notes.add(bad_stat, f"J_stationary: {_check.REASON_ROUNDING}")
    J, J_stat = np.where(bad_J, np.nan, J), np.where(bad_stat, np.nan, J_stat)
    out["J_exact"], out["J_stationary"] = J, J_stat
    out["J_star"] = np.broadcast_to(J_star, (R, E))
    _monte_carlo(c, L)
    _cost_ratio(c, J)
    if spec.has("cost_bound"):
        c.stage = "cost_bound"
        t3 = _cb.theorem3_bound(
            A_hat,
            L,
            C,
            K,
            eps_A=b.eps_A,
            eps_B=b.eps_B,
            sigma_u=system.sigma_u,
            sigma_v=system.sigma_v,
            norms=norms,
            rho_F=rho_F,
        )
        notes.add_reasons(t3.reason, "J_bound")
        out["J_bound"] = t3.J_b
        with np.errstate(invalid="ignore"):  # inf - inf: null, as both are
            out["delta_J"] = t3.J_b - J


def mc_note(limit: int) -> str:
    """The note of the cells without a Monte Carlo J (tagged "mc" in the notes)."""
    if limit == 0:
        return "J_mc: not requested (mc_reps = 0)"
    return f"J_mc: only computed for rep < mc_reps = {limit}"


def _monte_carlo(c: Cells, L: FloatArray) -> None:
    """J_mc for reps < mc_reps; one generator per (key, MC stream), so every
    estimator and gamma of a repetition sees the same noise: it is drawn once
    per repetition and drives all the repetition's cells (common random
    numbers, :func:`svrobs_core.cost_mc.mc_cost_shared`)."""
    clock = time.process_time()
    spec, system, keys = c.spec, c.system, c.keys
    R, E = c.shape
    J_mc = np.full((R, E), np.nan)
    J_se = np.full((R, E), np.nan)
    limit = spec.reps if spec.mc_reps is None else spec.mc_reps
    rows = np.array([key[3] < limit for key in keys], dtype=bool)
    c.notes.add(~rows[:, None], mc_note(limit), tag="mc")
    idx = np.flatnonzero(rows)
    if idx.size:
        gens = generators(spec.seed, [keys[i] for i in idx], MC_STREAM, fresh=True, rng=spec.rng)
        J_mc[idx], J_se[idx] = _mc.mc_cost_shared(
            system.A,
            system.B,
            c.A_hat[idx],
            c.B_hat[idx],
            L=L[idx],
            C=system.C,
            sigma_u=system.sigma_u,
            sigma_w=c.sigma_w,
            sigma_v=system.sigma_v,
            horizon=spec.horizon,
            rngs=list(gens),
            runs=spec.mc_runs,
        )
    c.out["J_mc"], c.out["J_mc_se"] = J_mc, J_se
    c.mc_seconds += time.process_time() - clock


def _cost_ratio(c: Cells, J: FloatArray) -> None:
    """r = |J_gamma - J_ref| / J_ref against gamma_ref of the same estimator
    (docs/science.md#64-j-and-the-cost-ratio)."""
    axis = c.axis
    ratio = np.full(J.shape, np.nan)
    names = np.array(axis.names)
    for ei, (name, g) in enumerate(zip(axis.names, axis.gammas)):
        if g is None:
            continue
        ref = [
            j
            for j, (nm, gg) in enumerate(zip(names, axis.gammas))
            if nm == name and gg == c.spec.gamma_ref
        ]
        if ref:
            ratio[:, ei] = np.abs(J[:, ei] - J[:, ref[0]]) / J[:, ref[0]]
        else:
            missing = np.zeros(J.shape, dtype=bool)
            missing[:, ei] = True
            c.notes.add(missing, "cost_ratio: gamma_ref not in the gamma grid")
    c.out["cost_ratio"] = ratio


def sls_stage(c: Cells, b: BoundsResult) -> None:
    """J_opt by SLS per cell (cvxpy + Clarabel) and the paper's bound on it
    (docs/science.md#8-sls-sub-optimal-observer-j_opt).

    Needs the estimate, the bounds' eps and the true system's K and norms
    (:func:`truth`, computed here when the gain stage did not): not the gain."""
    from . import sls as _sls  # cvxpy: imported only when the sls stage runs

    spec, system, notes = c.spec, c.system, c.notes
    K, _, norms, k_reason = truth(system, c.sigma_w, spec.horizon)
    if k_reason is not None:
        notes.add(True, f"true system: {k_reason}")
    R, E = c.shape
    su, sv = system.sigma_u, system.sigma_v
    eps1 = _sls.eps_max(b.eps_A, b.eps_B)
    F = _sls.sls_F(eps1, norms.hinf_PhiA_B, norms.hinf_PhiA_K, sigma_u=su, sigma_v=sv)
    C_bound = spec.sls_C_bound
    if C_bound is None:
        C_bound = float(_sls.default_C_bound(K, norms.h2_closed))
    J_opt = np.full((R, E), np.nan)
    status = np.empty((R, E), dtype=object)
    F_cells = np.broadcast_to(F, (R, E))
    undefined = ~np.isfinite(F_cells)
    norms_ok = np.isfinite(norms.hinf_PhiA_B) & np.isfinite(norms.hinf_PhiA_K)
    notes.add(
        undefined & ~norms_ok,
        "J_opt: F undefined (true system unstable: H-infinity norms infinite)",
    )
    notes.add(undefined & norms_ok, "J_opt: F undefined (eps_A or eps_B is null)")
    for ri, ei in np.ndindex(R, E):
        if undefined[ri, ei]:
            status[ri, ei] = "not_run"
            continue
        res = _sls.sls_observer(
            c.A_hat[ri, ei],
            system.C,
            K,
            float(F_cells[ri, ei]),
            C_bound=C_bound,
            T_fir=spec.sls_T_fir,
        )
        J_opt[ri, ei], status[ri, ei] = res.J_opt, res.status
    bound, reason = _sls.jopt_upper_bound_from_norms(
        b.eps_A, eps1, C_bound, norms, sigma_u=su, sigma_v=sv
    )
    notes.add_reasons(reason, None)
    c.out["J_opt"], c.out["sls_status"], c.out["J_opt_bound"] = (
        J_opt,
        status,
        np.broadcast_to(bound, (R, E)),
    )
