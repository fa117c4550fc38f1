"""Estimators of SPEC section 2: OLS, L2-loss SVR (closed form), shrunk OLS.

Shapes: Z is (..., d, N0) with d = n + m (columns are [x_k; u_k]), F is
(..., n, N0). Estimates Theta = [A_hat B_hat] are (..., n, d). Batch dims
(...) of Z and F broadcast. Every batch element is computed with the same
per-matrix arithmetic (stacked LAPACK / BLAS calls), so a result does not
depend on the batch it was computed in, bit for bit.
"""

from __future__ import annotations

import numpy as np

from .errors import DimensionError, check_matrix

LOSS_SCALES = ("sum", "mean")


def _check(Z, F):
    Z = check_matrix("Z", Z, ("d", "N0"))
    F = check_matrix("F", F, ("n", Z.shape[-1]))
    if Z.shape[-1] < 1:
        raise DimensionError("Z", f"needs a sample count N0 >= 1, got shape {Z.shape}")
    return Z, F


def _gammas(gammas, *, allow_zero: bool) -> np.ndarray:
    g = np.asarray(gammas, dtype=float)
    if g.ndim > 1:
        raise DimensionError("gammas", f"must be a scalar or a 1-D array, got shape {g.shape}")
    g = np.atleast_1d(g)
    low_ok = g >= 0 if allow_zero else g > 0
    if g.size == 0 or not np.all(np.isfinite(g)) or not np.all(low_ok):
        raise ValueError(f"gammas must be finite and {'>=' if allow_zero else '>'} 0, got {g}")
    return g


def ridge_parameters(gammas, N0: int, loss_scale: str = "sum") -> np.ndarray:
    """Ridge parameter g of Theta = F Z^T (Z Z^T + g I)^-1 (SPEC section 2).

    "sum": g = gamma (the paper as written); "mean": the loss term divided by
    N0, i.e. g = gamma * N0. gamma > 0 (the 1/(2 gamma) of eq:SVR). -> (G,)
    """
    g = _gammas(gammas, allow_zero=False)
    if loss_scale == "sum":
        return g
    if loss_scale == "mean":
        return g * float(N0)
    raise ValueError(f"loss_scale must be one of {LOSS_SCALES}, got {loss_scale!r}")


REFINE_STEPS = 1
REFINE_COND_LIMIT = 1e8  # above this cond(Z Z^T) one refinement step is not enough: use QR


def fit_ols(Z: np.ndarray, F: np.ndarray) -> np.ndarray:
    """OLS Theta = F Z^T (Z Z^T)^-1 (SPEC section 2), batched. -> (..., n, d)

    Normal equations by Cholesky of Z Z^T plus ``REFINE_STEPS`` steps of
    iterative refinement on the residual (F - Theta Z) Z^T, which restores
    lstsq accuracy while cond(Z Z^T) * eps << 1. Datasets whose Gram matrix
    is singular or worse conditioned than ``REFINE_COND_LIMIT`` (e.g.
    N0 < d) take the least-squares path of :func:`_fit_ols_qr` instead.
    """
    Z, F = _check(Z, F)
    batch = np.broadcast_shapes(Z.shape[:-2], F.shape[:-2])
    Z = np.broadcast_to(Z, (*batch, *Z.shape[-2:]))
    F = np.broadcast_to(F, (*batch, *F.shape[-2:]))
    Zt = np.swapaxes(Z, -1, -2)
    G = np.matmul(Z, Zt)
    lam = np.linalg.eigvalsh(G)
    ok = lam[..., 0] > lam[..., -1] / REFINE_COND_LIMIT
    Gs = np.where(ok[..., None, None], G, np.eye(G.shape[-1]))
    Lc = np.linalg.cholesky(Gs)

    def solve(rhs):  # (Z Z^T)^-1 rhs^T, transposed back: rows of Theta
        y = np.linalg.solve(Lc, np.swapaxes(rhs, -1, -2))
        return np.swapaxes(np.linalg.solve(np.swapaxes(Lc, -1, -2), y), -1, -2)

    theta = solve(np.matmul(F, Zt))
    for _ in range(REFINE_STEPS):
        theta = theta + solve(np.matmul(F - np.matmul(theta, Z), Zt))
    if not ok.all():
        bad = ~ok
        theta[bad] = _fit_ols_qr(Z[bad], F[bad])
    return theta


