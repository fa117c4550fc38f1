"""The regression data factorised once per dataset, and what its rounding can cost.

The self-normalized box (docs/uncertainty.md) needs ``V = Z Z^T + lam I``
through diag(V^-1), log det and eigenvalues. Forming ``Z Z^T`` squares the
conditioning: its rounding error ~u ||Z||^2 swamps the small eigenvalues once
cond(V) passes ~1e12. :func:`data_factor` works on the data instead: an
R-only Householder QR of ``[Z^T F^T]`` (backward stable: the exact QR of data
off by ~u ||Z_j|| per regressor row) and the SVD of the small triangle
``R11`` (``Z^T = Q R11``), so ``Z Z^T = U diag(s^2) U^T`` with ``s`` accurate to
~u ||Z|| absolutely. Datasets where that is not accurate enough (the error
estimate of :func:`v_parts` above EXTEND_K, and at most EXT_MAX_WORK big)
are factorised again in extended precision (``np.longdouble``, u ~ 5e-20 on
x86-64): the same Householder QR,
then the triangle of ``[R11; sqrt(lam) I]`` and its inverse per cell. See
docs/uncertainty.md#numerical-accuracy-of-the-radii.

:func:`relative_error` estimates the relative forward error of every radius
from that backward error; :func:`estimate_margin` bounds, per row of an
estimate, how far the computed estimate can be from the exact estimator on
the data (and the data from their exact simulation), in the V-norm of the box.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import cast

import numpy as np
from numpy.typing import ArrayLike

from .array_types import Array, FloatArray

__all__ = ["GramFactor", "VParts", "data_factor", "estimate_margin", "gram_factor", "v_parts"]

U_ROUND = np.finfo(float).eps / 2  # unit roundoff of a double
U_EXT = float(np.finfo(np.longdouble).eps) / 2  # of np.longdouble (= U_ROUND where no wider type)
EXTEND_K = 1e-10  # u ||Z||_F / sigma_min(Z) above this: the dataset is factorised again, extended
EXT_CHUNK_BYTES = 32 * 2**20  # extended-precision data held at once (at least one dataset)
# N0 (d + n)^2 above this: no extended pass (~2e-8 s per unit: 2 s a dataset); the
# double factor's estimate decides (null radii with the note where it is too large)
EXT_MAX_WORK = 1e8


@dataclass
class GramFactor:
    """Z Z^T = U diag(lam) U^T per dataset
    (docs/science.md#22-the-papers-l2-loss-svr-and-its-closed-form), with what the
    error estimates need.

    lam (..., d) ascending, >= 0; U (..., d, d). ``formed``: from a formed Gram
    matrix (:func:`gram_factor`; its error grows like u cond(V)) rather than
    from the data (:func:`data_factor`; like u sqrt(cond(V))). From the data
    also: ``col`` (..., d) the norms of the rows of Z (the regressors),
    ``fnorm`` (..., n) of the rows of F, and the triangle of the QR of
    [Z^T F^T]: ``R11`` (..., d, d), ``R12`` (..., d, n) and ``r22`` (..., n)
    the column norms of its R22 block (the residual of the least squares fit).
    ``ext`` (...) bool: the datasets factorised again in extended precision,
    whose triangle is ``R11x``, ``R12x``, ``r22x`` (np.longdouble, zeros elsewhere).
    """

    lam: Array
    U: Array
    formed: bool = True
    col: Array | None = None
    fnorm: Array | None = None
    R11: Array | None = None
    R12: Array | None = None
    r22: Array | None = None
    ext: Array | None = None
    R11x: Array | None = None
    R12x: Array | None = None
    r22x: Array | None = None

    def expand(self, axis: int) -> GramFactor:
        """The same factor with a new batch axis at ``axis`` (counted from the front
        of the batch dims), e.g. (R, ...) -> (R, 1, ...) to broadcast over cells."""

        def ins(x: Array, core: int) -> Array:
            return np.expand_dims(x, axis if axis >= 0 else x.ndim - core + axis + 1)

        def opt(x: Array | None, core: int) -> Array | None:
            return None if x is None else ins(x, core)

        return GramFactor(
            lam=ins(self.lam, 1),
            U=ins(self.U, 2),
            formed=self.formed,
            col=opt(self.col, 1),
            fnorm=opt(self.fnorm, 1),
            R11=opt(self.R11, 2),
            R12=opt(self.R12, 2),
            r22=opt(self.r22, 1),
            ext=opt(self.ext, 0),
            R11x=opt(self.R11x, 2),
            R12x=opt(self.R12x, 2),
            r22x=opt(self.r22x, 1),
        )


def gram_factor(G: ArrayLike) -> GramFactor:
    """Eigendecomposition of formed Gram matrices G = Z Z^T (..., d, d) (NaN for a
    non-finite G). Kept for callers that have only G; the pipeline uses
    :func:`data_factor`."""
    G = np.asarray(G, dtype=float)
    ok = np.isfinite(G).all(axis=(-2, -1))
    lam, U = np.linalg.eigh(np.where(ok[..., None, None], G, np.eye(G.shape[-1])))
    lam = np.where(ok[..., None], np.maximum(lam, 0.0), np.nan)
    return GramFactor(lam=lam, U=np.where(ok[..., None, None], U, np.nan))


def _householder_r(X: Array) -> Array:
    """R of the Householder QR of every X (b, m, k), in X's own precision (the
    extended path; float64 data go through LAPACK). -> (b, k, k), zero rows below
    min(m, k)."""
    X = np.array(X, copy=True)
    b, m, k = X.shape
    for j in range(min(m, k)):
        x = X[:, j:, j]
        nrm = np.sqrt(np.sum(x * x, axis=-1))
        alpha = np.where(x[:, 0] >= 0, -nrm, nrm)
        v = x.copy()
        v[:, 0] -= alpha
        vv = np.sum(v * v, axis=-1)
        scale = np.where(vv > 0, 2 / np.where(vv > 0, vv, 1), 0)
        w = np.einsum("bi,bij->bj", v, X[:, j:, j:])
        X[:, j:, j:] -= (scale[:, None] * v)[:, :, None] * w[:, None, :]
    R = np.zeros((b, k, k), dtype=X.dtype)
    r = min(m, k)
    R[:, :r] = np.triu(X[:, :r, :])
    return R


def _extended(Z: Array, F: Array) -> tuple[Array, Array, Array]:
    """(R11x, R12x, r22x) of [Z^T F^T] in np.longdouble, in chunks of datasets."""
    b, d, N0 = Z.shape
    n = F.shape[-2]
    k = d + n
    R = np.empty((b, k, k), dtype=np.longdouble)
    step = max(1, EXT_CHUNK_BYTES // (4 * 16 * k * max(N0, 1)))
    for s in range(0, b, step):  # chunks bound the memory (rare, ill-conditioned datasets)
        X = np.concatenate([Z[s : s + step], F[s : s + step]], axis=-2).astype(np.longdouble)
        R[s : s + step] = _householder_r(np.swapaxes(X, -1, -2))
    r22 = np.sqrt(np.sum(R[:, d:, d:] ** 2, axis=-2))
    return R[:, :d, :d], R[:, :d, d:], r22


def data_factor(Z: ArrayLike, F: ArrayLike) -> GramFactor:
    """The factor of Z Z^T from the data: QR of [Z^T F^T], then the SVD of R11;
    again in extended precision where the double factor is not accurate enough.

    Z (..., d, N0), F (..., n, N0). Non-finite data give NaN factors.
    """
    Z = np.asarray(Z, dtype=float)
    F = np.asarray(F, dtype=float)
    d, n = Z.shape[-2], F.shape[-2]
    k = d + n
    with np.errstate(over="ignore", invalid="ignore"):
        col = np.sqrt(np.einsum("...ij,...ij->...i", Z, Z))
        fnorm = np.sqrt(np.einsum("...ij,...ij->...i", F, F))
        ok = np.isfinite(col).all(axis=-1) & np.isfinite(fnorm).all(axis=-1)
        X = np.concatenate([Z, F], axis=-2)
        if not ok.all():
            X[~ok] = 0.0
        # numpy's stubs type every mode as QRResult; mode "r" returns the triangle
        R = cast(Array, np.linalg.qr(np.swapaxes(X, -1, -2), mode="r"))
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
    nan = ~fin

    def mask(x: Array, core: int) -> Array:
        return np.where(nan.reshape(nan.shape + (1,) * core), np.nan, x)

    with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
        k64 = U_ROUND * np.sqrt(np.sum(col * col, axis=-1)) / s[..., -1]
    ext = fin & ~(k64 <= EXTEND_K) & (U_EXT < U_ROUND) & (Z.shape[-1] * k * k <= EXT_MAX_WORK)
    R11x = np.zeros(R11.shape, dtype=np.longdouble)
    R12x = np.zeros(R[..., :d, d:].shape, dtype=np.longdouble)
    r22x = np.zeros(r22.shape, dtype=np.longdouble)
    if ext.any():
        R11x[ext], R12x[ext], r22x[ext] = _extended(Z[ext], F[ext])
    return GramFactor(
        lam=mask(lam, 1),
        U=mask(np.swapaxes(Wt, -1, -2)[..., ::-1], 2),
        formed=False,
        col=mask(col, 1),
        fnorm=mask(fnorm, 1),
        R11=mask(R11, 2),
        R12=mask(R[..., :d, d:], 2),
        r22=mask(r22, 1),
        ext=ext,
        R11x=R11x,
        R12x=R12x,
        r22x=r22x,
    )


@dataclass
class VParts:
    """What the box needs of V = Z Z^T + lam I, per cell (batch shape (...)).

    diag (..., d) = diag(V^-1); logdet = log det(I + G / scale) (scale = lam,
    or lambda0 for OLS); lam_min, lam_max: extreme eigenvalues of G = Z Z^T;
    lmax_A, lmax_B: lambda_max of (V^-1)_AA, (V^-1)_BB; err: the estimated
    relative error of the radii; cond = cond(V); ext: computed in extended
    precision; Rinv (cells, d, d) the extended cells' V^-1/2 factor (V^-1 =
    Rinv Rinv^T), in the (C) order of ``ext``.
    """

    diag: Array
    logdet: Array
    lam_min: Array
    lam_max: Array
    lmax_A: Array
    lmax_B: Array
    lv_min: Array
    err: Array
    cond: Array
    ext: Array
    Rinv: Array | None = None


def _tri_inv(R: Array) -> Array:
    """Inverse of upper triangular R (c, d, d), back substitution in R's precision."""
    d = R.shape[-1]
    X = np.zeros_like(R)
    eye = np.eye(d, dtype=R.dtype)
    for i in range(d - 1, -1, -1):
        rhs = eye[i] - np.einsum("cj,cjk->ck", R[:, i, i + 1 :], X[:, i + 1 :, :])
        X[:, i, :] = rhs / R[:, i, i][:, None]
    return X


