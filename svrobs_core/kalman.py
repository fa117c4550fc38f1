"""Steady-state Kalman predictor gain (docs/science.md#5-the-optimal-gain-k), batched.

``kalman_predictor`` / ``kalman_gain``: ``K = A P C^T (C P C^T + sigma_v^2 I)^-1``
with ``P`` the stabilising solution of
``P = A P A^T - A P C^T (C P C^T + R)^-1 C P A^T + Q``, computed for a whole
batch of ``A`` at once by the structure-preserving doubling algorithm (SDA,
Chu, Fan & Lin 2005) and, for ``sigma_w = 0``, by batched Newton-Hewer
iterations started from an SDA gain. Failures are status codes with a reason
per cell (:class:`KalmanResult`), never an exception.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import cast

import numpy as np
from numpy.typing import ArrayLike

from .array_types import Array, BoolArray, FloatArray
from .errors import SpecError, check_matrix
from .linalg import solve as _solve
from .norms import UNIT_CIRCLE_TOL, is_schur, spectral_radius
from .systems import SIGMA_V0_COND_LIMIT

__all__ = [
    "KALMAN_NONFINITE_INPUT",
    "KALMAN_NOT_CONVERGED",
    "KALMAN_OK",
    "KALMAN_REASONS",
    "KALMAN_SCALE_OVERFLOW",
    "KALMAN_UNDETECTABLE",
    "KALMAN_UNIT_CIRCLE",
    "KalmanResult",
    "dare_residual",
    "kalman_gain",
    "kalman_predictor",
]

# ---------------------------------------------------------------------------
# Kalman predictor gain (docs/science.md#5-the-optimal-gain-k)
# ---------------------------------------------------------------------------

KALMAN_OK = 0
KALMAN_UNDETECTABLE = 1  # (A, C) not detectable: an unstable mode is unobservable
KALMAN_UNIT_CIRCLE = 2  # sigma_w = 0 and A has an eigenvalue on the unit circle
KALMAN_NOT_CONVERGED = 3  # no stabilising solution reached (numerically ill-posed)
KALMAN_NONFINITE_INPUT = 4  # A, C, sigma_w or sigma_v not finite
KALMAN_SCALE_OVERFLOW = 5  # (sigma_w / sigma_v)^2 overflows and C is not square invertible

KALMAN_REASONS = {
    KALMAN_OK: "",
    KALMAN_UNDETECTABLE: "Kalman gain undefined: (A, C) is not detectable",
    KALMAN_UNIT_CIRCLE: (
        "Kalman gain undefined: sigma_w = 0 and A has an eigenvalue on the "
        "unit circle, so the DARE has no stabilising solution"
    ),
    KALMAN_NOT_CONVERGED: (
        "Kalman gain undefined: the DARE iteration did not reach a "
        "stabilising solution (ill-conditioned problem)"
    ),
    KALMAN_NONFINITE_INPUT: "Kalman gain undefined: non-finite A, C, sigma_w or sigma_v",
    KALMAN_SCALE_OVERFLOW: (
        "Kalman gain undefined: (sigma_w / sigma_v)^2 is beyond the double range "
        "and C is not square and invertible (the limit sigma_v -> 0 needs it)"
    ),
}

_SDA_TOL = 1e-14  # relative step size at which doubling stops (quadratic convergence)
_SDA_A_TOL = 1e-8  # and |A_k|_F below this: A_k ~ (A - K C)^(2^k) has vanished
_SDA_MAX_ITER = 64  # 2^64 Riccati steps: ample even for rho(A - K C) = 1 - 1e-15
_NEWTON_TOL = 1e-13
# a step this small that no longer halves: Newton's quadratic phase is over and the
# rest is rounding (a strongly unstable A leaves the Stein solve about 1e-9 off)
_NEWTON_STALL_TOL = 1e-8
_NEWTON_MAX_ITER = 60
# the refinement step after the doubling is kept where cond_1(I - F (x) F) is at
# most this: below it, the step cuts the doubling's largest error (2.7e-14 to
# 1.8e-15 at cond < 1e2, 3.4e-11 to 2.8e-13 at 1e5-1e6); above it, the Stein
# solve's rounding dominates (8.9e-5 against 1.8e-9 beyond 1e8), against a
# 60-digit solution on 600 random systems of 2-3 states (measured 2026-12-07; the
# worst case and 60 of those systems are in tests/core/test_gains.py)
_REFINE_MAX_COND = 1e6
# a converged gain whose A - K C has a spectral radius at least this is checked for
# an undetectable mode (PBH), which no gain moves
_SUSPECT_RHO = 0.999
_PBH_TOL = 1e-9


@dataclass
class KalmanResult:
    """Batched steady-state Kalman predictor.

    K (..., n, p): predictor gain, NaN where ``status != KALMAN_OK``.
    P (..., n, n): stabilising DARE solution (the one-step prediction error
        covariance), NaN where ``status != KALMAN_OK``.
    status (...) int: ``KALMAN_OK`` or one of the ``KALMAN_*`` failure codes;
        ``KALMAN_REASONS[code]`` is a sentence for the record's ``notes``.

    A cell is OK only when the iteration converged to the *stabilising*
    solution: for sigma_w > 0 the doubling matrix A_k ~ (A - K C)^(2^k) must
    have vanished, for sigma_w = 0 (Newton) A - K C is checked Schur stable
    (norms.schur_stable).
    """

    K: FloatArray
    P: FloatArray
    status: Array

    @property
    def ok(self) -> BoolArray:
        ok: BoolArray = self.status == KALMAN_OK
        return ok

    def reasons(self) -> Array:
        """Object array (...) of reason strings ('' where ok)."""
        out = np.empty(self.status.shape, dtype=object)
        for code, text in KALMAN_REASONS.items():
            out[self.status == code] = text
        return out


def _square_invertible(C: Array, n: int) -> BoolArray:
    """Per (p, n) C of the batch (b, p, n): square and invertible to SIGMA_V0_COND_LIMIT."""
    if C.shape[-2] != n or C.shape[0] == 0:
        return np.zeros(C.shape[0], dtype=bool)
    ok: BoolArray = np.linalg.cond(C) <= SIGMA_V0_COND_LIMIT
    return ok


def _mT(X: Array) -> Array:
    return np.swapaxes(X, -1, -2)


def _sym(X: Array) -> Array:
    return 0.5 * (X + _mT(X))


def _fro(X: Array) -> FloatArray:
    out: FloatArray = np.sqrt(np.einsum("...ij,...ij->...", X, X))
    return out


def _norm1(F: Array) -> FloatArray:
    """||F||_1 (the largest column sum of |F|) of a batch (b, n, n) -> (b,)."""
    out: FloatArray = np.abs(F).sum(axis=-2).max(axis=-1)
    return out


def _stein_matrix(F: Array) -> Array:
    """I - F (x) F (b, n^2, n^2): the Kronecker form of X -> X - F X F^T."""
    b, n, _ = F.shape
    kron = np.einsum("bij,bkl->bikjl", F, F).reshape(b, n * n, n * n)
    out: Array = np.eye(n * n) - kron
    return out


def _stein(F: Array, W: Array, M: Array | None = None) -> Array:
    """Solve X = F X F^T + W for a batch (b, n, n) by a Kronecker linear solve
    (M: ``_stein_matrix(F)`` when the caller has it)."""
    b, n, _ = F.shape
    x = _solve(_stein_matrix(F) if M is None else M, W.reshape(b, n * n, 1))
    return _sym(x.reshape(b, n, n))


def _gain_from_X(A: Array, C: Array, X: Array) -> Array:
    """K = A X C^T (C X C^T + I)^-1 (scaled form, X = P / sigma_v^2)."""
    p = C.shape[-2]
    S = C @ X @ _mT(C) + np.eye(p)
    return _mT(_solve(S, C @ X @ _mT(A)))


def _sda(A: Array, C: Array, q: Array) -> tuple[Array, BoolArray]:
    """Doubling for X = A X (I + C^T C X)^-1 A^T + q I on a batch (b, ...).

    In the control-DARE form X = Ac^T X (I + G X)^-1 Ac + H with Ac = A^T,
    G = C^T C, H = q I; H_k -> X quadratically when the stabilising solution
    exists and (A, sqrt(q) I) has no unit-circle uncontrollable modes (q > 0).
    Returns X (b, n, n) and a converged mask (b,).
    """
    b, n, _ = A.shape
    I = np.eye(n)
    Ak = _mT(A).copy()
    Gk = np.broadcast_to(_mT(C) @ C, (b, n, n)).copy()
    Hk = q[:, None, None] * I
    converged = np.zeros(b, dtype=bool)
    failed = np.zeros(b, dtype=bool)
    active = np.arange(b)
    with np.errstate(all="ignore"):
        for _ in range(_SDA_MAX_ITER):
            if active.size == 0:
                break
            sel = slice(None) if active.size == b else active
            a, g, h = Ak[sel], Gk[sel], Hk[sel]
            W = I + g @ h
            S = _solve(W, np.concatenate([a, g], axis=-1))
            S1, S2 = S[..., :n], S[..., n:]
            h_new = _sym(h + _mT(a) @ h @ S1)
            g_new = _sym(g + a @ S2 @ _mT(a))
            a_new = a @ S1
            step = _fro(h_new - h)
            scale = _fro(h_new)
            finite = (
                np.isfinite(h_new).all(axis=(-1, -2))
                & np.isfinite(g_new).all(axis=(-1, -2))
                & np.isfinite(a_new).all(axis=(-1, -2))
            )
            Ak[sel], Gk[sel], Hk[sel] = a_new, g_new, h_new
            # A_k -> 0 exactly when H_k tends to the stabilising solution
            done = finite & (step <= _SDA_TOL * scale) & (_fro(a_new) <= _SDA_A_TOL)
            bad = ~finite
            converged[active[done]] = True
            failed[active[bad]] = True
            active = active[~(done | bad)]
    return Hk, converged & ~failed


def _newton(A: Array, C: Array, q: Array, K0: Array) -> tuple[Array, BoolArray]:
    """Newton-Hewer for the scaled DARE from stabilising gains K0 (b, n, p)."""
    b, n, _ = A.shape
    K = K0
    X = np.full_like(A, np.nan)
    converged = np.zeros(b, dtype=bool)
    active = np.arange(b)
    scaleA = _fro(A)
    last = np.full(b, np.inf)  # each cell's previous step
    with np.errstate(all="ignore"):
        for _ in range(_NEWTON_MAX_ITER):
            if active.size == 0:
                break
            a, c, k = A[active], C[active], K[active]
            F = a - k @ c
            W = q[active, None, None] * np.eye(n) + k @ _mT(k)
            x = _stein(F, W)
            k_new = _gain_from_X(a, c, x)
            X[active], K[active] = x, k_new
            finite = np.isfinite(k_new).all(axis=(-1, -2))
            step = _fro(k_new - k) / (_fro(k_new) + scaleA[active])
            stalled = (step <= _NEWTON_STALL_TOL) & (step > 0.5 * last[active])
            done = finite & ((step <= _NEWTON_TOL) | stalled)
            last[active] = step
            converged[active[done]] = True
            active = active[~done & finite]
    # one last Lyapunov solve so that X and K are exactly consistent
    ok = converged.copy()
    if ok.any():
        idx = np.flatnonzero(ok)
        F = A[idx] - K[idx] @ C[idx]
        X[idx] = _stein(F, q[idx, None, None] * np.eye(n) + K[idx] @ _mT(K[idx]))
    return X, converged


def _undetectable(A: Array, C: Array) -> BoolArray:
    """PBH test: True where some eigenvalue |lambda| >= 1 has rank [A - lambda I; C] < n."""
    b, n, _ = A.shape
    lam = np.linalg.eigvals(A)  # (b, n)
    M = A[:, None, :, :] - lam[:, :, None, None] * np.eye(n)  # (b, n, n, n)
    Cc = np.broadcast_to(C[:, None].astype(complex), (b, n) + C.shape[1:])
    smin = np.linalg.svd(np.concatenate([M, Cc], axis=-2), compute_uv=False)[..., -1]
    scale = np.maximum(1.0, _fro(A) + _fro(C))[:, None]
    return cast(
        BoolArray,
        ((np.abs(lam) >= 1.0 - UNIT_CIRCLE_TOL) & (smin <= _PBH_TOL * scale)).any(axis=-1),
    )


def _broadcast_system(
    A: ArrayLike, C: ArrayLike, sigma_w: ArrayLike, sigma_v: ArrayLike
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray, tuple[int, ...], int, int]:
    A = check_matrix("A", A, ("n", "n"))
    n = A.shape[-1]
    C = check_matrix("C", C, ("p", n))
    p = C.shape[-2]
    sw = np.asarray(sigma_w, dtype=float)
    sv = np.asarray(sigma_v, dtype=float)
    if np.any(sw < 0):
        raise SpecError("sigma_w", "must be >= 0")
    if np.any(sv < 0):
        raise SpecError("sigma_v", "must be >= 0")
    batch = np.broadcast_shapes(A.shape[:-2], C.shape[:-2], sw.shape, sv.shape)
    A = np.broadcast_to(A, batch + (n, n)).reshape(-1, n, n)
    C = np.broadcast_to(C, batch + (p, n)).reshape(-1, p, n)
    sw = np.broadcast_to(sw, batch).reshape(-1)
    sv = np.broadcast_to(sv, batch).reshape(-1)
    return A, C, sw, sv, batch, n, p


def kalman_predictor(
    A: ArrayLike, C: ArrayLike, sigma_w: ArrayLike, sigma_v: ArrayLike
) -> KalmanResult:
    """Steady-state Kalman predictor of x+ = A x + w, y = C x + v
    (docs/science.md#5-the-optimal-gain-k).

    A (..., n, n); C (p, n) or (..., p, n); sigma_w, sigma_v scalars or arrays
    broadcasting against the batch shape (...). Q = sigma_w^2 I, R = sigma_v^2 I.

    ``sigma_v = 0`` needs a square invertible C and gives K = A C^-1, P = Q;
    any other ``sigma_v = 0`` cell raises ``SpecError('sigma_v', ...)``.
    Cells without a stabilising DARE solution get NaN K, P and a status code.
    """
    A, C, sw, sv, batch, n, p = _broadcast_system(A, C, sigma_w, sigma_v)
    b = A.shape[0]
    K = np.full((b, n, p), np.nan)
    P = np.full((b, n, n), np.nan)
    status = np.full(b, KALMAN_NOT_CONVERGED, dtype=np.int8)

    finite = (
        np.isfinite(A).all(axis=(-1, -2))
        & np.isfinite(C).all(axis=(-1, -2))
        & np.isfinite(sw)
        & np.isfinite(sv)
    )
    status[~finite] = KALMAN_NONFINITE_INPUT

    # sigma_v = 0: K = A C^-1 (validation error unless C is square and invertible)
    zero_v = finite & (sv == 0)
    if zero_v.any() and not _square_invertible(C[zero_v], n).all():
        raise SpecError("sigma_v", "sigma_v = 0 requires a square invertible C")
    # sigma_v > 0 so small against sigma_w that q = (sigma_w/sigma_v)^2 overflows:
    # K = A C^-1 (1 + O(sigma_v^2 / sigma_w^2)) is the sigma_v = 0 gain to the last bit
    with np.errstate(over="ignore", divide="ignore", invalid="ignore"):
        tiny_v = finite & (sv > 0) & ~np.isfinite((sw / np.where(sv > 0, sv, 1.0)) ** 2)
    t_idx = np.flatnonzero(tiny_v)
    ok_v = _square_invertible(C[t_idx], n)
    status[t_idx[~ok_v]] = KALMAN_SCALE_OVERFLOW
    limit = zero_v.copy()
    limit[t_idx[ok_v]] = True
    if limit.any():
        idx = np.flatnonzero(limit)
        K[idx] = _mT(_solve(_mT(C[idx]), _mT(A[idx])))
        P[idx] = (sw[idx] ** 2)[:, None, None] * np.eye(n)
        status[idx] = KALMAN_OK

    # Scaled DARE: X = P / sigma_v^2 solves X = A X (I + C^T C X)^-1 A^T + q I, q = (sigma_w/sigma_v)^2
    todo = finite & (sv > 0) & ~tiny_v
    if todo.any():
        idx = np.flatnonzero(todo)
        a, c = A[idx], C[idx]
        q = (sw[idx] / sv[idx]) ** 2
        zero_w = q == 0
        # q > 0: doubling directly.  q = 0: doubling with q = 1 only for a
        # stabilising start gain, then Newton-Hewer to the q = 0 solution
        # (SDA itself cannot leave H = 0, so it would miss unstable modes).
        X, conv = _sda(a, c, np.where(zero_w, 1.0, q))
        unit = np.zeros(idx.size, dtype=bool)
        if zero_w.any():
            z = np.flatnonzero(zero_w)
            unit[z] = (np.abs(np.abs(np.linalg.eigvals(a[z])) - 1.0) <= UNIT_CIRCLE_TOL).any(-1)
            z_ok = z[conv[z] & ~unit[z]]
            conv[z] = False
            if z_ok.size:
                with np.errstate(all="ignore"):
                    K0 = _gain_from_X(a[z_ok], c[z_ok], X[z_ok])
                Xz, cz = _newton(a[z_ok], c[z_ok], np.zeros(z_ok.size), K0)
                if cz.any():  # Newton keeps A - K C stable in theory; verify it
                    Kz = _gain_from_X(a[z_ok[cz]], c[z_ok[cz]], Xz[cz])
                    cz[cz] = is_schur(a[z_ok[cz]] - Kz @ c[z_ok[cz]])
                X[z_ok], conv[z_ok] = Xz, cz
        # one Newton-Hewer refinement step: its error is quadratic in the
        # doubling's (which loses a few digits when A has unstable modes), plus
        # the Stein solve's own, about cond(I - F (x) F) eps: kept where that
        # condition number is at most _REFINE_MAX_COND
        r_idx = np.flatnonzero(conv & ~zero_w)
        if r_idx.size:
            with np.errstate(all="ignore"):
                Kr = _gain_from_X(a[r_idx], c[r_idx], X[r_idx])
                F = a[r_idx] - Kr @ c[r_idx]
                M = _stein_matrix(F)
                Xr = _stein(F, q[r_idx, None, None] * np.eye(n) + Kr @ _mT(Kr), M)
                # cond_1(M) <= (1 + f^2) / (1 - f^2), f = ||F||_1 < 1: at most 199
                # where f^2 < 0.99; the condition number itself only elsewhere
                well = _norm1(F) ** 2 < 0.99
                hard = np.flatnonzero(~well)
                well[hard] = np.linalg.cond(M[hard], 1) <= _REFINE_MAX_COND
            use = np.isfinite(Xr).all(axis=(-1, -2)) & well
            X[r_idx[use]] = Xr[use]
        with np.errstate(all="ignore"):
            Kc = _gain_from_X(a, c, X)
        good = conv & np.isfinite(Kc).all(axis=(-1, -2))
        # the doubling can also stop on an undetectable (A, C), its A_k vanishing
        # only by rounding once H_k is huge: the gain leaves a mode with |lambda| >= 1
        # in A - K C. Such a mode keeps rho(A - K C) near 1 or above, so only those
        # cells are put to the PBH test
        g = np.flatnonzero(good)
        with np.errstate(all="ignore"):
            F = a[g] - Kc[g] @ c[g]
        # rho <= min(||F||_1, ||F||_inf): the eigenvalues only where that is not below
        near = np.flatnonzero(~(np.minimum(_norm1(F), _norm1(_mT(F))) < _SUSPECT_RHO))
        if near.size:
            rho = spectral_radius(F[near])
            suspect = ~(rho < _SUSPECT_RHO)
            s_idx = g[near[suspect]]
            good[s_idx] = (rho[suspect] < 1.0) & ~_undetectable(a[s_idx], c[s_idx])
        st = np.full(idx.size, KALMAN_NOT_CONVERGED, dtype=np.int8)
        st[good] = KALMAN_OK
        st[unit & ~good] = KALMAN_UNIT_CIRCLE
        bad = np.flatnonzero(~good)
        if bad.size:
            und = _undetectable(a[bad], c[bad])
            st[bad[und]] = KALMAN_UNDETECTABLE
        g_idx = idx[good]
        K[g_idx] = Kc[good]
        P[g_idx] = (sv[g_idx] ** 2)[:, None, None] * X[good]
        status[idx] = st

    return KalmanResult(
        K=K.reshape(batch + (n, p)),
        P=P.reshape(batch + (n, n)),
        status=status.reshape(batch),
    )


def kalman_gain(A: ArrayLike, C: ArrayLike, sigma_w: ArrayLike, sigma_v: ArrayLike) -> FloatArray:
    """Steady-state Kalman predictor gain K = A P C^T (C P C^T + sigma_v^2 I)^-1.

    Batched over leading dims of A (..., n, n); C (p, n) shared or batched.
    sigma_v = 0 with square invertible C gives K = A C^-1. Where the DARE has
    no stabilising solution the entries are NaN; ``kalman_predictor`` returns
    the same K with P, a status code per cell and its reason.
    """
    return kalman_predictor(A, C, sigma_w, sigma_v).K


def dare_residual(
    A: ArrayLike, C: ArrayLike, sigma_w: ArrayLike, sigma_v: ArrayLike, *, P: ArrayLike
) -> FloatArray:
    """Relative residual of the filter DARE at P, batched -> (...)."""
    A = np.asarray(A, float)
    C = np.asarray(C, float)
    P = np.asarray(P, float)
    n, p = A.shape[-1], C.shape[-2]
    Q = (np.asarray(sigma_w, float) ** 2)[..., None, None] * np.eye(n)
    R = (np.asarray(sigma_v, float) ** 2)[..., None, None] * np.eye(p)
    S = C @ P @ _mT(C) + R
    rhs = A @ P @ _mT(A) - A @ P @ _mT(C) @ _solve(S, C @ P @ _mT(A)) + Q
    return _fro(rhs - P) / (_fro(P) + _fro(Q) + _fro(R))
