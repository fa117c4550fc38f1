"""Theorem 3 cost bound J_b (docs/science.md#7-cost-bound-theorem-3).

    J_b = ||Phi~_w K - Phi~_v||_H2 sigma_v
        + sqrt(2) eps1 ||Phi~_w||_H2 ||[Phi_A B; I_m]||_Hinf sigma_u
        + sqrt(2) eps2 ||Phi~_w||_H2 ||[Phi_A K; I_p]||_Hinf sigma_v

with ``Phi~_w = (zI - A~ + LC)^-1``, ``Phi~_v = Phi~_w L`` (so
``Phi~_w K - Phi~_v = (zI - F)^-1 (K - L)``, ``F = A~ - L C``),
``Phi_A = (zI - A)^-1`` (true A), ``eps_L = ||K - L||`` (spectral norm),
``eps1 = max(eps_A, eps_B)``, ``eps2 = max(eps_A, eps_L)``. Implemented exactly
as stated (docs/science.md#101-where-the-paper-is-ambiguous-or-wrong-what-svrobs-does, item 13:
H2 norms, not squared, compared with the mean-square
J; the data show where it holds).

The H-infinity factors depend only on the true system: compute them once per
system with :func:`true_system_norms` and pass the result to
:func:`theorem3_bound` for the whole batch of cells. The per-cell work is one
batched Kronecker solve with two right-hand sides (both H2 norms share the
operator ``I - F kron F``), a batched spectral norm and, unless ``rho_F`` is
given, a batched eigenvalue call for the stability of ``F``.

NaN semantics: ``J_b`` is NaN (record ``null``) where

* the true ``A`` is not Schur stable (``rho(A) >= 1``, e.g. the paper's U
  system): the H-infinity norms of ``[Phi_A B; I]`` and ``[Phi_A K; I]`` are
  undefined; reason :data:`REASON_A_UNSTABLE` (:data:`REASON_A_BOUNDARY` for a
  computed rho(A) within UNIT_CIRCLE_TOL below 1, :func:`svrobs_core.norms.schur_stable`);
* ``F = A~ - L C`` is not Schur stable: the H2 norms are undefined; reason
  :data:`REASON_F_UNSTABLE` (:data:`REASON_F_BOUNDARY`);
* an input is non-finite (e.g. no gain): reason :data:`REASON_NONFINITE`.

When several apply, the first in this list is reported.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from .array_types import Array, FloatArray
from .norms import (
    REASON_NONFINITE,
    UNIT_CIRCLE_TOL,
    h2_norm,
    hinf_norm,
    schur_stable,
    stability_radius,
    stability_reason,
    stein_solve,
)

REASON_A_UNSTABLE = "unstable: rho(A) >= 1, H-inf of [Phi_A B; I] undefined"
REASON_F_UNSTABLE = "unstable: rho(A_tilde - L C) >= 1, H2 of Phi~_w undefined"
REASON_CLOSED_UNSTABLE = "unstable: rho(A - K C) >= 1"
# the same for a computed radius within UNIT_CIRCLE_TOL below 1 (norms.schur_stable)
_NEAR = f"not below 1 - {UNIT_CIRCLE_TOL:g} up to rounding (the stability boundary)"
REASON_A_BOUNDARY = f"rho(A) {_NEAR}: H-inf of [Phi_A B; I] undefined"
REASON_F_BOUNDARY = f"rho(A_tilde - L C) {_NEAR}: H2 of Phi~_w undefined"
REASON_CLOSED_BOUNDARY = f"rho(A - K C) {_NEAR}"


@dataclass(frozen=True, kw_only=True)
class TrueSystemNorms:
    """Norms that depend only on the true system (compute once per system).

    Values are floats for one system (arrays of the batch shape if A, B, C, K
    were batched); NaN where undefined, with the reason in the matching
    ``*_reason`` field (None when defined).
    """

    hinf_PhiA_B: float | FloatArray  # ||[(zI - A)^-1 B; I_m]||_Hinf
    hinf_PhiA_K: float | FloatArray  # ||[(zI - A)^-1 K; I_p]||_Hinf
    h2_closed: float | FloatArray  # ||(zI - A + K C)^-1||_H2   (SLS, section 8)
    hinf_closed: float | FloatArray  # ||(zI - A + K C)^-1||_Hinf (SLS, section 8)
    rho_A: float | FloatArray
    rho_closed: float | FloatArray  # rho(A - K C)
    open_reason: str | Array | None  # reason for the two [Phi_A .; I] norms
    closed_reason: str | Array | None  # reason for the two closed-loop norms


def _scalar(x: ArrayLike) -> Any:
    x = np.asarray(x)
    if x.ndim == 0:
        return x.item()
    return x


def true_system_norms(
    A: ArrayLike, B: ArrayLike, C: ArrayLike, K: ArrayLike, *, grid: int = 1024
) -> TrueSystemNorms:
    """H-infinity / H2 norms of the true system used by Theorem 3 and SLS.

    A (..., n, n), B (..., n, m), C (..., p, n), K (..., n, p). ``[Phi_A B; I]``
    is the system (F=A, G=B, H=[I_n; 0], D=[0; I_m]) with n+m outputs and m
    inputs; ``[Phi_A K; I]`` likewise with K (n+p outputs, p inputs).
    """
    A = np.asarray(A, dtype=float)
    B = np.asarray(B, dtype=float)
    if B.ndim == 1:
        B = B[:, None]
    C = np.asarray(C, dtype=float)
    K = np.asarray(K, dtype=float)
    n, m, p = A.shape[-1], B.shape[-1], C.shape[-2]
    rho_A = stability_radius(A)

    def stacked(G: FloatArray, q: int) -> FloatArray:
        H = np.concatenate([np.eye(n), np.zeros((q, n))], axis=0)
        D = np.concatenate([np.zeros((n, q)), np.eye(q)], axis=0)
        return hinf_norm(A, G, H, D, rho=rho_A, grid=grid)

    hB = stacked(B, m)
    hK = stacked(K, p)
    Fk = A - K @ C
    rho_k = stability_radius(Fk)
    I = np.eye(n)
    h2c = h2_norm(Fk, I, I, rho=rho_k)
    hic = hinf_norm(Fk, I, I, rho=rho_k, grid=grid)

    return TrueSystemNorms(
        hinf_PhiA_B=_scalar(hB),
        hinf_PhiA_K=_scalar(hK),
        h2_closed=_scalar(h2c),
        hinf_closed=_scalar(hic),
        rho_A=_scalar(rho_A),
        rho_closed=_scalar(rho_k),
        open_reason=stability_reason(
            None, rho_A, unstable=REASON_A_UNSTABLE, boundary=REASON_A_BOUNDARY
        ),
        closed_reason=stability_reason(
            None, rho_k, unstable=REASON_CLOSED_UNSTABLE, boundary=REASON_CLOSED_BOUNDARY
        ),
    )


@dataclass(frozen=True, kw_only=True)
class Theorem3Result:
    """Per-cell Theorem 3 quantities, arrays of the batch shape."""

    J_b: FloatArray  # the bound (NaN where undefined)
    reason: object  # object array of None / str (plain object for one cell)
    term_v: FloatArray  # ||Phi~_w K - Phi~_v||_H2 sigma_v
    term_u: FloatArray  # sqrt2 eps1 ||Phi~_w||_H2 ||[Phi_A B; I]||_Hinf sigma_u
    term_K: FloatArray  # sqrt2 eps2 ||Phi~_w||_H2 ||[Phi_A K; I]||_Hinf sigma_v
    h2_Phi_w: FloatArray  # ||Phi~_w||_H2
    h2_Phi_dK: FloatArray  # ||Phi~_w K - Phi~_v||_H2 = ||(zI - F)^-1 (K - L)||_H2
    eps_L: FloatArray
    eps1: FloatArray
    eps2: FloatArray
    rho_F: FloatArray


def phi_w_h2_norms(
    A_tilde: ArrayLike, L: ArrayLike, C: ArrayLike, K: ArrayLike, *, rho_F: ArrayLike | None = None
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """(||Phi~_w||_H2, ||Phi~_w (K - L)||_H2, rho_F), batched, one shared solve.

    NaN where F = A~ - L C is not :func:`~svrobs_core.norms.schur_stable` or non-finite."""
    At = np.asarray(A_tilde, dtype=float)
    L = np.asarray(L, dtype=float)
    C = np.asarray(C, dtype=float)
    K = np.asarray(K, dtype=float)
    n = At.shape[-1]
    F = At - L @ C
    if rho_F is None:
        rho_F = stability_radius(F)
    rho_F = np.asarray(rho_F, dtype=float)
    batch = np.broadcast_shapes(F.shape[:-2], K.shape[:-2], rho_F.shape)
    ok = schur_stable(rho_F)
    Fs = np.where(ok[..., None, None], F, 0.0)
    dK = np.where(np.isfinite(K - L), K - L, 0.0)
    rhs = np.stack(
        np.broadcast_arrays(
            np.broadcast_to(np.eye(n), dK.shape[:-2] + (n, n)), dK @ np.swapaxes(dK, -1, -2)
        ),
        axis=-1,
    )
    W = stein_solve(Fs, rhs, multi_rhs=True)  # (..., n, n, 2)
    tr = np.trace(W, axis1=-3, axis2=-2)  # (..., 2)
    h = np.sqrt(np.maximum(tr, 0.0))
    h_w = np.broadcast_to(h[..., 0], batch)
    h_dk = np.broadcast_to(h[..., 1], batch)
    bad = ~np.broadcast_to(ok, batch) | ~np.broadcast_to(np.isfinite(K - L).all((-2, -1)), batch)
    return np.where(bad, np.nan, h_w), np.where(bad, np.nan, h_dk), np.broadcast_to(rho_F, batch)


@np.errstate(over="ignore", invalid="ignore")  # near the double range: inf/NaN, not warnings
def theorem3_bound(
    A_tilde: ArrayLike,
    L: ArrayLike,
    C: ArrayLike,
    K: ArrayLike,
    *,
    eps_A: ArrayLike,
    eps_B: ArrayLike,
    sigma_u: ArrayLike,
    sigma_v: ArrayLike,
    norms: TrueSystemNorms,
    rho_F: ArrayLike | None = None,
) -> Theorem3Result:
    """J_b of Theorem 3 per cell. -> Theorem3Result (arrays of the batch shape)

    A_tilde (..., n, n), L (..., n, p), C (p, n), K (n, p) (the true
    system's Kalman predictor gain), eps_A, eps_B (...) from Corollary 1,
    sigma_u, sigma_v scalars or (...); ``norms`` from
    :func:`true_system_norms` (A, B, C, K) of the same true system.
    ``rho_F``: optional precomputed :func:`~svrobs_core.norms.stability_radius` of
    ``A~ - L C``.
    """
    L = np.asarray(L, dtype=float)
    K = np.asarray(K, dtype=float)
    h_w, h_dk, rho_F = phi_w_h2_norms(A_tilde, L, C, K, rho_F=rho_F)
    batch = np.broadcast_shapes(
        h_w.shape, np.shape(eps_A), np.shape(eps_B), np.shape(sigma_u), np.shape(sigma_v)
    )
    dK = K - L
    finite = np.isfinite(dK).all(axis=(-2, -1))
    eps_L = np.linalg.norm(np.where(finite[..., None, None], dK, 0.0), ord=2, axis=(-2, -1))
    eps_L = np.where(finite, eps_L, np.nan)
    eps_A = np.asarray(eps_A, dtype=float)
    eps_B = np.asarray(eps_B, dtype=float)
    eps1 = np.maximum(eps_A, eps_B)  # null if either is null
    eps2 = np.maximum(eps_A, eps_L)
    su = np.asarray(sigma_u, dtype=float)
    sv = np.asarray(sigma_v, dtype=float)
    s2 = np.sqrt(2.0)
    term_v = h_dk * sv
    term_u = s2 * eps1 * h_w * norms.hinf_PhiA_B * su
    term_K = s2 * eps2 * h_w * norms.hinf_PhiA_K * sv
    J_b = np.broadcast_to(term_v + term_u + term_K, batch)

    # reasons, in order of precedence
    reason = np.full(batch, None, dtype=object)
    reason[np.broadcast_to(~np.isfinite(J_b), batch)] = REASON_NONFINITE
    f_reason = stability_reason(None, rho_F, unstable=REASON_F_UNSTABLE, boundary=REASON_F_BOUNDARY)
    f_reason = np.broadcast_to(np.asarray(f_reason, dtype=object), batch)
    f_bad = (f_reason != None) & (f_reason != REASON_NONFINITE)  # noqa: E711 (object arrays)
    reason[f_bad] = f_reason[f_bad]
    open_reason = norms.open_reason
    if isinstance(open_reason, np.ndarray):
        o = np.broadcast_to(open_reason, batch)
        reason = np.where(o != None, o, reason)
    elif open_reason is not None:
        reason[...] = open_reason
    J_b = np.where(reason == None, J_b, np.nan)
    rb = reason.item() if reason.ndim == 0 else reason

    def bc(x: ArrayLike) -> FloatArray:
        return np.broadcast_to(x, batch)

    return Theorem3Result(
        J_b=J_b,
        reason=rb,
        term_v=bc(term_v),
        term_u=bc(term_u),
        term_K=bc(term_K),
        h2_Phi_w=bc(h_w),
        h2_Phi_dK=bc(h_dk),
        eps_L=bc(eps_L),
        eps1=bc(eps1),
        eps2=bc(eps2),
        rho_F=bc(rho_F),
    )