def _sigma_max(X: Array) -> Array:
    """Largest singular value of each (c, a, b), from the double rounding of X
    (NaN where X is not finite, e.g. the inverse of a singular triangle)."""
    with np.errstate(over="ignore", invalid="ignore"):
        X = np.asarray(X, dtype=float)
    ok = np.asarray(np.isfinite(X).all(axis=(-2, -1)))  # (c,): an array, not a numpy bool
    s = np.linalg.svd(np.where(ok[..., None, None], X, 0.0), compute_uv=False)[..., 0]
    return np.where(ok, s, np.nan)


def _ext_parts(R11x: Array, lam: Array, lambda0: float, n: int) -> tuple[Array, ...]:
    """VParts' fields of the extended cells: R11x (c, d, d) longdouble, lam (c,)."""
    c, d, _ = R11x.shape
    ld = np.longdouble
    eye = np.eye(d, dtype=ld)

    def stacked_r(scale: Array) -> Array:  # R of [R11; sqrt(scale) I]
        aug = np.concatenate([R11x, np.sqrt(scale.astype(ld))[:, None, None] * eye], axis=-2)
        return _householder_r(aug)

    ols = lam == 0
    lam_ld = lam.astype(ld)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        Rv = np.where(ols[:, None, None], R11x, stacked_r(np.where(ols, 1.0, lam)))
        Rinv = _tri_inv(Rv)
        diag = np.sum(Rinv * Rinv, axis=-1)
        R0 = np.where(ols[:, None, None], stacked_r(np.full(c, float(lambda0))), Rv)
        scale = np.where(ols, ld(lambda0), lam_ld)
        logdet = 2 * np.sum(np.log(np.abs(np.diagonal(R0, axis1=-2, axis2=-1))), axis=-1)
        logdet = logdet - d * np.log(scale)
        R11inv = _tri_inv(R11x)
        s_inv = _sigma_max(R11inv)
        lam_min = 1.0 / (s_inv * s_inv)
        lam_max = _sigma_max(R11x) ** 2
        lv_min = 1.0 / _sigma_max(Rinv) ** 2
        lmax_A = _sigma_max(Rinv[:, :n, :]) ** 2
        lmax_B = _sigma_max(Rinv[:, n:, :]) ** 2 if d > n else np.zeros(c)
    return (
        diag.astype(float),
        logdet.astype(float),
        lam_min,
        lam_max,
        lmax_A,
        lmax_B,
        lv_min,
        Rinv,
    )