def _fit_ols_qr(Z: np.ndarray, F: np.ndarray) -> np.ndarray:
    """Least squares as numpy.linalg.lstsq does, batched, for ill-conditioned Z.

    R-only QR of the augmented [Z^T F^T] = Q [[R11, R12], [0, R22]] reduces it
    to min ||R11 X - R12||, solved with the SVD of the small R11. Rank-deficient
    Z gives lstsq's minimum-norm solution with rcond = eps * max(d, N0).
    """
    d, N0 = Z.shape[-2:]
    R = np.linalg.qr(np.swapaxes(np.concatenate([Z, F], axis=-2), -1, -2), mode="r")
    U, s, Vh = np.linalg.svd(R[..., :d, :d], full_matrices=False)  # R11 = U diag(s) Vh
    cutoff = np.finfo(float).eps * max(d, N0) * s[..., :1]
    s_inv = np.divide(1.0, s, out=np.zeros_like(s), where=s > cutoff)
    UtR12 = np.matmul(np.swapaxes(U, -1, -2), R[..., :d, d:])  # (..., r, n)
    return np.swapaxes(np.matmul(np.swapaxes(Vh, -1, -2), s_inv[..., :, None] * UtR12), -1, -2)


def fit_svr(Z: np.ndarray, F: np.ndarray, gammas, loss_scale: str = "sum") -> np.ndarray:
    """SVR closed form Theta = F Z^T (Z Z^T + g I)^-1 for every gamma at once.

    SPEC section 2 (eq:SVR_all): ``g = gamma`` for loss_scale "sum",
    ``g = gamma * N0`` for "mean". Z Z^T = V diag(lam) V^T is decomposed once
    per dataset (eigh) and reused for all gammas:
    Theta_g = (F Z^T V) diag(1/(lam + g)) V^T. Eigenvalues of the PSD Z Z^T
    are floored at 0 (rounding only). ``gammas`` scalar or 1-D (G,), all > 0.
    -> (..., G, n, d)
    """
    Z, F = _check(Z, F)
    Zt = np.swapaxes(Z, -1, -2)
    return svr_from_gram(
        np.matmul(Z, Zt), np.matmul(F, Zt), Z.shape[-1], gammas, loss_scale=loss_scale
    )


def svr_from_gram(
    G: np.ndarray, FZt: np.ndarray, N0: int, gammas, *, loss_scale: str = "sum"
) -> np.ndarray:
    """:func:`fit_svr` from the sufficient statistics ``G = Z Z^T`` (..., d, d)
    and ``FZt = F Z^T`` (..., n, d) of datasets with ``N0`` samples each.

    The same arithmetic as :func:`fit_svr` (which calls it). -> (..., G, n, d)
    """
    G = np.asarray(G, dtype=float)
    FZt = np.asarray(FZt, dtype=float)
    g = ridge_parameters(gammas, N0, loss_scale)
    lam, V = np.linalg.eigh(G)  # (..., d), (..., d, d)
    lam = np.maximum(lam, 0.0)
    P = np.matmul(FZt, V)  # (..., n, d)
    denom = lam[..., None, None, :] + g[:, None, None]  # (..., G, 1, d)
    return np.matmul(P[..., None, :, :] / denom, np.swapaxes(V, -1, -2)[..., None, :, :])


def shrunk_ols(theta_ols: np.ndarray, gammas) -> np.ndarray:
    """Theta_OLS / (1 + gamma) for each gamma (SPEC section 2, Lemma 1's model).

    (..., n, d) -> (..., G, n, d)
    """
    theta = np.asarray(theta_ols, dtype=float)
    g = _gammas(gammas, allow_zero=True)
    return theta[..., None, :, :] / (1.0 + g)[:, None, None]


class SVRIdentifier:
    """scikit-learn-style wrapper of :func:`fit_svr` for one gamma (SPEC section 2).

    ``SVRIdentifier(gamma, loss_scale).fit(Z, F).coef_`` is Theta (..., n, d).
    """

    def __init__(self, gamma: float = 0.05, loss_scale: str = "sum"):
        self.gamma = gamma
        self.loss_scale = loss_scale

    def fit(self, Z, F):
        self.coef_ = fit_svr(Z, F, [self.gamma], self.loss_scale)[..., 0, :, :]
        return self

    def predict(self, Z):
        """Theta Z: (..., d, N) -> (..., n, N)."""
        return np.matmul(self.coef_, np.asarray(Z, dtype=float))


class OLSIdentifier:
    """scikit-learn-style wrapper of :func:`fit_ols` (SPEC section 2)."""

    def fit(self, Z, F):
        self.coef_ = fit_ols(Z, F)
        return self

    def predict(self, Z):
        """Theta Z: (..., d, N) -> (..., n, N)."""
        return np.matmul(self.coef_, np.asarray(Z, dtype=float))
