"""Observer gains of SPEC sections 4 and 5: Kalman predictor gain, the
certificate g(L), the certified design, and the reuse_gain policy.

Everything here is pure and vectorised over leading batch dimensions ``...``:

* ``kalman_predictor`` / ``kalman_gain``: steady-state Kalman predictor gain
  ``K = A P C^T (C P C^T + sigma_v^2 I)^-1`` with ``P`` the stabilising
  solution of ``P = A P A^T - A P C^T (C P C^T + R)^-1 C P A^T + Q``, computed
  for a whole batch of ``A`` at once by the structure-preserving doubling
  algorithm (SDA, Chu, Fan & Lin 2005) and, for ``sigma_w = 0``, by batched
  Newton-Hewer iterations started from an SDA gain.
* ``certificate``: ``g(L) = max_i sum_j |c_ij| + n r_A``,
  ``c = (1+gamma) A_tilde - L C`` (SPEC section 4, **Decision**).
* ``design_gain``: ``min ||L - K_hat||_F`` s.t. every row sum
  ``sum_j |c_ij| + n r_A <= 1 - margin``. For orthogonal ``C`` (in particular
  ``C = I``) this is an exact, vectorised Euclidean projection of every row of
  ``(1+gamma) A_tilde - K_hat C`` onto an l1 ball (Duchi et al. 2008); for any
  other ``C`` cvxpy + Clarabel solves it cell by cell.
* ``reuse_gains``: the ``reuse_gain`` sweep option along increasing ``N``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .errors import SpecError

__all__ = [
    "KALMAN_NONFINITE_INPUT",
    "KALMAN_NOT_CONVERGED",
    "KALMAN_OK",
    "KALMAN_REASONS",
    "KALMAN_UNDETECTABLE",
    "KALMAN_UNIT_CIRCLE",
    "GainResult",
    "KalmanResult",
    "ReuseResult",
    "certificate",
    "dare_residual",
    "design_gain",
    "kalman_gain",
    "kalman_predictor",
    "project_l1_ball",
    "reuse_gains",
]

# ---------------------------------------------------------------------------
# Kalman predictor gain (SPEC section 5)
# ---------------------------------------------------------------------------

KALMAN_OK = 0
KALMAN_UNDETECTABLE = 1  # (A, C) not detectable: an unstable mode is unobservable
KALMAN_UNIT_CIRCLE = 2  # sigma_w = 0 and A has an eigenvalue on the unit circle
KALMAN_NOT_CONVERGED = 3  # no stabilising solution reached (numerically ill-posed)
KALMAN_NONFINITE_INPUT = 4  # A, C, sigma_w or sigma_v not finite

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
}

_SDA_TOL = 1e-14  # relative step size at which doubling stops (quadratic convergence)
_SDA_A_TOL = 1e-8  # and |A_k|_F below this: A_k ~ (A - K C)^(2^k) has vanished
_SDA_MAX_ITER = 64  # 2^64 Riccati steps: ample even for rho(A - K C) = 1 - 1e-15
_NEWTON_TOL = 1e-13
_NEWTON_MAX_ITER = 60
_UNIT_CIRCLE_TOL = 1e-10
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
    have vanished, for sigma_w = 0 (Newton) rho(A - K C) < 1 is checked.
    """

    K: np.ndarray
    P: np.ndarray
    status: np.ndarray

    @property
    def ok(self) -> np.ndarray:
        return self.status == KALMAN_OK

    def reasons(self) -> np.ndarray:
        """Object array (...) of reason strings ('' where ok)."""
        out = np.empty(self.status.shape, dtype=object)
        for code, text in KALMAN_REASONS.items():
            out[self.status == code] = text
        return out


def _mT(X):
    return np.swapaxes(X, -1, -2)


def _sym(X):
    return 0.5 * (X + _mT(X))


def _fro(X):
    return np.sqrt(np.einsum("...ij,...ij->...", X, X))


def _spectral_radius(F):
    return np.abs(np.linalg.eigvals(F)).max(axis=-1)


def _stein(F, W):
    """Solve X = F X F^T + W for a batch (b, n, n) by a Kronecker linear solve."""
    b, n, _ = F.shape
    kron = np.einsum("bij,bkl->bikjl", F, F).reshape(b, n * n, n * n)
    M = np.eye(n * n) - kron
    x = np.linalg.solve(M, W.reshape(b, n * n, 1))
    return _sym(x.reshape(b, n, n))


