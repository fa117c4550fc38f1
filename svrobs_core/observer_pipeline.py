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
from . import sls as _sls
from .norms import spectral_radius
from .rollouts import MC_STREAM, rng_for


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
    return _truth_cached(A.tobytes(), B.tobytes(), C.tobytes(), A.shape, B.shape, C.shape,
                         system.sigma_u, float(sigma_w), system.sigma_v, horizon)


def _reason_notes(notes, reasons, prefix: str):
    reasons = np.broadcast_to(np.asarray(reasons, dtype=object), notes.items.shape)
    for idx in np.ndindex(reasons.shape):
        if reasons[idx]:
            text = reasons[idx] if prefix is None else f"{prefix}: {reasons[idx]}"
            notes.add(_mask_at(notes.items.shape, idx), text)


def _mask_at(shape, idx):
    m = np.zeros(shape, dtype=bool)
    m[idx] = True
    return m


def design(spec, system, sigma_w, A_hat, gamma, rad):
    """The designed gain of every cell (before the reuse policy): GainResult, K-hat notes."""
    g = gamma[None, :]
    scaled = (1.0 + g)[..., None, None] * A_hat
    kal = _gains.kalman_predictor(scaled, system.C, sigma_w, system.sigma_v)
    res = _gains.design_gain(A_hat, g, rad.r_A[None, :], system.C, kal.K, spec.margin)
    return res, (None if kal.ok.all() else kal.reasons())


def run_observer_stages(spec, system, sigma_w, keys, A_hat, B_hat, gamma, rad, b, axis, out,
                        notes, designed):
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
        notes.add(~designed.feasible & np.isfinite(designed.g_L),
                  "gain: margin not reachable; L minimises g(L)")
    if not spec.has("cost"):
        return
    su, sv = system.sigma_u, system.sigma_v
    J = _cost.exact_cost(A, B, A_hat, B_hat, L, C, su, sigma_w, sv, spec.horizon)
    J_stat, stat_reason = _cost.stationary_cost(
        A, B, A_hat, B_hat, L, C, su, sigma_w, sv, rho_F=rho_F, return_reason=True)
    _reason_notes(notes, stat_reason, "J_stationary")
    out["J_exact"], out["J_stationary"] = J, J_stat
    out["J_star"] = np.full((R, E), J_star)
    _monte_carlo(spec, system, sigma_w, keys, A_hat, B_hat, L, out, notes)
    _cost_ratio(spec, axis, J, out, notes)
    if spec.has("cost_bound"):
        t3 = _cb.theorem3_bound(A_hat, L, C, K, b.eps_A, b.eps_B, su, sv, norms, rho_F=rho_F)
        _reason_notes(notes, t3.reason, "J_bound")
        out["J_bound"] = t3.J_b
        out["delta_J"] = t3.J_b - J
    if spec.has("sls"):
        run_sls(spec, system, b, norms, K, A_hat, out, notes)


def _monte_carlo(spec, system, sigma_w, keys, A_hat, B_hat, L, out, notes):
    """J_mc for reps < mc_reps; one generator per (key, MC stream), so every
    estimator and gamma of a repetition sees the same noise."""
    R, E = A_hat.shape[:2]
    J_mc = np.full((R, E), np.nan)
    J_se = np.full((R, E), np.nan)
    limit = spec.reps if spec.mc_reps is None else spec.mc_reps
    for ri, key in enumerate(keys):
        if key[3] >= limit:
            notes.add(_row((R, E), ri), f"J_mc: only computed for rep < mc_reps = {limit}")
            continue
        for ei in range(E):
            rng = rng_for(spec.seed, key, MC_STREAM)
            J_mc[ri, ei], J_se[ri, ei] = _cost.mc_cost(
                system.A, system.B, A_hat[ri, ei], B_hat[ri, ei], L[ri, ei], system.C,
                system.sigma_u, sigma_w, system.sigma_v, spec.horizon, rng, spec.mc_runs)
    out["J_mc"], out["J_mc_se"] = J_mc, J_se


def _cost_ratio(spec, axis, J, out, notes):
    """r = |J_gamma - J_ref| / J_ref against gamma_ref of the same estimator (SPEC 6)."""
    ratio = np.full(J.shape, np.nan)
    names = np.array(axis.names)
    for ei, (name, g) in enumerate(zip(axis.names, axis.gammas)):
        if g is None:
            continue
        ref = [j for j, (nm, gg) in enumerate(zip(names, axis.gammas))
               if nm == name and gg == spec.gamma_ref]
        if ref:
            ratio[:, ei] = np.abs(J[:, ei] - J[:, ref[0]]) / J[:, ref[0]]
        else:
            notes.add(_column(J.shape, ei), "cost_ratio: gamma_ref not in the gamma grid")
    out["cost_ratio"] = ratio


def _row(shape, ri):
    m = np.zeros(shape, dtype=bool)
    m[ri] = True
    return m


def _column(shape, ei):
    m = np.zeros(shape, dtype=bool)
    m[:, ei] = True
    return m


def run_sls(spec, system, b, norms, K, A_hat, out, notes):
    """J_opt by SLS per cell (cvxpy + Clarabel) and the paper's bound on it (SPEC 8)."""
    R, E = A_hat.shape[:2]
    su, sv = system.sigma_u, system.sigma_v
    eps1 = np.fmax(b.eps_A, b.eps_B)
    F = _sls.sls_F(eps1, norms.hinf_PhiA_B, norms.hinf_PhiA_K, su, sv)
    C_bound = spec.sls_C_bound
    if C_bound is None:
        C_bound = float(_sls.default_C_bound(K, norms.h2_closed))
    J_opt = np.full((R, E), np.nan)
    status = np.empty((R, E), dtype=object)
    for ri, ei in np.ndindex(R, E):
        if not np.isfinite(F[ri, ei]):
            status[ri, ei] = "not_run"
            notes.add(_mask_at((R, E), (ri, ei)),
                      "J_opt: F undefined (true system unstable: H-infinity norms infinite)")
            continue
        res = _sls.sls_observer(A_hat[ri, ei], system.C, K, F[ri, ei], C_bound, spec.sls_T_fir)
        J_opt[ri, ei], status[ri, ei] = res.J_opt, res.status
    bound, reason = _sls.jopt_upper_bound(
        b.eps_A, eps1, C_bound, norms.hinf_PhiA_B, norms.hinf_PhiA_K, su, sv,
        norms.h2_closed, norms.hinf_closed)
    _reason_notes(notes, reason, None)
    out["J_opt"], out["sls_status"], out["J_opt_bound"] = J_opt, status, np.broadcast_to(bound, (R, E))
