"""How far the computed spectral radius can be from the exact one
(docs/science.md#62-stationary-j_stationary).

LAPACK's eigenvalues are the exact eigenvalues of a nearby matrix ``F + E``,
``||E||_F <= c n^2 u ||F||_F``, but an eigenvalue moves with ``E`` by up to its
condition number times ``||E||``: for a strongly non-normal ``F`` (entries of
1e4 with every |eigenvalue| near 1) the computed radius can be 1e-4 below an
exact radius above 1. Stability is decided on an upper bound of the exact radius:

* **Henrici's theorem** (Golub & Van Loan, Thm 7.2.3), from the eigenvalues
  alone: every eigenvalue of ``F`` lies within ``max(theta, theta^(1/n))`` of a
  computed one, ``theta = ||E|| sum_{k<n} d^k``, ``d`` the departure from
  normality ``sqrt(||F + E||_F^2 - sum |mu|^2)``. Cheap, and enough wherever
  the radius is not within about ``u^(1/n)`` of 1 or ``F`` is near normal.
* **A Bauer-Fike enclosure** from the computed eigenvectors, for the cells the
  first leaves undecided: with ``F V = V diag(mu) + R``, the eigenvalues of
  ``F`` are those of ``diag(mu) + V^-1 R``, each within ``||V^-1 R||_inf`` of a
  ``mu``; the residual, the inverse and their rounding are bounded explicitly.

The smaller of the two is the bound. A radius whose bound is not below
``1 - UNIT_CIRCLE_TOL`` counts as the boundary wherever stability is decided.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

from .array_types import FloatArray

_U = np.finfo(float).eps / 2  # unit roundoff
# ||E||_F <= _BACKWARD n^2 u ||F||_F for LAPACK's Hessenberg QR eigenvalues (with balancing)
_BACKWARD = 8.0


def _gamma(k: int) -> float:
    """The rounding factor of a k-term dot product, doubled for complex arithmetic."""
    return 2.0 * k * _U / (1.0 - k * _U)


def radius_upper_bound(
    F: ArrayLike, *, decide: float | None = None
) -> tuple[FloatArray, FloatArray]:
    """(rho, rho_hi): the computed spectral radius of each matrix of ``F`` (...,
    n, n) and an upper bound on its exact one; both NaN for a non-finite ``F``,
    ``rho_hi`` inf where no bound is found (an overflow). ``decide``: the
    eigenvector enclosure only where Henrici's bound is not below it but the
    computed radius is (default: wherever it could tighten the bound)."""
    F = np.asarray(F, dtype=float)
    n = F.shape[-1]
    if n == 0:
        z = np.zeros(F.shape[:-2])
        return z, z.copy()
    finite = np.isfinite(F).all(axis=(-2, -1))
    Fs = np.where(finite[..., None, None], F, 0.0)
    with np.errstate(over="ignore", invalid="ignore"):
        mu = np.linalg.eigvals(Fs)
        rho = np.abs(mu).max(axis=-1)
        hi = _henrici(Fs, mu, rho)
        if n > 1:
            todo = (hi > rho) if decide is None else (hi >= decide) & (rho < decide)
            open_ = np.flatnonzero(todo & finite.reshape(hi.shape))
            if open_.size:
                flat = hi.reshape(-1)
                flat[open_] = np.fmin(flat[open_], _bauer_fike(Fs.reshape(-1, n, n)[open_]))
                hi = flat.reshape(hi.shape)
    nan = np.where(finite, 0.0, np.nan)
    return rho + nan, np.where(np.isnan(hi), np.inf, hi) + nan


def _henrici(F: FloatArray, mu: np.ndarray, rho: FloatArray) -> FloatArray:
    n = F.shape[-1]
    # scaled by a power of 2 (exact), so that no square underflows or overflows
    top = np.max(np.abs(F), axis=(-2, -1))
    scale = np.exp2(np.frexp(np.where(top > 0, top, 1.0))[1].astype(float))
    F = F / scale[..., None, None]
    mu = mu / scale[..., None]
    fro = np.sqrt(np.sum(F * F, axis=(-2, -1))) * (1 + 2 * n * _U)
    e = _BACKWARD * n * n * _U * fro
    s = np.sum(np.abs(mu) ** 2, axis=-1) * (1 - 4 * n * _U)
    d = np.sqrt(np.maximum((fro + e) ** 2 - s, 0.0) + 4 * n * _U * (fro + e) ** 2)
    theta = e * sum(d**k for k in range(n)) * (1 + 4 * n * _U)
    move = np.fmax(theta, theta ** (1.0 / n)) if n > 1 else theta
    hi: FloatArray = rho * (1 + 2 * _U) + move * scale * (1 + 2 * _U)
    return hi


def _bauer_fike(F: FloatArray) -> FloatArray:
    n = F.shape[-1]
    mu, V = np.linalg.eig(F)
    aV, aF, amu = np.abs(V), np.abs(F), np.abs(mu)
    # the residual F V - V diag(mu) and its own rounding
    R = F @ V - V * mu[..., None, :]
    Rb = np.abs(R) + _gamma(n + 2) * (aF @ aV + aV * amu[..., None, :])
    try:
        W = np.linalg.inv(V)
    except np.linalg.LinAlgError:  # one singular V (a defective F): the others alone
        W = np.full(V.shape, np.nan + 0j)
        for i in range(V.shape[0]):  # the rare matrices left open by Henrici's bound
            try:
                W[i] = np.linalg.inv(V[i])
            except np.linalg.LinAlgError:
                pass
    aW = np.abs(W)
    # ||V^-1 - W|| <= ||W|| z / (1 - z), z >= ||I - W V|| (with the product's rounding)
    Z = np.eye(n) - W @ V
    z = np.max(np.sum(np.abs(Z) + _gamma(n + 1) * (aW @ aV), axis=-1), axis=-1)
    w_inf = np.max(np.sum(aW, axis=-1), axis=-1)
    inv_norm = np.where(z < 0.5, w_inf / (1 - z), np.inf)
    g = inv_norm * np.max(np.sum(Rb, axis=-1), axis=-1)
    hi: FloatArray = (amu.max(axis=-1) * (1 + 4 * _U) + g) * (1 + 4 * _U)
    return np.where(np.isfinite(hi), hi, np.inf)


__all__ = ["radius_upper_bound"]