def _gain_from_X(A, C, X):
    """K = A X C^T (C X C^T + I)^-1 (scaled form, X = P / sigma_v^2)."""
    p = C.shape[-2]
    S = C @ X @ _mT(C) + np.eye(p)
    return _mT(np.linalg.solve(S, C @ X @ _mT(A)))


def _sda(A, C, q):
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
            S = np.linalg.solve(W, np.concatenate([a, g], axis=-1))
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


def _newton(A, C, q, K0):
    """Newton-Hewer for the scaled DARE from stabilising gains K0 (b, n, p)."""
    b, n, _ = A.shape
    K = K0
    X = np.full_like(A, np.nan)
    converged = np.zeros(b, dtype=bool)
    active = np.arange(b)
    scaleA = _fro(A)
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
            done = finite & (_fro(k_new - k) <= _NEWTON_TOL * (_fro(k_new) + scaleA[active]))
            converged[active[done]] = True
            active = active[~done & finite]
    # one last Lyapunov solve so that X and K are exactly consistent
    ok = converged.copy()
    if ok.any():
        idx = np.flatnonzero(ok)
        F = A[idx] - K[idx] @ C[idx]
        X[idx] = _stein(F, q[idx, None, None] * np.eye(n) + K[idx] @ _mT(K[idx]))
    return X, converged


def _undetectable(A, C):
    """PBH test: True where some eigenvalue |lambda| >= 1 has rank [A - lambda I; C] < n."""
    b, n, _ = A.shape
    lam = np.linalg.eigvals(A)  # (b, n)
    M = A[:, None, :, :] - lam[:, :, None, None] * np.eye(n)  # (b, n, n, n)
    Cc = np.broadcast_to(C[:, None].astype(complex), (b, n) + C.shape[1:])
    smin = np.linalg.svd(np.concatenate([M, Cc], axis=-2), compute_uv=False)[..., -1]
    scale = np.maximum(1.0, _fro(A) + _fro(C))[:, None]
    return ((np.abs(lam) >= 1.0 - _UNIT_CIRCLE_TOL) & (smin <= _PBH_TOL * scale)).any(axis=-1)


def _broadcast_system(A, C, sigma_w, sigma_v):
    A = np.asarray(A, dtype=float)
    C = np.asarray(C, dtype=float)
    if A.ndim < 2 or A.shape[-1] != A.shape[-2]:
        raise SpecError("A", f"must be (..., n, n), got shape {A.shape}")
    n = A.shape[-1]
    if C.ndim < 2 or C.shape[-1] != n:
        raise SpecError("C", f"must be (..., p, {n}), got shape {C.shape}")
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


