"""Finite-sample error bounds: Theorem 1, Lemma 2, Corollary 1
(docs/science.md#3-error-bounds-theorem-1-lemma-2-corollary-1).

Everything is elementwise / batched: parameters broadcast like numpy arrays,
estimates carry leading batch dims (...). Nothing is clipped: a violated bound
shows up as coverage < 1 or thm1_holds = False.

theta_A and theta_B hold M^(2T0-1), which leaves the double range long
before the bound becomes meaningless to ask for (M = 1.1, T0 = 3800; M = 1e20,
T0 = 9), so they are computed from logarithms; a theta that over- or
underflows all the same, and any H or r that is not finite, gives NaN radii
with a reason (``Radii.reason_A``/``reason_B``) instead of 0 or inf, and every
quantity computed from a NaN radius is undefined (NaN, or None for the
booleans), never a certificate.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, cast

import numpy as np
from numpy.typing import ArrayLike

from .array_types import Array, FloatArray
from .linalg import perron_upper_bound, up


@dataclass
class Radii:
    """H_A, H_B, r_A, r_B broadcast over the gamma array given (NaN where
    undefined); reason_A/reason_B: object arrays of None / why it is undefined."""

    H_A: Array
    H_B: Array
    r_A: Array
    r_B: Array
    reason_A: Array | None = None
    reason_B: Array | None = None


def _log(x: ArrayLike) -> FloatArray:
    with np.errstate(divide="ignore"):
        out: FloatArray = np.log(np.asarray(x, dtype=float))
    return out


def log_thetas(
    *,
    n: int,
    m: int,
    N: ArrayLike,
    T0: ArrayLike,
    sigma_u: ArrayLike,
    sigma_w: ArrayLike,
    M: ArrayLike,
) -> tuple[FloatArray, FloatArray]:
    """log theta_A, log theta_B of Theorem 1 (docs/science.md#31-the-constants), without overflow.

    theta_A = 4n (m M su^2 + sw^2) / (N (n M^(2T0-1) su^2 + M^(2T0-2) sw^2)),
    theta_B = 4m (n M^(2T0-1) su^2 + (M^(2T0-2) + 1) sw^2) / (N su^2); sums
    of powers by logaddexp (sigma_w = 0 gives log 0 = -inf terms, handled).
    """
    lM, lsu2, lsw2 = _log(M), 2 * _log(sigma_u), 2 * _log(sigma_w)
    lMu = (2 * np.asarray(T0, dtype=float) - 1) * lM + lsu2  # log M^(2T0-1) su^2
    lMw = (2 * np.asarray(T0, dtype=float) - 2) * lM  # log M^(2T0-2)
    ln, lN = np.log(n), _log(N)
    l_num_A = np.log(4 * n) + np.logaddexp(np.log(m) + lM + lsu2, lsw2)
    l_den_A = lN + np.logaddexp(ln + lMu, lMw + lsw2)
    l_num_B = np.log(4 * m) + np.logaddexp(ln + lMu, np.logaddexp(lMw, 0.0) + lsw2)
    return l_num_A - l_den_A, l_num_B - lN - lsu2


def thetas(
    *, n: int, m: int, N: Any, T0: Any, sigma_u: Any, sigma_w: Any, M: Any
) -> tuple[Any, Any]:
    """theta_A, theta_B of Theorem 1 (docs/science.md#31-the-constants).

    The formula as written where its powers stay in range (so the numbers do
    not change), else the exp of :func:`log_thetas` (inf / 0 where the value
    itself is out of the double range)."""
    with np.errstate(over="ignore", invalid="ignore", under="ignore", divide="ignore"):
        Mu = M ** (2 * T0 - 1) * sigma_u**2  # M^(2T0-1) sigma_u^2
        Mw = M ** (2 * T0 - 2)  # M^(2T0-2)
        theta_A = 4 * n * (m * M * sigma_u**2 + sigma_w**2) / (N * (n * Mu + Mw * sigma_w**2))
        theta_B = 4 * m * (n * Mu + (Mw + 1) * sigma_w**2) / (N * sigma_u**2)
        direct = np.isfinite(Mu) & np.isfinite(Mw) & (Mu > 0)
        if np.all(direct):
            return theta_A, theta_B
        la, lb = log_thetas(n=n, m=m, N=N, T0=T0, sigma_u=sigma_u, sigma_w=sigma_w, M=M)
        return np.where(direct, theta_A, np.exp(la)), np.where(direct, theta_B, np.exp(lb))


def _range_reason(
    theta: Array, H: Array, r: Array, log_theta: Array, name: str, *, M: ArrayLike, T0: Any
) -> Array:
    """None where theta is a normal positive double and H, r are finite, else why not."""
    tiny = np.finfo(float).tiny
    ok = np.isfinite(theta) & (theta >= tiny) & np.isfinite(H) & np.isfinite(r)
    out = np.full(np.shape(ok), None, dtype=object)
    ten = np.broadcast_to(log_theta / np.log(10.0), np.shape(ok))
    power = np.broadcast_to(
        (2 * np.asarray(T0, dtype=float) - 1) * _log(M) / np.log(10.0), ok.shape
    )
    for where in np.argwhere(~ok):
        idx = tuple(where)
        if not np.isfinite(theta[idx]) or theta[idx] < tiny:
            why = f"theta_{name} = 1e{ten[idx]:.0f} with M^(2T0-1) = 1e{power[idx]:.0f}"
        else:
            why = f"H_{name} not finite (M^2 = 1e{2 * power[idx] / (2 * T0 - 1):.0f})"
        out[idx] = f"bounds: H_{name}, r_{name} undefined ({why}: out of the double range)"
    return out


def H(theta: Any, dim: int, *, gamma: Any, N0: Any, M: Any, delta: Any) -> Any:
    """H(theta, d) of Theorem 1 (docs/science.md#32-theorem-1)."""
    q = (theta + dim * gamma * M**2) / ((1 + gamma) * N0)
    return np.sqrt(q) + np.sqrt(2 * q * np.log(1 / delta))


def radii(
    *,
    n: int,
    m: int,
    N: ArrayLike,
    N0: ArrayLike,
    T0: ArrayLike,
    sigma_u: ArrayLike,
    sigma_w: ArrayLike,
    gamma: ArrayLike,
    M: ArrayLike,
    delta: ArrayLike,
) -> Radii:
    """Theorem 1 / Lemma 2 radii; ``gamma`` may be an array (0 for ols).

    H_A = H(theta_A, n), H_B = H(theta_B, m), r = sqrt((1+gamma) H)
    (docs/science.md#33-lemma-2-entrywise-intervals).
    N is the rollout count, N0 the sample count (N0 = (T0-1) N for all-data,
    N for final-data). All arguments broadcast; outputs have the broadcast shape.
    """
    args = {
        "N": N,
        "N0": N0,
        "T0": T0,
        "sigma_u": sigma_u,
        "sigma_w": sigma_w,
        "gamma": gamma,
        "M": M,
        "delta": delta,
    }
    a = {k: np.asarray(v, dtype=float) for k, v in args.items()}
    if np.any(a["N"] <= 0) or np.any(a["N0"] <= 0):
        raise ValueError("N and N0 must be > 0")
    if np.any(a["sigma_u"] <= 0) or np.any(a["sigma_w"] < 0) or np.any(a["M"] <= 0):
        raise ValueError("need sigma_u > 0, sigma_w >= 0, M > 0")
    if np.any(a["gamma"] < 0):
        raise ValueError("gamma must be >= 0")
    if np.any((a["delta"] <= 0) | (a["delta"] >= 1)):
        raise ValueError("delta must be in (0, 1)")
    if int(n) < 1 or int(m) < 1:
        raise ValueError("n and m must be >= 1")
    sizes = {"N": a["N"], "T0": a["T0"], "sigma_u": a["sigma_u"], "sigma_w": a["sigma_w"]}
    la, lb = log_thetas(n=n, m=m, M=a["M"], **sizes)
    theta_A, theta_B = thetas(n=n, m=m, M=a["M"], **sizes)
    kw = {"gamma": a["gamma"], "N0": a["N0"], "M": a["M"], "delta": a["delta"]}
    with np.errstate(over="ignore", invalid="ignore"):
        H_A = H(theta_A, n, **kw)
        H_B = H(theta_B, m, **kw)
        H_A, H_B, la, lb = np.broadcast_arrays(H_A, H_B, la, lb)
        one_g = 1 + a["gamma"]
        r_A, r_B = np.sqrt(one_g * H_A), np.sqrt(one_g * H_B)
    mt = {"M": a["M"], "T0": a["T0"]}
    why_A = _range_reason(np.broadcast_to(theta_A, H_A.shape), H_A, r_A, la, "A", **mt)
    why_B = _range_reason(np.broadcast_to(theta_B, H_B.shape), H_B, r_B, lb, "B", **mt)
    bad_A, bad_B = why_A != None, why_B != None  # noqa: E711  (object arrays)
    nan = np.nan
    return Radii(
        H_A=np.where(bad_A, nan, H_A),
        H_B=np.where(bad_B, nan, H_B),
        r_A=np.where(bad_A, nan, r_A),
        r_B=np.where(bad_B, nan, r_B),
        reason_A=why_A,
        reason_B=why_B,
    )


@dataclass(kw_only=True)
class BoundsResult:
    """Per-estimate bound quantities; every array has the batch shape (...)."""

    eps_A: Array
    eps_B: Array
    rho_upper_bound: Array
    stable_certified: Array  # bool; None (object array) where rho_upper_bound is NaN
    coverage_A: Array | None = None  # fraction of entries of A inside the interval
    coverage_B: Array | None = None
    thm1_holds_A: Array | None = None  # bool: Theorem 1 held for every row (None: undefined)
    thm1_holds_B: Array | None = None


def nullable(values: ArrayLike, defined: ArrayLike) -> Array:
    """A boolean array, or an object array with None where not ``defined``."""
    values = np.asarray(values, dtype=bool)
    defined = np.broadcast_to(np.asarray(defined, dtype=bool), values.shape)
    if defined.all():
        return values
    out = values.astype(object)
    out[~defined] = None
    return out


def _finite(X: Array) -> Array:
    return cast(Array, np.isfinite(X).all(axis=(-2, -1)))


def _coverage(true: FloatArray, est: FloatArray, g: FloatArray, r: FloatArray) -> Array:
    c = (1 + g) * est  # Lemma 2 centre of the interval of the true entry
    with np.errstate(invalid="ignore"):
        inside = np.abs(true - c) <= r
    cov = np.mean(inside, axis=(-2, -1))
    return np.where(_finite(c) & np.isfinite(r[..., 0, 0]), cov, np.nan)


def _thm1(true: FloatArray, est: FloatArray, g: FloatArray, H_: FloatArray) -> Array:
    delta = true - est
    with np.errstate(over="ignore", invalid="ignore"):  # huge estimates: inf, null below
        lhs = np.linalg.norm(g * est - delta, axis=-1) / (1 + g[..., 0])  # (..., n)
        holds = np.all(lhs <= H_[..., None], axis=-1)
    return nullable(holds, np.isfinite(lhs).all(axis=-1) & np.isfinite(H_))


def evaluate_bounds(
    A_tilde: ArrayLike,
    B_tilde: ArrayLike,
    gamma: ArrayLike,
    r: Radii,
    *,
    A_true: ArrayLike | None = None,
    B_true: ArrayLike | None = None,
) -> BoundsResult:
    """Corollary 1 eps, the Perron-Frobenius certificate, and (with truth) coverage.

    A_tilde (..., n, n), B_tilde (..., n, m); gamma and the radii broadcast
    against the batch shape (...); docs/science.md#34-corollary-1-spectral-norm-bounds:
    eps_A = sqrt(sum_ij (|gamma A~_ij| + r_A)^2) (B: j <= m),
    rho_upper_bound = rho(|(1+gamma) A~| + r_A 11^T) (an upper bound of it, never
    below: the matrix rounded up and the Collatz-Wielandt bound of
    :func:`svrobs_core.linalg.perron_upper_bound`), stable_certified = rho_ub < 1,
    coverage = fraction of entries with |true - (1+gamma) est| <= r,
    thm1_holds = every row has ||gamma est_i - (true_i - est_i)|| / (1+gamma) <= H.
    """
    A = np.asarray(A_tilde, dtype=float)
    B = np.asarray(B_tilde, dtype=float)
    g = np.asarray(gamma, dtype=float)[..., None, None]
    rA = np.asarray(r.r_A, dtype=float)[..., None, None]
    rB = np.asarray(r.r_B, dtype=float)[..., None, None]
    with np.errstate(over="ignore", invalid="ignore"):
        eps_A = np.sqrt(np.sum((np.abs(g * A) + rA) ** 2, axis=(-2, -1)))
        eps_B = np.sqrt(np.sum((np.abs(g * B) + rB) ** 2, axis=(-2, -1)))
        # |(1+gamma) A~| + r_A rounded up (1 + gamma and the product: one ulp each)
        rho = perron_upper_bound(up(up(up(np.abs((1 + g) * A))) + rA))
    eps_A, eps_B = (np.where(np.isfinite(e), e, np.nan) for e in (eps_A, eps_B))
    with np.errstate(invalid="ignore"):
        stable = nullable(rho < 1, np.isfinite(rho) & np.isfinite(eps_A))
    out = BoundsResult(eps_A=eps_A, eps_B=eps_B, rho_upper_bound=rho, stable_certified=stable)
    if A_true is not None:
        A_true = np.asarray(A_true, dtype=float)
        out.coverage_A = _coverage(A_true, A, g, rA)
        out.thm1_holds_A = _thm1(A_true, A, g, np.asarray(r.H_A, dtype=float))
    if B_true is not None:
        B_true = np.asarray(B_true, dtype=float)
        out.coverage_B = _coverage(B_true, B, g, rB)
        out.thm1_holds_B = _thm1(B_true, B, g, np.asarray(r.H_B, dtype=float))
    return out
