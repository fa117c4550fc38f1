"""Estimators (docs/science.md#2-estimators): OLS, L2-loss SVR (closed form), shrunk OLS.

Shapes: Z is (..., d, N0) with d = n + m (columns are [x_k; u_k]), F is
(..., n, N0). Estimates Theta = [A_hat B_hat] are (..., n, d). Batch dims
(...) of Z and F broadcast. Every batch element is computed with the same
per-matrix arithmetic (stacked LAPACK / BLAS calls), so a result does not
depend on the batch it was computed in, bit for bit.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Literal, cast, overload

import numpy as np
from numpy.typing import ArrayLike

from .array_types import Array, FloatArray, IntArray
from .errors import DimensionError, check_matrix
from .linalg import solve as _solve

LOSS_SCALES = ("sum", "mean")


def _check(Z: ArrayLike, F: ArrayLike) -> tuple[FloatArray, FloatArray]:
    Z = check_matrix("Z", Z, ("d", "N0"))
    F = check_matrix("F", F, ("n", Z.shape[-1]))
    if Z.shape[-1] < 1:
        raise DimensionError("Z", f"needs a sample count N0 >= 1, got shape {Z.shape}")
    return Z, F


def _gammas(gammas: ArrayLike, *, allow_zero: bool) -> FloatArray:
    g = np.asarray(gammas, dtype=float)
    if g.ndim > 1:
        raise DimensionError("gammas", f"must be a scalar or a 1-D array, got shape {g.shape}")
    g = np.atleast_1d(g)
    low_ok = g >= 0 if allow_zero else g > 0
    if g.size == 0 or not np.all(np.isfinite(g)) or not np.all(low_ok):
        raise ValueError(f"gammas must be finite and {'>=' if allow_zero else '>'} 0, got {g}")
    return g


def ridge_parameters(gammas: ArrayLike, N0: int, loss_scale: str = "sum") -> FloatArray:
    """Ridge parameter g of Theta = F Z^T (Z Z^T + g I)^-1 (docs/science.md#2-estimators).

    "sum": g = gamma (the paper as written); "mean": the loss term divided by
    N0, i.e. g = gamma * N0. gamma > 0 (the 1/(2 gamma) of eq:SVR). -> (G,)
    """
    g = _gammas(gammas, allow_zero=False)
    if loss_scale == "sum":
        return g
    if loss_scale == "mean":
        with np.errstate(over="ignore"):  # beyond the double range: inf, a NaN estimate
            return g * float(N0)
    raise ValueError(f"loss_scale must be one of {LOSS_SCALES}, got {loss_scale!r}")


REFINE_STEPS = 1
# ridge_qr's refinement steps, relative to the estimate: a first step at or above
# REFINE_STEP_NULL means the iteration does not contract (the estimate is rounding:
# NaN); a second step, which measures the error the first left, above
# REFINE_STEP_TRUST means the estimate is not trusted to 1e-9 (reported as an
# infinite condition number, so its certificates are withheld). The second step
# measures, it is not applied: the residual's own rounding is the floor that more
# steps cannot pass (docs/science.md#22-the-papers-l2-loss-svr-and-its-closed-form).
REFINE_STEP_NULL = 0.5
REFINE_STEP_TRUST = 3.8e-11  # the error was at most 26x this step: within 1e-9
REFINE_COND_LIMIT = 1e8  # above this cond(Z Z^T) one refinement step is not enough: use QR


@overload
def fit_ols(Z: ArrayLike, F: ArrayLike, *, return_cond: Literal[False] = ...) -> FloatArray: ...
@overload
def fit_ols(
    Z: ArrayLike, F: ArrayLike, *, return_cond: Literal[True]
) -> tuple[FloatArray, FloatArray]: ...
def fit_ols(
    Z: ArrayLike, F: ArrayLike, *, return_cond: bool = False
) -> FloatArray | tuple[FloatArray, FloatArray]:
    """OLS Theta = F Z^T (Z Z^T)^-1 (docs/science.md#21-ols), batched. -> (..., n, d)

    Normal equations by Cholesky of Z Z^T plus ``REFINE_STEPS`` steps of
    iterative refinement on the residual (F - Theta Z) Z^T, which restores
    lstsq accuracy while cond(Z Z^T) * eps << 1. Datasets whose Gram matrix
    is singular or worse conditioned than ``REFINE_COND_LIMIT`` (e.g.
    N0 < d) take the least-squares path of :func:`_fit_ols_qr` instead.
    Datasets with non-finite values give NaN. With ``return_cond`` also
    cond(Z Z^T) per dataset (...), from the QR factor for the QR datasets
    (inf when Z is numerically rank deficient, NaN when not finite).
    """
    Z, F = _check(Z, F)
    batch = np.broadcast_shapes(Z.shape[:-2], F.shape[:-2])
    Z = np.broadcast_to(Z, (*batch, *Z.shape[-2:]))
    F = np.broadcast_to(F, (*batch, *F.shape[-2:]))
    Zt = np.swapaxes(Z, -1, -2)
    with np.errstate(over="ignore", invalid="ignore"):  # non-finite data: NaN, below
        G = np.matmul(Z, Zt)
    eye = np.eye(G.shape[-1])
    finite = np.isfinite(G).all(axis=(-1, -2)) & np.isfinite(F).all(axis=(-1, -2))
    lam = np.linalg.eigvalsh(np.where(finite[..., None, None], G, eye))
    ok = finite & (lam[..., 0] > lam[..., -1] / REFINE_COND_LIMIT)
    Gs = np.where(ok[..., None, None], G, eye)
    Lc = np.linalg.cholesky(Gs)

    def solve(rhs: FloatArray) -> FloatArray:  # (Z Z^T)^-1 rhs^T, transposed back: rows of Theta
        y = np.linalg.solve(Lc, np.swapaxes(rhs, -1, -2))
        x: FloatArray = np.swapaxes(np.linalg.solve(np.swapaxes(Lc, -1, -2), y), -1, -2)
        return x

    with np.errstate(all="ignore"):  # the other cells are overwritten below
        theta = solve(np.matmul(F, Zt))
        for _ in range(REFINE_STEPS):
            theta = theta + solve(np.matmul(F - np.matmul(theta, Z), Zt))
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):  # inf: ill-conditioned
        cond = np.where(finite, lam[..., -1] / lam[..., 0], np.nan)
    if not ok.all():
        bad = finite & ~ok
        theta[bad], cond[bad] = _fit_ols_qr(Z[bad], F[bad])
        theta[~finite] = np.nan
    return (theta, cond) if return_cond else theta


def _normal_residual(Z: Array, F: Array, theta: Array, g: ArrayLike) -> FloatArray:
    """(F - Theta Z) Z^T - g Theta accumulated in extended precision (np.longdouble).

    The residual of the (ridge) normal equations for one refinement step:
    computed in working precision it would carry an error ~eps ||Z||^2
    ||Theta||, which is what limits the solve to cond(Z Z^T) * eps.
    Z (b, 1, d, N0), F (b, 1, n, N0), theta (b, G, n, d), g (G,) -> (b, G, n, d)."""
    Zl = Z.astype(np.longdouble)
    Tl = theta.astype(np.longdouble)
    r = F.astype(np.longdouble) - np.matmul(Tl, Zl)
    S = np.matmul(r, np.swapaxes(Zl, -1, -2)) - np.asarray(g, dtype=float)[:, None, None] * Tl
    out: FloatArray = S.astype(float)
    return out


def _fit_ols_qr(Z: FloatArray, F: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Least squares as numpy.linalg.lstsq does, batched, for ill-conditioned Z.

    R-only QR of the augmented [Z^T F^T] = Q [[R11, R12], [0, R22]] reduces it
    to min ||R11 X - R12||, solved with the SVD of the small R11. Rank-deficient
    Z gives lstsq's minimum-norm solution with rcond = eps * max(d, N0). Then
    one refinement step with the extended-precision normal residual of
    :func:`_normal_residual` through the same pseudo-inverse (Z Z^T)^+ =
    V diag(1/s^2) V^T. -> (Theta, cond(Z Z^T) = (s_max / s_min)^2, inf if rank deficient)
    """
    d, N0 = Z.shape[-2:]
    R = cast(
        FloatArray, np.linalg.qr(np.swapaxes(np.concatenate([Z, F], axis=-2), -1, -2), mode="r")
    )
    U, s, Vh = np.linalg.svd(R[..., :d, :d], full_matrices=False)  # R11 = U diag(s) Vh
    cutoff = np.finfo(float).eps * max(d, N0) * s[..., :1]
    s_inv = np.divide(1.0, s, out=np.zeros_like(s), where=s > cutoff)
    UtR12 = np.matmul(np.swapaxes(U, -1, -2), R[..., :d, d:])  # (..., r, n)
    V = np.swapaxes(Vh, -1, -2)
    theta = np.swapaxes(np.matmul(V, s_inv[..., :, None] * UtR12), -1, -2)
    S = _normal_residual(Z[:, None], F[:, None], theta[:, None], [0.0])[:, 0]  # (b, n, d)
    dT = np.matmul(np.matmul(S, V) * (s_inv**2)[..., None, :], Vh)
    full = s.shape[-1] == d  # N0 >= d: R11 is square
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):  # inf: ill-conditioned
        cond = np.where(full & (s[..., -1] > cutoff[..., 0]), (s[..., 0] / s[..., -1]) ** 2, np.inf)
    return theta + dT, cond


def fit_svr(
    Z: ArrayLike, F: ArrayLike, gammas: ArrayLike, *, loss_scale: str = "sum"
) -> FloatArray:
    """SVR closed form Theta = F Z^T (Z Z^T + g I)^-1 for every gamma at once.

    ``g = gamma`` for loss_scale "sum", ``g = gamma * N0`` for "mean"
    (docs/science.md#22-the-papers-l2-loss-svr-and-its-closed-form). Solved as :func:`svr_from_gram` does, with
    the data at hand for the ill-conditioned cells. ``gammas`` scalar or 1-D
    (G,), all > 0. -> (..., G, n, d)
    """
    Z, F = _check(Z, F)
    batch = np.broadcast_shapes(Z.shape[:-2], F.shape[:-2])
    Z = np.broadcast_to(Z, (*batch, *Z.shape[-2:]))
    F = np.broadcast_to(F, (*batch, *F.shape[-2:]))
    Zt = np.swapaxes(Z, -1, -2)
    Zf = Z.reshape(-1, *Z.shape[-2:])
    Ff = F.reshape(-1, *F.shape[-2:])
    return svr_from_gram(
        np.matmul(Z, Zt),
        np.matmul(F, Zt),
        Z.shape[-1],
        gammas,
        loss_scale=loss_scale,
        data=lambda rows: (Zf[rows], Ff[rows]),
    )


SVR_COND_LIMIT = 1e6  # above this cond(Z Z^T + g I) the eigh solution loses > ~1e-10: QR path
FALLBACK_CHUNK_BYTES = 4 * 2**20  # data of the QR path held at once (at least one dataset)


def ridge_condition(G: ArrayLike, g: ArrayLike) -> FloatArray:
    """cond(Z Z^T + g I) = (lam_max + g) / (lam_min + g) from ``G = Z Z^T``. -> (..., len(g))

    Eigenvalues of the PSD G are floored at 0 (rounding only); inf where
    singular (g = 0), NaN for non-finite G.
    """
    G = np.asarray(G, dtype=float)
    g = np.atleast_1d(np.asarray(g, dtype=float))
    ok = np.isfinite(G).all(axis=(-1, -2))
    lam = np.linalg.eigvalsh(np.where(ok[..., None, None], G, 0.0))
    lam = np.maximum(lam, 0.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        kappa = (lam[..., -1:] + g) / (lam[..., :1] + g)
    return np.where(ok[..., None], kappa, np.nan)


@overload
def svr_from_gram(
    G: ArrayLike,
    FZt: ArrayLike,
    N0: int,
    gammas: ArrayLike,
    *,
    loss_scale: str = ...,
    data: Callable[[IntArray], tuple[FloatArray, FloatArray]] | None = ...,
    return_cond: Literal[False] = ...,
) -> FloatArray: ...
@overload
def svr_from_gram(
    G: ArrayLike,
    FZt: ArrayLike,
    N0: int,
    gammas: ArrayLike,
    *,
    loss_scale: str = ...,
    data: Callable[[IntArray], tuple[FloatArray, FloatArray]] | None = ...,
    return_cond: Literal[True],
) -> tuple[FloatArray, FloatArray]: ...
def svr_from_gram(
    G: ArrayLike,
    FZt: ArrayLike,
    N0: int,
    gammas: ArrayLike,
    *,
    loss_scale: str = "sum",
    data: Callable[[IntArray], tuple[FloatArray, FloatArray]] | None = None,
    return_cond: bool = False,
) -> FloatArray | tuple[FloatArray, FloatArray]:
    """:func:`fit_svr` from the sufficient statistics ``G = Z Z^T`` (..., d, d)
    and ``FZt = F Z^T`` (..., n, d) of datasets with ``N0`` samples each.

    Well-conditioned cells (cond(G + g I) <= ``SVR_COND_LIMIT``): ``G = V
    diag(lam) V^T`` once per dataset (eigh), reused for every gamma,
    ``Theta_g = (F Z^T V) diag(1/(lam + g)) V^T``. The other cells need the
    data: ``data(rows) -> (Z, F)`` of those rows of the flattened batch
    (``(b, d, N0)``, ``(b, n, N0)``), and get the backward-stable solve of
    :func:`ridge_qr`. Without ``data`` they keep the eigh solution (whose
    error grows like cond(G + g I) * eps). -> (..., G, n, d); with
    ``return_cond`` also cond(Z Z^T + g I) (..., G), from the QR factor for
    the QR cells (the eigenvalues of G cannot resolve it above ~1/eps).
    """
    G = np.asarray(G, dtype=float)
    FZt = np.asarray(FZt, dtype=float)
    g = ridge_parameters(gammas, N0, loss_scale)
    ok = np.isfinite(G).all(axis=(-1, -2)) & np.isfinite(FZt).all(axis=(-1, -2))
    g_ok = np.isfinite(g)  # gamma * N0 ("mean") beyond the double range: NaN cells
    lam, V = np.linalg.eigh(np.where(ok[..., None, None], G, 0.0))  # (..., d), (..., d, d)
    lam = np.maximum(lam, 0.0)
    with np.errstate(over="ignore", invalid="ignore"):  # huge data: inf/NaN, noted downstream
        P = np.matmul(FZt, V)  # (..., n, d)
        denom = lam[..., None, None, :] + g[:, None, None]  # (..., G, 1, d)
        theta = np.matmul(P[..., None, :, :] / denom, np.swapaxes(V, -1, -2)[..., None, :, :])
    cells = ok[..., None] & g_ok  # (..., G)
    theta = np.where(cells[..., None, None], theta, np.nan)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        kappa = (lam[..., -1:] + g) / (lam[..., :1] + g)  # (..., G)
    kappa = np.where(cells, kappa, np.nan)
    bad = cells & ~(kappa <= SVR_COND_LIMIT)
    if data is None or not bad.any():
        return (theta, kappa) if return_cond else theta
    d, n = G.shape[-1], FZt.shape[-2]
    flat = theta.reshape(-1, *theta.shape[-3:])
    kflat = kappa.reshape(-1, g.size).copy()
    bad = bad.reshape(-1, g.size)
    rows = np.flatnonzero(bad.any(axis=1))
    step = max(1, FALLBACK_CHUNK_BYTES // (8 * (d + n) * max(1, int(N0))))
    for s in range(0, rows.size, step):  # chunks of datasets bound the memory, not a hot loop
        r = rows[s : s + step]
        Z, F = data(r)
        th, kq = ridge_qr(Z, F, g, return_cond=True)
        flat[r] = np.where(bad[r][..., None, None], th, flat[r])
        kflat[r] = np.where(bad[r], kq, kflat[r])
    theta = flat.reshape(theta.shape)
    return (theta, kflat.reshape(kappa.shape)) if return_cond else theta


@overload
def ridge_qr(
    Z: ArrayLike, F: ArrayLike, g: ArrayLike, *, return_cond: Literal[False] = ...
) -> FloatArray: ...
@overload
def ridge_qr(
    Z: ArrayLike, F: ArrayLike, g: ArrayLike, *, return_cond: Literal[True]
) -> tuple[FloatArray, FloatArray]: ...
def ridge_qr(
    Z: ArrayLike, F: ArrayLike, g: ArrayLike, *, return_cond: bool = False
) -> FloatArray | tuple[FloatArray, FloatArray]:
    """Ridge Theta = F Z^T (Z Z^T + g I)^-1 by a backward-stable solve, batched.

    docs/science.md#22-the-papers-l2-loss-svr-and-its-closed-form. The ridge problem is the
    least-squares problem
    ``[Z^T; sqrt(g) I] Theta^T ~ [F^T; 0]``: an R-only QR of ``[Z^T F^T]``
    reduces the data to ``[[R11, R12], [0, R22]]`` (d + n columns), then per
    g a QR of the small ``[R11; sqrt(g) I]`` gives R_g (R_g^T R_g = Z Z^T +
    g I) and Theta. One step of iterative refinement with the normal-equation
    residual ``(F - Theta Z) Z^T - g Theta`` accumulated in extended precision
    (``np.longdouble``) and corrected through R_g brings the error to
    ~cond(R_g) * eps. Z (b, d, N0), F (b, n, N0), g (G,) > 0 -> (b, G, n, d);
    with ``return_cond`` also cond(Z Z^T + g I) = cond(R_g)^2, (b, G).
    """
    Z = np.asarray(Z, dtype=float)
    F = np.asarray(F, dtype=float)
    g = np.atleast_1d(np.asarray(g, dtype=float))
    b, d, N0 = Z.shape
    n = F.shape[-2]
    k = d + n
    R = cast(
        FloatArray, np.linalg.qr(np.swapaxes(np.concatenate([Z, F], axis=-2), -1, -2), mode="r")
    )
    if R.shape[-2] < k:  # N0 < d + n: pad the triangle with zero rows
        R = np.concatenate([R, np.zeros((b, k - R.shape[-2], k))], axis=-2)
    R11, R12 = R[:, None, :d, :d], R[:, None, :d, d:]
    eye = np.sqrt(g)[:, None, None] * np.eye(d)  # (G, d, d)
    aug = np.concatenate(
        [np.broadcast_to(R11, (b, g.size, d, d)), np.broadcast_to(eye, (b, *eye.shape))], axis=-2
    )
    Q, Rg = np.linalg.qr(aug)  # (b, G, 2d, d), (b, G, d, d)
    rhs = np.matmul(np.swapaxes(Q[..., :d, :], -1, -2), R12)  # Q^T [R12; 0]
    Xt = _solve(Rg, rhs)  # Theta^T: (b, G, d, n); NaN where R_g is numerically singular
    # refinement: R_g^T R_g dX = S^T with the extended-precision residual S
    S = _normal_residual(Z[:, None], F[:, None], np.swapaxes(Xt, -1, -2), g)
    dX = _solve(Rg, _solve(np.swapaxes(Rg, -1, -2), np.swapaxes(S, -1, -2)))
    theta = np.swapaxes(Xt + dX, -1, -2)
    # the refinement's step measures the first solve's error: a step as large as the
    # estimate itself (its iteration not contracting) leaves rounding, whatever its
    # size, and the cell is NaN (docs/science.md#22-the-papers-l2-loss-svr-and-its-closed-form)
    theta = np.where(~(_step_ratio(dX, Xt + dX) < REFINE_STEP_NULL)[..., None, None], np.nan, theta)
    if not return_cond:
        return theta
    finite = np.isfinite(Rg).all(axis=(-2, -1))
    s = np.linalg.svd(np.where(finite[..., None, None], Rg, 0.0), compute_uv=False)
    with np.errstate(divide="ignore", over="ignore", invalid="ignore"):  # beyond the range: inf
        cond = np.where(finite, (s[..., 0] / s[..., -1]) ** 2, np.nan)
    # a second step measures the error the first left (it is not applied): above
    # REFINE_STEP_TRUST the estimate is not trusted to 1e-9, whatever cond says
    with np.errstate(invalid="ignore", over="ignore"):  # a NaN estimate: NaN steps, withheld
        S2 = _normal_residual(Z[:, None], F[:, None], theta, g)
        dX2 = _solve(Rg, _solve(np.swapaxes(Rg, -1, -2), np.swapaxes(S2, -1, -2)))
    settled = _step_ratio(dX2, np.swapaxes(theta, -1, -2)) <= REFINE_STEP_TRUST
    return theta, np.where(settled, cond, np.inf)


def _step_ratio(step: FloatArray, estimate: FloatArray) -> FloatArray:
    """max |step| / max |estimate| per cell (largest entries: no overflow); 0 for no
    step, NaN for a NaN one."""
    size = np.abs(estimate).max(axis=(-2, -1), initial=0.0)
    moved = np.abs(step).max(axis=(-2, -1), initial=0.0)
    with np.errstate(invalid="ignore", divide="ignore"):
        return cast(FloatArray, np.where(moved == 0, 0.0, moved / size))


def shrunk_ols(theta_ols: ArrayLike, gammas: ArrayLike) -> FloatArray:
    """Theta_OLS / (1 + gamma) for each gamma (docs/science.md#23-shrunk-ols, Lemma 1's model).

    (..., n, d) -> (..., G, n, d)
    """
    theta = np.asarray(theta_ols, dtype=float)
    g = _gammas(gammas, allow_zero=True)
    return theta[..., None, :, :] / (1.0 + g)[:, None, None]


class SVRIdentifier:
    """scikit-learn-style wrapper of :func:`fit_svr` for one gamma (docs/science.md#2-estimators).

    ``SVRIdentifier(gamma, loss_scale).fit(Z, F).coef_`` is Theta (..., n, d).
    """

    def __init__(self, gamma: float = 0.05, loss_scale: str = "sum") -> None:
        self.gamma = gamma
        self.loss_scale = loss_scale

    def fit(self, Z: ArrayLike, F: ArrayLike) -> SVRIdentifier:
        self.coef_ = fit_svr(Z, F, [self.gamma], loss_scale=self.loss_scale)[..., 0, :, :]
        return self

    def predict(self, Z: ArrayLike) -> FloatArray:
        """Theta Z: (..., d, N) -> (..., n, N)."""
        out: FloatArray = np.matmul(self.coef_, np.asarray(Z, dtype=float))
        return out


class OLSIdentifier:
    """scikit-learn-style wrapper of :func:`fit_ols` (docs/science.md#21-ols)."""

    def fit(self, Z: ArrayLike, F: ArrayLike) -> OLSIdentifier:
        self.coef_ = fit_ols(Z, F)
        return self

    def predict(self, Z: ArrayLike) -> FloatArray:
        """Theta Z: (..., d, N) -> (..., n, N)."""
        out: FloatArray = np.matmul(self.coef_, np.asarray(Z, dtype=float))
        return out
