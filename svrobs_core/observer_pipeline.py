"""Observer stages of one dataset: gain, cost, cost_bound, sls (SPEC sections 4-8).

Called by :mod:`svrobs_core.experiments` with the estimates and bounds of
one (system, sigma_w, N) over the (rep, estimator/gamma) grid (R, E); fills
the record fields and the per-cell notes. Everything that depends only on
the true system (K, J*, its transfer-matrix norms) is computed once.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np

from . import cost as _cost
from . import cost_bound as _cb
from . import gains as _gains
from .norms import spectral_radius
from .rollouts import MC_STREAM, generators


@lru_cache(maxsize=64)
def _truth_cached(A_b, B_b, C_b, shape_A, shape_B, shape_C, sigma_u, sigma_w, sigma_v, horizon):
    A = np.frombuffer(A_b).reshape(shape_A)
    B = np.frombuffer(B_b).reshape(shape_B)
    C = np.frombuffer(C_b).reshape(shape_C)
    kal = _gains.kalman_predictor(A, C, sigma_w, sigma_v)
    K = kal.K
    J_star = float(_cost.optimal_cost(A, B, K, C, sigma_u, sigma_w, sigma_v, horizon))
    norms = _cb.true_system_norms(A, B, C, K)
    return K, J_star, norms, kal.reasons() if not kal.ok else None


def truth(system, sigma_w: float, horizon: int):
    """K, J*, TrueSystemNorms and Kalman failure reason of the true system (cached)."""
    A, B, C = system.A, system.B, system.C
    return _truth_cached(
        A.tobytes(),
        B.tobytes(),
        C.tobytes(),
        A.shape,
        B.shape,
        C.shape,
        system.sigma_u,
        float(sigma_w),
        system.sigma_v,
        horizon,
    )


def _reason_notes(notes, reasons, prefix: str):
    """Notes for the cells whose reason (object array or scalar) is non-empty."""
    notes.add_reasons(reasons, prefix)


def design(spec, system, sigma_w, A_hat, gamma, rad):
    """The designed gain of every cell (before the reuse policy): GainResult, K-hat notes."""
    g = gamma[None, :]
    scaled = (1.0 + g)[..., None, None] * A_hat
    kal = _gains.kalman_predictor(scaled, system.C, sigma_w, system.sigma_v)
    res = _gains.design_gain(A_hat, g, rad.r_A[None, :], system.C, kal.K, spec.margin)
    return res, (None if kal.ok.all() else kal.reasons())


def run_observer_stages(
    spec, system, sigma_w, keys, A_hat, B_hat, gamma, rad, b, axis, out, notes, designed
):
    """Fill gain/cost/bound/sls fields for one dataset; ``designed`` is the
    (possibly reused) GainResult the caller chose for this N."""
    A, B, C = system.A, system.B, system.C
    R, E = A_hat.shape[:2]
    K, J_star, norms, k_reason = truth(system, sigma_w, spec.horizon)
    if k_reason is not None:
        notes.add(True, f"true system: {k_reason}")
    L = designed.L
    out["L"], out["g_L"], out["certified"] = L, designed.g_L, designed.certified
    out["K"] = np.broadcast_to(K, (R, E) + K.shape)
    rho_F = spectral_radius(A_hat - L @ C)
    out["rho_true"] = spectral_radius(A - L @ C)
    if designed.feasible is not None:
        notes.add(
            ~designed.feasible & np.isfinite(designed.g_L),
            "gain: margin not reachable, L minimises g(L)",
        )
    if not spec.has("cost"):
        return
    su, sv = system.sigma_u, system.sigma_v
    J = _cost.exact_cost(A, B, A_hat, B_hat, L, C, su, sigma_w, sv, spec.horizon)
    J_stat, stat_reason = _cost.stationary_cost(
        A, B, A_hat, B_hat, L, C, su, sigma_w, sv, rho_F=rho_F, return_reason=True
    )
    _reason_notes(notes, stat_reason, "J_stationary")
    out["J_exact"], out["J_stationary"] = J, J_stat
    out["J_star"] = np.broadcast_to(J_star, (R, E))
    _monte_carlo(spec, system, sigma_w, keys, A_hat, B_hat, L, out, notes)
    _cost_ratio(spec, axis, J, out, notes)
    if spec.has("cost_bound"):
        t3 = _cb.theorem3_bound(A_hat, L, C, K, b.eps_A, b.eps_B, su, sv, norms, rho_F=rho_F)
        _reason_notes(notes, t3.reason, "J_bound")
        out["J_bound"] = t3.J_b
        out["delta_J"] = t3.J_b - J
    if spec.has("sls"):
        run_sls(spec, system, b, norms, K, A_hat, out, notes)


def mc_note(limit: int) -> str:
    """The note of the cells without a Monte Carlo J (tagged "mc" in the notes)."""
    if limit == 0:
        return "J_mc: not requested (mc_reps = 0)"
    return f"J_mc: only computed for rep < mc_reps = {limit}"


def _monte_carlo(spec, system, sigma_w, keys, A_hat, B_hat, L, out, notes):
    """J_mc for reps < mc_reps; one generator per (key, MC stream), so every
    estimator and gamma of a repetition sees the same noise: it is drawn once
    per repetition and drives all the repetition's cells (common random
    numbers, :func:`svrobs_core.cost.mc_cost_shared`)."""
    R, E = A_hat.shape[:2]
    J_mc = np.full((R, E), np.nan)
    J_se = np.full((R, E), np.nan)
    limit = spec.reps if spec.mc_reps is None else spec.mc_reps
    rows = np.array([key[3] < limit for key in keys], dtype=bool)
    notes.add(~rows[:, None], mc_note(limit), tag="mc")
    idx = np.flatnonzero(rows)
    if idx.size:
        gens = generators(spec.seed, [keys[i] for i in idx], MC_STREAM, fresh=True)
        J_mc[idx], J_se[idx] = _cost.mc_cost_shared(
            system.A,
            system.B,
            A_hat[idx],
            B_hat[idx],
            L[idx],
            system.C,
            system.sigma_u,
            sigma_w,
            system.sigma_v,
            spec.horizon,
            list(gens),
            spec.mc_runs,
        )
    out["J_mc"], out["J_mc_se"] = J_mc, J_se


def _cost_ratio(spec, axis, J, out, notes):
    """r = |J_gamma - J_ref| / J_ref against gamma_ref of the same estimator (SPEC 6)."""
    ratio = np.full(J.shape, np.nan)
    names = np.array(axis.names)
    for ei, (name, g) in enumerate(zip(axis.names, axis.gammas)):
        if g is None:
            continue
        ref = [
            j
            for j, (nm, gg) in enumerate(zip(names, axis.gammas))
            if nm == name and gg == spec.gamma_ref
        ]
        if ref:
            ratio[:, ei] = np.abs(J[:, ei] - J[:, ref[0]]) / J[:, ref[0]]
        else:
            missing = np.zeros(J.shape, dtype=bool)
            missing[:, ei] = True
            notes.add(missing, "cost_ratio: gamma_ref not in the gamma grid")
    out["cost_ratio"] = ratio


def run_sls(spec, system, b, norms, K, A_hat, out, notes):
    """J_opt by SLS per cell (cvxpy + Clarabel) and the paper's bound on it (SPEC 8)."""
    from . import sls as _sls  # cvxpy: imported only when the sls stage runs

    R, E = A_hat.shape[:2]
    su, sv = system.sigma_u, system.sigma_v
    eps1 = np.fmax(b.eps_A, b.eps_B)
    F = _sls.sls_F(eps1, norms.hinf_PhiA_B, norms.hinf_PhiA_K, su, sv)
    C_bound = spec.sls_C_bound
    if C_bound is None:
        C_bound = float(_sls.default_C_bound(K, norms.h2_closed))
    J_opt = np.full((R, E), np.nan)
    status = np.empty((R, E), dtype=object)
    undefined = ~np.isfinite(np.broadcast_to(F, (R, E)))
    notes.add(undefined, "J_opt: F undefined (true system unstable: H-infinity norms infinite)")
    for ri, ei in np.ndindex(R, E):
        if undefined[ri, ei]:
            status[ri, ei] = "not_run"
            continue
        res = _sls.sls_observer(A_hat[ri, ei], system.C, K, F[ri, ei], C_bound, spec.sls_T_fir)
        J_opt[ri, ei], status[ri, ei] = res.J_opt, res.status
    bound, reason = _sls.jopt_upper_bound(
        b.eps_A,
        eps1,
        C_bound,
        norms.hinf_PhiA_B,
        norms.hinf_PhiA_K,
        su,
        sv,
        norms.h2_closed,
        norms.hinf_closed,
    )
    _reason_notes(notes, reason, None)
    out["J_opt"], out["sls_status"], out["J_opt_bound"] = (
        J_opt,
        status,
        np.broadcast_to(bound, (R, E)),
    )
