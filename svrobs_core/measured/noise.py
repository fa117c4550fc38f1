"""The noise level of measured data: the residual estimate and a finite-sample
upper confidence bound valid for trajectory data (docs/measured.md#sigma-w-estimate).

    RSS = ||W||_F^2 - sum_i ||S_i||^2_{G^-1},   ||W||_F^2 / sigma^2 ~ chi2(n N0) exactly,
    sum_i ||S_i||^2_{G^-1} <= sigma^2 n c (l + 2 log(n / delta2))   (self-normalized, prob 1 - delta2)

so sigma^2 <= RSS / D, D = chi2_{n N0}^-1(delta1) - n c (l + 2 log(n / delta2)),
with c = 1 + lambda0 / lambda_min(G), l = log det(I + G / lambda0). And RSS <= ||W||_F^2
gives the lower bound sigma^2 >= RSS / chi2_{n N0}^-1(1 - delta1).

sigma_bar scales every radius of the box, so it carries an estimate of its relative
error (``NoiseLevel.rel_err``, docs/measured.md#sigma-w-estimate): lambda_min and l come
from the data's factor with the error estimate of the radii
(:func:`svrobs_core.data_factor.v_parts`), the residual with a bound on its rounding
(:func:`residual_error`), and D's cancellation multiplies their errors by
n c (l + ...) / D. Where the estimate exceeds RADIUS_RTOL, sigma_bar is null with a reason.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from ..array_types import Array, FloatArray
from ..data_factor import U_ROUND, GramFactor, gram_factor, v_parts
from ..uncertainty import RADIUS_RTOL

REASON_RANGE = (
    "the data or their squares are not finite doubles (a value beyond about 1e154 or a "
    "Gram beyond the double range; data of magnitude near 1e-154 or below underflow): "
    "rescale the channels"
)
REASON_FEW = "too few transitions to bound sigma_w (N0 <= d)"
REASON_DENOMINATOR = (
    "too few transitions to bound sigma_w for data of this size: the bound's denominator "
    "chi2 quantile - n c (log det(I + G / lambda0) + 2 log(n / delta)) is <= 0 (the "
    "log-determinant grows with the data's magnitude over lambda0: raise lambda0 or "
    "rescale the data)"
)
REASON_SINGULAR = "Z Z^T is singular: sigma_w cannot be bounded"
REASON_INACCURATE = (
    f"the bound on sigma_w could be off by more than {RADIUS_RTOL:g} relative (the residual"
    " is near the rounding of the data, or the bound's denominator near 0)"
)
# relative accuracy of scipy's chi2 quantile (against mpmath: below 5e-12 up to 1e6
# degrees of freedom)
PPF_RTOL = 1e-10


@dataclass
class NoiseLevel:
    """Per dataset (R,): sigma_hat = sqrt(RSS / (n (N0 - d))), sigma_bar the upper
    bound (NaN where undefined, with ``reason``), sigma_low the lower bound
    sqrt(RSS / chi2_{n N0}^-1(1 - delta1)) (RSS <= ||W||^2: probability >= 1 - delta1),
    the RSS of OLS, and rel_err the estimated relative error of sigma_bar (at most
    RADIUS_RTOL where sigma_bar is given)."""

    sigma_hat: FloatArray
    sigma_bar: FloatArray
    sigma_low: FloatArray
    rss: FloatArray
    reason: Array  # object: a reason string or None per dataset
    rel_err: FloatArray


def residual_sum(Z: FloatArray, F: FloatArray, theta: FloatArray) -> FloatArray:
    """||F - Theta Z||_F^2 per dataset: Z (R, d, N0), F (R, n, N0), theta (R, n, d)."""
    rss: FloatArray = np.sum((F - theta @ Z) ** 2, axis=(-2, -1))
    return rss


def residual_error(
    Z: FloatArray, F: FloatArray, theta: FloatArray, margin: FloatArray, rss: FloatArray
) -> FloatArray:
    """A bound on |sqrt(rss) - sqrt(RSS*)| per dataset (R,), RSS* the exact least
    squares residual of the data, rss = :func:`residual_sum` of the computed OLS
    estimate theta (R, n, d), whose distance from the exact fit is at most
    margin_i in the norm of Z Z^T (:func:`svrobs_core.data_factor.estimate_margin`).

    Two parts: the rounding of F - Theta Z and of its squares, at most
    (d + 1) u (||f_i|| + sum_j |theta_ij| ||Z_j||) per row plus (N0 + 2) u / 2 of
    the norm; and the fit's excess, sqrt(RSS* + M^2) - sqrt(RSS*) <= min(M,
    M^2 / ||r(theta)||) with M = ||margin|| (the residual of the exact fit is
    orthogonal to the rows of Z, so the excess is of second order)."""
    d, N0 = Z.shape[-2:]
    with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
        col = np.sqrt(np.sum(Z * Z, axis=-1))  # (R, d)
        a = np.sqrt(np.sum(F * F, axis=-1)) + np.sum(np.abs(theta) * col[..., None, :], axis=-1)
        e = (d + 1) * U_ROUND * np.sqrt(np.sum(a * a, axis=-1))
        s = np.sqrt(rss)
        e = e + (N0 + 2) * U_ROUND * s / 2
        M = np.sqrt(np.sum(margin * margin, axis=-1))
        floor = s - e  # a lower bound of ||r(theta)|| in exact arithmetic
        excess = np.where(floor > 0, np.minimum(M, M * M / floor), M)
        out: FloatArray = e + excess
    return np.where(np.isnan(out), np.inf, out)


def noise_level(
    G: ArrayLike | GramFactor,
    rss: FloatArray,
    *,
    n: int,
    N0: int,
    delta1: float,
    delta2: float,
    lambda0: float,
    resid_err: ArrayLike = 0.0,
) -> NoiseLevel:
    """sigma_hat and the upper bound sigma_bar (probability >= 1 - delta1 - delta2).

    G: the data's factor (:func:`svrobs_core.data_factor.data_factor`) of the R
    datasets' regressors, or their Gram matrices (R, d, d) (formed: a larger error
    estimate); rss (R,) the OLS residual sum of squares of the n estimated rows, N0
    samples each; resid_err (R,) a bound on |sqrt(rss) - sqrt(RSS)| against the exact
    least squares residual of the data."""
    from scipy.stats import chi2  # lazily: scipy.stats takes 1.5 s to import

    fac = G if isinstance(G, GramFactor) else gram_factor(G)
    rss = np.asarray(rss, dtype=float)
    d = fac.lam.shape[-1]
    R = rss.shape[0]
    reason = np.full(R, None, dtype=object)
    if N0 <= d:
        nan = np.full(R, np.nan)
        reason[:] = REASON_FEW
        return NoiseLevel(
            sigma_hat=nan,
            sigma_bar=nan.copy(),
            sigma_low=nan.copy(),
            rss=rss,
            reason=reason,
            rel_err=nan.copy(),
        )
    sigma_hat = np.sqrt(rss / (n * (N0 - d)))
    parts = v_parts(fac, 0.0, lambda0=lambda0, n=min(n, d))
    lam_min, e = parts.lam_min, parts.err
    ok = np.isfinite(fac.lam).all(axis=-1) & np.isfinite(rss)
    # singular: lambda_min not told apart from 0 by its own error estimate (a small
    # lambda_min that is known well is not: the bound's error estimate decides)
    singular = ~(lam_min > 0) | ~(e < 1.0)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        c = 1.0 + lambda0 / lam_min
        tail = parts.logdet + 2.0 * np.log(n / delta2)
        q1 = chi2.ppf(delta1, n * N0)
        D = q1 - n * c * tail
        sigma_bar = np.sqrt(rss / D)
        # |error of D|: the quantile, c (lambda_min), l and D's own arithmetic
        dD = PPF_RTOL * q1 + n * ((c - 1.0) * e * tail + c * e) + 8 * U_ROUND * (q1 + n * c * tail)
        s_err = np.asarray(resid_err, dtype=float) / np.sqrt(rss)
        rel_err = np.where(D > dD, s_err + 0.5 * dD / (D - dD), np.inf)
    good = ok & ~singular & (D > 0)
    accurate = rel_err <= RADIUS_RTOL
    reason[good & ~accurate] = REASON_INACCURATE
    reason[ok & ~singular & ~(D > 0)] = REASON_DENOMINATOR
    reason[singular & ok] = REASON_SINGULAR
    reason[~ok] = REASON_RANGE
    good &= accurate
    return NoiseLevel(
        sigma_hat=np.where(ok, sigma_hat, np.nan),
        sigma_bar=np.where(good, sigma_bar, np.nan),
        sigma_low=np.where(ok, np.sqrt(rss / chi2.isf(delta1, n * N0)), np.nan),
        rss=rss,
        reason=reason,
        rel_err=np.where(good, rel_err, np.nan),
    )