def v_parts(fac: GramFactor, lam: ArrayLike, *, lambda0: float = 1.0, n: int) -> VParts:
    """diag(V^-1), log det, the eigenvalues the box needs, and their error estimate.

    A perturbation E of the data moves (V^-1)_jj, and every Rayleigh quotient of
    V^-1, by at most a relative 2 k + k^2 with k = ||E|| / sqrt(lambda_min(V))
    (docs/uncertainty.md#numerical-accuracy-of-the-radii). From the data the
    backward error is ||E|| <= u ||Z||_F (u of the factor's precision, plus the
    rounding of its results to double), from a formed Gram ||E G|| ~ u tr(G),
    i.e. k = u tr(G) / lambda_min(V). log det, lambda_min (OLS) and beta carry
    at most d + 2 such terms: err = (d + 2)(2 k + k^2) + 64 u.
    """
    g = fac.lam
    d = g.shape[-1]
    lam = np.asarray(lam, dtype=float)
    batch = np.broadcast_shapes(g.shape[:-1], lam.shape)
    g = np.broadcast_to(g, batch + (d,))
    U = np.broadcast_to(fac.U, batch + (d, d))
    lam = np.broadcast_to(lam, batch)
    ols = lam == 0
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        lv = g + lam[..., None]  # eigenvalues of V
        scale = np.where(ols, lambda0, lam)[..., None]
        logdet = np.sum(np.log1p(g / scale), axis=-1)
        inv = 1.0 / lv  # eigenvalues of V^-1
        diag = np.einsum("...jk,...jk,...k->...j", U, U, inv)
        UA, UB = U[..., :n, :], U[..., n:, :]
        WA = np.matmul(UA * inv[..., None, :], np.swapaxes(UA, -1, -2))  # (V^-1)_AA
        WB = np.matmul(UB * inv[..., None, :], np.swapaxes(UB, -1, -2))
        fin = np.isfinite(WA).all(axis=(-2, -1)) & np.isfinite(WB).all(axis=(-2, -1))
        lmax_A = np.linalg.eigvalsh(np.where(fin[..., None, None], WA, 0.0))[..., -1]
        lmax_B = (
            np.linalg.eigvalsh(np.where(fin[..., None, None], WB, 0.0))[..., -1]
            if d > n
            else np.zeros(batch)
        )
        lam_min, lam_max = g[..., 0], g[..., -1]
        lv_min = lv[..., 0]
        u = np.full(batch, U_ROUND)
        ext = np.zeros(batch, dtype=bool)
        Rinv = None
        if fac.ext is not None and fac.ext.any():
            ext = np.broadcast_to(fac.ext, batch).copy()
            idx = ext
            assert fac.R11x is not None  # set with ext (data_factor)
            R11x = np.broadcast_to(fac.R11x, batch + (d, d))[idx]
            parts = _ext_parts(R11x, lam[idx], lambda0, n)
            diag, logdet, lam_min, lam_max = (np.array(x) for x in (diag, logdet, lam_min, lam_max))
            lmax_A, lmax_B, lv_min = (np.array(x) for x in (lmax_A, lmax_B, lv_min))
            for full, part in zip(
                (diag, logdet, lam_min, lam_max, lmax_A, lmax_B, lv_min), parts[:7]
            ):
                full[idx] = part
            Rinv = parts[7]
            u[idx] = U_EXT
        trace = np.sum(g, axis=-1)
        if fac.formed:
            k = U_ROUND * trace / lv_min
        else:
            k = u * np.sqrt(trace) / np.sqrt(lv_min) + np.where(ext, 4 * d * U_ROUND, 0.0)
        err = (d + 2) * (2 * k + k * k) + 64 * U_ROUND
        cond = (lam_max + lam) / lv_min
    return VParts(
        diag=diag,
        logdet=logdet,
        lam_min=lam_min,
        lam_max=lam_max,
        lmax_A=np.where(fin | ext, lmax_A, np.nan),
        lmax_B=np.where(fin | ext, lmax_B, np.nan),
        lv_min=lv_min,
        err=np.where(np.isnan(err), np.inf, err),
        cond=cond,
        ext=ext,
        Rinv=Rinv,
    )


