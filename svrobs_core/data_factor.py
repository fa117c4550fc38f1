"""The regression data factorised once per dataset, and what its rounding can cost.

The self-normalized box (docs/uncertainty.md) needs ``V = Z Z^T + lam I``
through diag(V^-1), log det and eigenvalues. Forming ``Z Z^T`` squares the
conditioning: its rounding error ~u ||Z||^2 swamps the small eigenvalues once
cond(V) passes ~1e12. :func:`data_factor` works on the data instead: an
R-only Householder QR of ``[Z^T F^T]`` (backward stable: the exact QR of data
off by ~u ||Z_j|| per regressor row) and the SVD of the small triangle
``R11`` (``Z^T = Q R11``), so ``Z Z^T = U diag(s^2) U^T`` with ``s`` accurate to
~u ||Z|| absolutely. See docs/uncertainty.md#numerical-accuracy-of-the-radii.

:func:`relative_error` estimates the relative forward error of every radius
from that backward error; :func:`estimate_margin` bounds, per row of an
estimate, how far the computed estimate can be from the exact estimator on
the data (and the data from their exact simulation), in the V-norm of the box.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["GramFactor", "data_factor", "estimate_margin", "gram_factor", "relative_error"]

U_ROUND = np.finfo(float).eps / 2  # unit roundoff of a double


@dataclass
class GramFactor:
    """Z Z^T = U diag(lam) U^T per dataset (SPEC section 2), with what the error
    estimates need.

    lam (..., d) ascending, >= 0; U (..., d, d). ``formed``: from a formed Gram
    matrix (:func:`gram_factor`; its error grows like u cond(V)) rather than
    from the data (:func:`data_factor`; like u sqrt(cond(V))). From the data
    also: ``col`` (..., d) the norms of the rows of Z (the regressors),
    ``fnorm`` (..., n) of the rows of F, and the triangle of the QR of
    [Z^T F^T]: ``R11`` (..., d, d), ``R12`` (..., d, n) and ``r22`` (..., n)
    the column norms of its R22 block (the residual of the least squares fit).
    """

    lam: np.ndarray
    U: np.ndarray
    formed: bool = True
    col: np.ndarray | None = None
    fnorm: np.ndarray | None = None
    R11: np.ndarray | None = None
    R12: np.ndarray | None = None
    r22: np.ndarray | None = None

    def expand(self, axis: int) -> GramFactor:
        """The same factor with a new batch axis at ``axis`` (counted from the front
        of the batch dims), e.g. (R, ...) -> (R, 1, ...) to broadcast over cells."""

        def ins(x, core):
            if x is None:
                return None
            return np.expand_dims(x, axis if axis >= 0 else x.ndim - core + axis + 1)

        return GramFactor(
            lam=ins(self.lam, 1),
            U=ins(self.U, 2),
            formed=self.formed,
            col=ins(self.col, 1),
            fnorm=ins(self.fnorm, 1),
            R11=ins(self.R11, 2),
            R12=ins(self.R12, 2),
            r22=ins(self.r22, 1),
        )


def gram_factor(G) -> GramFactor:
    """Eigendecomposition of formed Gram matrices G = Z Z^T (..., d, d) (NaN for a
    non-finite G). Kept for callers that have only G; the pipeline uses
    :func:`data_factor`."""
    G = np.asarray(G, dtype=float)
    ok = np.isfinite(G).all(axis=(-2, -1))
    lam, U = np.linalg.eigh(np.where(ok[..., None, None], G, np.eye(G.shape[-1])))
    lam = np.where(ok[..., None], np.maximum(lam, 0.0), np.nan)
    return GramFactor(lam=lam, U=np.where(ok[..., None, None], U, np.nan))


def data_factor(Z, F) -> GramFactor:
    """The factor of Z Z^T from the data: QR of [Z^T F^T], then the SVD of R11.

    Z (..., d, N0), F (..., n, N0). Non-finite data give NaN factors.
    """
    Z = np.asarray(Z, dtype=float)
    F = np.asarray(F, dtype=float)
    d, n = Z.shape[-2], F.shape[-2]
    k = d + n
    ok = np.isfinite(Z).all(axis=(-2, -1)) & np.isfinite(F).all(axis=(-2, -1))
    X = np.where(ok[..., None, None], np.concatenate([Z, F], axis=-2), 0.0)
    with np.errstate(over="ignore", invalid="ignore"):
        col = np.sqrt(np.sum(Z * Z, axis=-1))
        fnorm = np.sqrt(np.sum(F * F, axis=-1))
        R = np.linalg.qr(np.swapaxes(X, -1, -2), mode="r")
    if R.shape[-2] < k:  # N0 < d + n: the triangle padded with zero rows
        pad = np.zeros(R.shape[:-2] + (k - R.shape[-2], k))
        R = np.concatenate([R, pad], axis=-2)
    fin = ok & np.isfinite(R).all(axis=(-2, -1))
    R = np.where(fin[..., None, None], R, 0.0)
    R11 = R[..., :d, :d]
    _, s, Wt = np.linalg.svd(R11)  # R11 = P diag(s) Wt: Z Z^T = W diag(s^2) W^T
    with np.errstate(over="ignore"):  # squares beyond the double range: inf, noted downstream
        lam = (s * s)[..., ::-1]
        r22 = np.sqrt(np.sum(R[..., d:, d:] ** 2, axis=-2))
    U = np.swapaxes(Wt, -1, -2)[..., ::-1]
    nan = ~fin

    def mask(x, core):
        return np.where(nan.reshape(nan.shape + (1,) * core), np.nan, x)

    return GramFactor(
        lam=mask(lam, 1),
        U=mask(U, 2),
        formed=False,
        col=mask(col, 1),
        fnorm=mask(fnorm, 1),
        R11=mask(R11, 2),
        R12=mask(R[..., :d, d:], 2),
        r22=mask(r22, 1),
    )


def relative_error(fac: GramFactor, lam) -> tuple[np.ndarray, np.ndarray]:
    """(estimated relative error of the radii, cond(V)) for V = Z Z^T + lam I. -> (...)

    A perturbation E of the data moves (V^-1)_jj, and every Rayleigh quotient of
    V^-1, by at most a relative 2 k + k^2 with k = ||E|| / sqrt(lambda_min(V))
    (docs/uncertainty.md#numerical-accuracy-of-the-radii). From the data the
    backward error is ||E|| <= u ||Z||_F, from a formed Gram ||E G|| ~ u tr(G),
    i.e. k = u tr(G) / lambda_min(V). log det, lambda_min (OLS) and beta carry
    at most d + 2 such terms: the estimate is (d + 2)(2 k + k^2) + 64 u.
    """
    g = fac.lam
    d = g.shape[-1]
    lam = np.asarray(lam, dtype=float)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        lv_min = g[..., 0] + lam
        lv_max = g[..., -1] + lam
        trace = np.sum(g, axis=-1)
        if fac.formed:
            k = U_ROUND * trace / lv_min
        else:
            k = U_ROUND * np.sqrt(trace) / np.sqrt(lv_min)
        err = (d + 2) * (2 * k + k * k) + 64 * U_ROUND
        cond = lv_max / lv_min
    return np.where(np.isnan(err), np.inf, err), cond


def estimate_margin(fac: GramFactor, theta, *, lam, shrink=0.0) -> np.ndarray:
    """Per row i a bound m_i on ||theta_i - theta*_i||_V, where theta is the
    computed estimate and theta* the exact estimator on the exactly simulated
    data; then |theta_ij - theta*_ij| <= m_i sqrt((V^-1)_jj). -> (..., n)

    theta (..., n, d): the estimate (shrunk-ols: shrink > 0, the OLS estimate
    is theta (1 + shrink)); lam the ridge parameter (0 for OLS). Three terms
    (docs/uncertainty.md#numerical-accuracy-of-the-radii): the normal-equation
    residual S_i = theta_i V - f_i Z^T in the V^-1 norm (the solve's error,
    from the QR triangle: S_i^T = R11^T (R11 theta_i^T - R12_i) + lam theta_i^T);
    c u a_i with a_i = ||f_i|| + sum_j |theta_ij| ||Z_j|| + ||r_i|| (the
    rounding of the simulation and of the QR, c = 8 (d + n)); and k (||r_i|| +
    c u a_i) for the residual r_i seen through a perturbed V (k as in
    :func:`relative_error`). NaN without the data's factor (:func:`gram_factor`).
    """
    theta = np.asarray(theta, dtype=float)
    n, d = theta.shape[-2:]
    if fac.formed or fac.R11 is None:
        return np.full(np.broadcast_shapes(theta.shape[:-1], fac.lam.shape[:-1] + (n,)), np.nan)
    lam = np.asarray(lam, dtype=float)
    shrink = np.asarray(shrink, dtype=float)
    with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
        th = theta * (1.0 + shrink)[..., None, None]
        lamv = lam[..., None, None]
        fit = fac.R11 @ np.swapaxes(th, -1, -2) - fac.R12  # (..., d, n)
        S = np.swapaxes(fac.R11, -1, -2) @ fit + lamv * np.swapaxes(th, -1, -2)
        inv = 1.0 / (fac.lam + lam[..., None])  # eigenvalues of V^-1
        y = np.swapaxes(fac.U, -1, -2) @ S  # (..., d, n)
        s_norm = np.sqrt(np.sum(y * y * inv[..., :, None], axis=-2))  # (..., n)
        resid = np.sqrt(np.sum(fit * fit, axis=-2) + fac.r22**2)
        a = fac.fnorm + np.sum(np.abs(th) * fac.col[..., None, :], axis=-1) + resid
        c = 8 * (d + n) * U_ROUND
        k = U_ROUND * np.sqrt(np.sum(fac.lam, axis=-1)) / np.sqrt(fac.lam[..., 0] + lam)
        margin = s_norm + c * a + k[..., None] * (resid + c * a)
    return np.where(np.isfinite(margin), margin, np.inf)