def kalman_predictor(A, C, sigma_w, sigma_v) -> KalmanResult:
    """Steady-state Kalman predictor of x+ = A x + w, y = C x + v (SPEC section 5).

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
    if zero_v.any():
        idx = np.flatnonzero(zero_v)
        if p != n or np.any(np.linalg.cond(C[idx]) > 1e12):
            raise SpecError("sigma_v", "sigma_v = 0 requires a square invertible C")
        K[idx] = _mT(np.linalg.solve(_mT(C[idx]), _mT(A[idx])))
        P[idx] = (sw[idx] ** 2)[:, None, None] * np.eye(n)
        status[idx] = KALMAN_OK

    # Scaled DARE: X = P / sigma_v^2 solves X = A X (I + C^T C X)^-1 A^T + q I, q = (sigma_w/sigma_v)^2
    todo = finite & (sv > 0)
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
            unit[z] = (np.abs(np.abs(np.linalg.eigvals(a[z])) - 1.0) <= _UNIT_CIRCLE_TOL).any(-1)
            z_ok = z[conv[z] & ~unit[z]]
            conv[z] = False
            if z_ok.size:
                with np.errstate(all="ignore"):
                    K0 = _gain_from_X(a[z_ok], c[z_ok], X[z_ok])
                Xz, cz = _newton(a[z_ok], c[z_ok], np.zeros(z_ok.size), K0)
                if cz.any():  # Newton keeps A - K C stable in theory; verify it
                    Kz = _gain_from_X(a[z_ok[cz]], c[z_ok[cz]], Xz[cz])
                    cz[cz] = _spectral_radius(a[z_ok[cz]] - Kz @ c[z_ok[cz]]) < 1.0
                X[z_ok], conv[z_ok] = Xz, cz
        # one Newton-Hewer refinement step: its error is quadratic in the
        # doubling's (which loses a few digits when A has unstable modes)
        r_idx = np.flatnonzero(conv & ~zero_w)
        if r_idx.size:
            with np.errstate(all="ignore"):
                Kr = _gain_from_X(a[r_idx], c[r_idx], X[r_idx])
                Xr = _stein(
                    a[r_idx] - Kr @ c[r_idx], q[r_idx, None, None] * np.eye(n) + Kr @ _mT(Kr)
                )
            fin = np.isfinite(Xr).all(axis=(-1, -2))
            X[r_idx[fin]] = Xr[fin]
        with np.errstate(all="ignore"):
            Kc = _gain_from_X(a, c, X)
        good = conv & np.isfinite(Kc).all(axis=(-1, -2))
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


def kalman_gain(A, C, sigma_w, sigma_v) -> np.ndarray:
    """Steady-state Kalman predictor gain K = A P C^T (C P C^T + sigma_v^2 I)^-1.

    Batched over leading dims of A (..., n, n); C (p, n) shared or batched.
    sigma_v = 0 with square invertible C gives K = A C^-1. Where the DARE has
    no stabilising solution the entries are NaN; ``kalman_predictor`` returns
    the same K with P, a status code per cell and its reason.
    """
    return kalman_predictor(A, C, sigma_w, sigma_v).K


def dare_residual(A, C, sigma_w, sigma_v, P) -> np.ndarray:
    """Relative residual of the filter DARE at P, batched -> (...)."""
    A = np.asarray(A, float)
    C = np.asarray(C, float)
    P = np.asarray(P, float)
    n, p = A.shape[-1], C.shape[-2]
    Q = (np.asarray(sigma_w, float) ** 2)[..., None, None] * np.eye(n)
    R = (np.asarray(sigma_v, float) ** 2)[..., None, None] * np.eye(p)
    S = C @ P @ _mT(C) + R
    rhs = A @ P @ _mT(A) - A @ P @ _mT(C) @ np.linalg.solve(S, C @ P @ _mT(A)) + Q
    return _fro(rhs - P) / (_fro(P) + _fro(Q) + _fro(R))


# ---------------------------------------------------------------------------
# Certificate and design (SPEC section 4)
# ---------------------------------------------------------------------------


@dataclass
class GainResult:
    """Observer gains for a batch of cells.

    L (..., n, p); g_L (...) = certificate(L); certified (...) bool = g_L < 1
    (the SPEC section 4 **Decision**; NaN g gives False); feasible (...) bool:
    the design's margin constraint could be met (False means the fallback
    min g(L) was used). Cells with a non-finite input (e.g. a NaN K_hat) have
    NaN L and g, certified and feasible False (general-C path: also a cell
    where Clarabel fails outright).
    """

    L: np.ndarray
    g_L: np.ndarray
    certified: np.ndarray
    feasible: np.ndarray | None = None


def _scaled_center(A_tilde, gamma):
    A_tilde = np.asarray(A_tilde, dtype=float)
    gamma = np.asarray(gamma, dtype=float)
    return (1.0 + gamma)[..., None, None] * A_tilde


def certificate(L, A_tilde, gamma, r_A, C) -> np.ndarray:
    """g(L) = max_i sum_j |c_ij| + n r_A with c = (1+gamma) A_tilde - L C. -> (...)

    L (..., n, p), A_tilde (..., n, n), C (p, n) or (..., p, n); gamma and r_A
    broadcast against the batch shape (use gamma = 0 for OLS).
    """
    Ct = _scaled_center(A_tilde, gamma)
    n = Ct.shape[-1]
    c = Ct - np.asarray(L, dtype=float) @ np.asarray(C, dtype=float)
    return np.abs(c).sum(axis=-1).max(axis=-1) + n * np.asarray(r_A, dtype=float)


def project_l1_ball(V, radius) -> np.ndarray:
    """Euclidean projection of every vector V[..., :] onto {w : ||w||_1 <= radius}.

    Exact sort-based algorithm (Duchi, Shalev-Shwartz, Singer & Chandra 2008),
    vectorised over all leading dims; ``radius`` (...) >= 0 broadcasts against
    V.shape[:-1]. Radius 0 gives the zero vector.
    """
    V = np.asarray(V, dtype=float)
    radius = np.broadcast_to(np.asarray(radius, dtype=float), V.shape[:-1])
    d = V.shape[-1]
    a = np.abs(V)
    u = -np.sort(-a, axis=-1)
    cs = np.cumsum(u, axis=-1)
    j = np.arange(1, d + 1)
    cond = u - (cs - radius[..., None]) / j > 0
    k = np.where(cond, j, 0).max(axis=-1).clip(min=1)
    theta = (np.take_along_axis(cs, (k - 1)[..., None], axis=-1)[..., 0] - radius) / k
    W = np.sign(V) * np.maximum(a - theta[..., None], 0.0)
    inside = a.sum(axis=-1) <= radius
    return np.where(inside[..., None], V, W)


def _is_orthogonal(C) -> bool:
    C = np.asarray(C, dtype=float)
    if C.shape[-1] != C.shape[-2]:
        return False
    p = C.shape[-1]
    return bool(np.all(np.abs(_mT(C) @ C - np.eye(p)) <= 1e-12))


def design_gain(A_tilde, gamma, r_A, C, K_hat, margin=0.01, method="auto") -> GainResult:
    """min ||L - K_hat||_F s.t. sum_j |c_ij(L)| + n r_A <= 1 - margin for all i.

    A_tilde (..., n, n), K_hat (..., n, p), C (p, n) or (..., p, n); gamma,
    r_A, margin broadcast against the batch shape. If the constraint is
    infeasible the fallback is ``min_L g(L)`` (ties broken by the L closest to
    K_hat) and ``feasible`` is False; ``certified`` is always ``g(L) < 1``.

    method: "auto" (closed form when C is orthogonal, e.g. C = I, else
    cvxpy), "closed_form" (requires orthogonal C) or "cvxpy" (per cell).
    """
    Ct = _scaled_center(A_tilde, gamma)
    K_hat = np.asarray(K_hat, dtype=float)
    C = np.asarray(C, dtype=float)
    n, p = Ct.shape[-1], C.shape[-2]
    if K_hat.shape[-2:] != (n, p):
        raise SpecError("K_hat", f"must be (..., {n}, {p}), got shape {K_hat.shape}")
    r_A = np.asarray(r_A, dtype=float)
    batch = np.broadcast_shapes(
        Ct.shape[:-2], K_hat.shape[:-2], C.shape[:-2], r_A.shape, np.shape(margin)
    )
    Ct = np.broadcast_to(Ct, batch + (n, n))
    K_hat = np.broadcast_to(K_hat, batch + (n, p))
    Cb = np.broadcast_to(C, batch + (p, n))
    rho = np.broadcast_to(1.0 - np.asarray(margin, dtype=float) - n * r_A, batch)
    good = (
        np.isfinite(Ct).all(axis=(-1, -2))
        & np.isfinite(K_hat).all(axis=(-1, -2))
        & np.isfinite(Cb).all(axis=(-1, -2))
        & np.isfinite(rho)
    )

    orth = _is_orthogonal(C)
    if method == "auto":
        method = "closed_form" if orth else "cvxpy"
    if method == "closed_form":
        if not orth:
            raise ValueError("closed_form design needs an orthogonal C (e.g. C = I)")
        feasible = good & (rho >= 0)
        with np.errstate(invalid="ignore"):
            c0 = Ct - K_hat @ Cb
            # infeasible -> radius 0 -> c = 0, the unique minimiser of g(L)
            c = project_l1_ball(c0, np.where(feasible, rho, 0.0)[..., None])
            L = (Ct - c) @ _mT(Cb)  # C orthogonal: L C = Ct - c
    elif method == "cvxpy":
        L = np.full(batch + (n, p), np.nan)
        feasible = np.zeros(batch, dtype=bool)
        solver = _CvxpyDesign(n, p)
        for ix in np.ndindex(batch):
            if good[ix]:
                L[ix], feasible[ix] = solver.solve(Ct[ix], Cb[ix], K_hat[ix], rho[ix])
    else:
        raise ValueError(f"unknown method {method!r}")

    L = np.where(good[..., None, None], L, np.nan)
    g = certificate(L, Ct, 0.0, r_A, Cb)
    with np.errstate(invalid="ignore"):
        certified = g < 1.0
    return GainResult(L=L, g_L=g, certified=certified, feasible=feasible & good)


class _CvxpyDesign:
    """The general-C design as parametrised cvxpy problems, solved by Clarabel."""

    def __init__(self, n, p):
        import cvxpy as cp

        self.cp = cp
        self.L = cp.Variable((n, p))
        self.Ct = cp.Parameter((n, n))
        self.C = cp.Parameter((p, n))
        self.K = cp.Parameter((n, p))
        self.rho = cp.Parameter()
        rows = cp.sum(cp.abs(self.Ct - self.L @ self.C), axis=1)
        self.main = cp.Problem(cp.Minimize(cp.sum_squares(self.L - self.K)), [rows <= self.rho])
        self.t = cp.Variable()
        self.min_g = cp.Problem(cp.Minimize(self.t), [rows <= self.t])

    def solve(self, Ct, C, K_hat, rho):
        cp = self.cp
        self.Ct.value, self.C.value, self.K.value = Ct, C, K_hat
        self.rho.value = float(rho)
        self.main.solve(solver=cp.CLARABEL)
        if self.main.status in (cp.OPTIMAL, cp.OPTIMAL_INACCURATE):
            return self.L.value, True
        nan = np.full(self.L.shape, np.nan)
        if self.main.status not in (cp.INFEASIBLE, cp.INFEASIBLE_INACCURATE):
            return nan, False  # solver failure: NaN gain, not certified
        # fallback: min g(L); then, among the minimisers, the L closest to K_hat
        self.min_g.solve(solver=cp.CLARABEL)
        if self.min_g.status not in (cp.OPTIMAL, cp.OPTIMAL_INACCURATE):
            return nan, False
        L1 = self.L.value
        self.rho.value = float(np.abs(Ct - L1 @ C).sum(axis=-1).max())
        self.main.solve(solver=cp.CLARABEL)
        if self.main.status in (cp.OPTIMAL, cp.OPTIMAL_INACCURATE):
            L2 = self.L.value
            if np.abs(Ct - L2 @ C).sum(axis=-1).max() <= self.rho.value + 1e-9:
                return L2, False
        return L1, False


# ---------------------------------------------------------------------------
# reuse_gain (SPEC section 4)
# ---------------------------------------------------------------------------


@dataclass
class ReuseResult:
    """The reuse_gain choice along the N axis (axis 0).

    L (nN, ..., n, p), g_L (nN, ...) evaluated with each N's own estimate,
    certified (nN, ...) = g_L < 1, reused (nN, ...) True where the previous
    N's gain was kept, source (nN, ...) int: index along N of the design used.
    """

    L: np.ndarray
    g_L: np.ndarray
    certified: np.ndarray
    reused: np.ndarray
    source: np.ndarray


def reuse_gains(L, A_tilde, gamma, r_A, C) -> ReuseResult:
    """reuse_gain policy along increasing N (SPEC section 4).

    L (nN, ..., n, p): the gain designed at each N (axis 0 sorted by
    increasing N, same system, sigma_w, estimator, gamma, rep along the rest);
    A_tilde (nN, ..., n, n), gamma and r_A broadcast to (nN, ...); C (p, n).

    At the first N the designed gain is used. At a later N the previously
    chosen gain is kept iff it was certified at the previous N and is still
    certified (g < 1) for the new estimate (A_tilde, gamma, r_A); otherwise
    the gain designed at this N is used. Vectorised over all non-N dims.
    """
    L = np.asarray(L, dtype=float)
    Ct = _scaled_center(A_tilde, gamma)
    n, p = L.shape[-2], L.shape[-1]
    batch = np.broadcast_shapes(L.shape[:-2], Ct.shape[:-2], np.shape(r_A))
    L = np.broadcast_to(L, batch + (n, p))
    Ct = np.broadcast_to(Ct, batch + (n, n))
    r_A = np.broadcast_to(np.asarray(r_A, dtype=float), batch)
    nN = batch[0]

    out_L = np.empty(batch + (n, p))
    g = np.empty(batch)
    reused = np.zeros(batch, dtype=bool)
    source = np.empty(batch, dtype=np.intp)
    with np.errstate(invalid="ignore"):
        for k in range(nN):
            g_new = certificate(L[k], Ct[k], 0.0, r_A[k], C)
            if k == 0:
                keep = np.zeros(batch[1:], dtype=bool)
                g_prev = np.zeros(batch[1:])
            else:
                g_prev = certificate(out_L[k - 1], Ct[k], 0.0, r_A[k], C)
                keep = (g[k - 1] < 1.0) & (g_prev < 1.0)
            out_L[k] = np.where(keep[..., None, None], out_L[k - 1] if k else L[k], L[k])
            g[k] = np.where(keep, g_prev, g_new)
            reused[k] = keep
            source[k] = np.where(keep, source[k - 1] if k else 0, k)
        certified = g < 1.0
    return ReuseResult(L=out_L, g_L=g, certified=certified, reused=reused, source=source)