def estimate_margin(
    fac: GramFactor,
    theta: ArrayLike,
    *,
    lam: ArrayLike,
    shrink: ArrayLike = 0.0,
    parts: VParts | None = None,
) -> FloatArray:
    """Per row i a bound m_i on ||theta_i - theta*_i||_V, where theta is the
    computed estimate and theta* the exact estimator on the exactly simulated
    data; then |theta_ij - theta*_ij| <= m_i sqrt((V^-1)_jj). -> (..., n)

    theta (..., n, d): the estimate (shrunk-ols: shrink > 0, the OLS estimate
    is theta (1 + shrink)); lam the ridge parameter (0 for OLS); ``parts`` the
    cells' :func:`v_parts` (computed here if not given). Three terms
    (docs/uncertainty.md#numerical-accuracy-of-the-radii): the normal-equation
    residual S_i = theta_i V - f_i Z^T in the V^-1 norm (the solve's error,
    from the QR triangle: S_i^T = R11^T (R11 theta_i^T - R12_i) + lam theta_i^T);
    c u a_i with a_i = ||f_i|| + sum_j |theta_ij| ||Z_j|| + ||r_i|| (the
    rounding of the simulation and of the QR, c = 8 (d + n)); and k (||r_i|| +
    c u a_i) for the residual r_i seen through the factor's perturbed V (k as
    in :func:`v_parts`). The extended cells compute S in extended precision.
    NaN without the data's factor (:func:`gram_factor`).
    """
    theta = np.asarray(theta, dtype=float)
    n, d = theta.shape[-2:]
    if (
        fac.formed
        or fac.R11 is None
        or fac.R12 is None
        or fac.r22 is None
        or fac.col is None
        or fac.fnorm is None
    ):  # a formed Gram matrix has no triangle of the data
        return np.full(np.broadcast_shapes(theta.shape[:-1], fac.lam.shape[:-1] + (n,)), np.nan)
    lam = np.asarray(lam, dtype=float)
    shrink = np.asarray(shrink, dtype=float)
    if parts is None:
        parts = v_parts(fac, lam, n=n)
    with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
        th = theta * (1.0 + shrink)[..., None, None]
        batch = np.broadcast_shapes(th.shape[:-2], fac.lam.shape[:-1], lam.shape)
        th = np.broadcast_to(th, batch + (n, d))
        lamb = np.broadcast_to(lam, batch)
        fit = fac.R11 @ np.swapaxes(th, -1, -2) - fac.R12  # (..., d, n)
        S = np.swapaxes(fac.R11, -1, -2) @ fit + lamb[..., None, None] * np.swapaxes(th, -1, -2)
        inv = 1.0 / (fac.lam + lamb[..., None])  # eigenvalues of V^-1
        y = np.swapaxes(fac.U, -1, -2) @ S  # (..., d, n)
        # ||S_i||_{V^-1}: scaled by sqrt(inv) before squaring (S ~ ||Z||^2 |theta| would
        # overflow when squared for data of size 1e77, well inside the double range)
        y = y * np.sqrt(inv)[..., :, None]
        s_norm = np.sqrt(np.sum(y * y, axis=-2))  # (..., n)
        resid = np.sqrt(np.sum(fit * fit, axis=-2) + fac.r22**2)
        if parts.Rinv is not None:
            idx = parts.ext
            ld = np.longdouble
            # set with ext (data_factor)
            assert fac.R11x is not None and fac.R12x is not None and fac.r22x is not None
            R11x = np.broadcast_to(fac.R11x, batch + (d, d))[idx]
            R12x = np.broadcast_to(fac.R12x, batch + (d, n))[idx]
            tht = np.swapaxes(th[idx], -1, -2).astype(ld)
            fit_x = R11x @ tht - R12x
            S_x = np.swapaxes(R11x, -1, -2) @ fit_x + lamb[idx].astype(ld)[:, None, None] * tht
            z = np.swapaxes(parts.Rinv, -1, -2) @ S_x  # ||S_i||_{V^-1} = ||Rinv^T S_i^T||
            s_norm, resid = np.array(s_norm), np.array(resid)
            s_norm[idx] = np.sqrt(np.sum(z * z, axis=-2)).astype(float)
            r22x = np.broadcast_to(fac.r22x, batch + (n,))[idx]
            resid[idx] = np.sqrt(np.sum(fit_x * fit_x, axis=-2) + r22x**2).astype(float)
        a = fac.fnorm + np.sum(np.abs(th) * fac.col[..., None, :], axis=-1) + resid
        c = 8 * (d + n) * U_ROUND
        u = np.where(parts.ext, U_EXT, U_ROUND)
        k = u * np.sqrt(np.sum(fac.col**2, axis=-1)) / np.sqrt(np.broadcast_to(parts.lv_min, batch))
        margin = s_norm + c * a + k[..., None] * (resid + c * a)
    return np.where(np.isfinite(margin), margin, np.inf)
