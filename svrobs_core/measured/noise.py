"""The noise level of measured data: the residual estimate and a finite-sample
upper confidence bound valid for trajectory data (docs/measured.md#sigma-w-estimate).

    RSS = ||W||_F^2 - sum_i ||S_i||^2_{G^-1},   ||W||_F^2 / sigma^2 ~ chi2(n N0) exactly,
    sum_i ||S_i||^2_{G^-1} <= sigma^2 n c (l + 2 log(n / delta2))   (self-normalized, prob 1 - delta2)

so sigma^2 <= RSS / D, D = chi2_{n N0}^-1(delta1) - n c (l + 2 log(n / delta2)),
with c = 1 + lambda0 / lambda_min(G), l = log det(I + G / lambda0). And RSS <= ||W||_F^2
gives the lower bound sigma^2 >= RSS / chi2_{n N0}^-1(1 - delta1).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..array_types import Array, FloatArray
from ..uncertainty import SINGULAR_RTOL

REASON_FEW = "too few transitions to bound sigma_w (N0 <= d or the bound's denominator <= 0)"
REASON_SINGULAR = "Z Z^T is singular: sigma_w cannot be bounded"


@dataclass
class NoiseLevel:
    """Per dataset (R,): sigma_hat = sqrt(RSS / (n (N0 - d))), sigma_bar the upper
    bound (NaN where undefined, with ``reason``), sigma_low the lower bound
    sqrt(RSS / chi2_{n N0}^-1(1 - delta1)) (RSS <= ||W||^2: probability >= 1 - delta1),
    and the RSS of OLS."""

    sigma_hat: FloatArray
    sigma_bar: FloatArray
    sigma_low: FloatArray
    rss: FloatArray
    reason: Array  # object: a reason string or None per dataset


def residual_sum(Z: FloatArray, F: FloatArray, theta: FloatArray) -> FloatArray:
    """||F - Theta Z||_F^2 per dataset: Z (R, d, N0), F (R, n, N0), theta (R, n, d)."""
    rss: FloatArray = np.sum((F - theta @ Z) ** 2, axis=(-2, -1))
    return rss


def noise_level(
    G: FloatArray,
    rss: FloatArray,
    *,
    n: int,
    N0: int,
    delta1: float,
    delta2: float,
    lambda0: float,
) -> NoiseLevel:
    """sigma_hat and the upper bound sigma_bar (probability >= 1 - delta1 - delta2).

    G (R, d, d) the Gram matrices of the regressors, rss (R,) the OLS residual
    sum of squares of the n estimated rows, N0 samples each."""
    from scipy.stats import chi2  # lazily: scipy.stats takes 1.5 s to import

    G = np.asarray(G, dtype=float)
    rss = np.asarray(rss, dtype=float)
    d = G.shape[-1]
    R = rss.shape[0]
    reason = np.full(R, None, dtype=object)
    if N0 <= d:
        nan = np.full(R, np.nan)
        reason[:] = REASON_FEW
        return NoiseLevel(
            sigma_hat=nan, sigma_bar=nan.copy(), sigma_low=nan.copy(), rss=rss, reason=reason
        )
    sigma_hat = np.sqrt(rss / (n * (N0 - d)))
    ok = np.isfinite(G).all(axis=(-2, -1)) & np.isfinite(rss)
    lam = np.linalg.eigvalsh(np.where(ok[:, None, None], G, np.eye(d)))
    lam = np.maximum(lam, 0.0)
    singular = ~(lam[:, 0] > SINGULAR_RTOL * lam[:, -1])
    with np.errstate(divide="ignore", invalid="ignore"):
        c = 1.0 + lambda0 / lam[:, 0]
        logdet = np.sum(np.log1p(lam / lambda0), axis=-1)
        D = chi2.ppf(delta1, n * N0) - n * c * (logdet + 2.0 * np.log(n / delta2))
        sigma_bar = np.sqrt(rss / D)
    good = ok & ~singular & (D > 0)
    reason[ok & ~singular & ~(D > 0)] = REASON_FEW
    reason[singular & ok] = REASON_SINGULAR
    reason[~ok] = "non-finite data"
    return NoiseLevel(
        sigma_hat=np.where(ok, sigma_hat, np.nan),
        sigma_bar=np.where(good, sigma_bar, np.nan),
        sigma_low=np.where(ok, np.sqrt(rss / chi2.isf(delta1, n * N0)), np.nan),
        rss=rss,
        reason=reason,
    )
