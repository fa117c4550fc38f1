"""Finite-sample error bounds of SPEC section 3 (Theorem 1, Lemma 2, Corollary 1).

Everything is elementwise / batched: parameters broadcast like numpy arrays,
estimates carry leading batch dims (...). Nothing is clipped: a violated bound
shows up as coverage < 1 or thm1_holds = False.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class Radii:
    """H_A, H_B, r_A, r_B broadcast over the gamma array given."""

    H_A: np.ndarray
    H_B: np.ndarray
    r_A: np.ndarray
    r_B: np.ndarray


def thetas(*, n, m, N, T0, sigma_u, sigma_w, M):
    """theta_A, theta_B of Theorem 1 (SPEC section 3)."""
    Mu = M ** (2 * T0 - 1) * sigma_u**2  # M^(2T0-1) sigma_u^2
    Mw = M ** (2 * T0 - 2)  # M^(2T0-2)
    theta_A = 4 * n * (m * M * sigma_u**2 + sigma_w**2) / (N * (n * Mu + Mw * sigma_w**2))
    theta_B = 4 * m * (n * Mu + (Mw + 1) * sigma_w**2) / (N * sigma_u**2)
    return theta_A, theta_B


def H(theta, dim, *, gamma, N0, M, delta):
    """H(theta, d) of Theorem 1 (SPEC section 3)."""
    q = (theta + dim * gamma * M**2) / ((1 + gamma) * N0)
    return np.sqrt(q) + np.sqrt(2 * q * np.log(1 / delta))


def radii(*, n, m, N, N0, T0, sigma_u, sigma_w, gamma, M, delta) -> Radii:
    """Theorem 1 / Lemma 2 radii; ``gamma`` may be an array (0 for ols).

    SPEC section 3: H_A = H(theta_A, n), H_B = H(theta_B, m), r = sqrt((1+gamma) H).
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
    theta_A, theta_B = thetas(
        n=n, m=m, N=a["N"], T0=a["T0"], sigma_u=a["sigma_u"], sigma_w=a["sigma_w"], M=a["M"]
    )
    kw = {"gamma": a["gamma"], "N0": a["N0"], "M": a["M"], "delta": a["delta"]}
    H_A = H(theta_A, n, **kw)
    H_B = H(theta_B, m, **kw)
    H_A, H_B = np.broadcast_arrays(H_A, H_B)
    one_g = 1 + a["gamma"]
    return Radii(H_A=H_A.copy(), H_B=H_B.copy(), r_A=np.sqrt(one_g * H_A), r_B=np.sqrt(one_g * H_B))


@dataclass(kw_only=True)
class BoundsResult:
    """Per-estimate bound quantities; every array has the batch shape (...)."""

    eps_A: np.ndarray
    eps_B: np.ndarray
    rho_upper_bound: np.ndarray
    stable_certified: np.ndarray  # bool
    coverage_A: np.ndarray | None = None  # fraction of entries of A inside the interval
    coverage_B: np.ndarray | None = None
    thm1_holds_A: np.ndarray | None = None  # bool: Theorem 1 held for every row
    thm1_holds_B: np.ndarray | None = None


def spectral_radius(X) -> np.ndarray:
    """max |eigenvalue| of each matrix of a stack (..., k, k) -> (...)."""
    return np.max(np.abs(np.linalg.eigvals(np.asarray(X, dtype=float))), axis=-1)


def _coverage(true, est, g, r):
    c = (1 + g) * est  # Lemma 2 centre of the interval of the true entry
    inside = np.abs(true - c) <= r
    return np.mean(inside, axis=(-2, -1))


def _thm1(true, est, g, H_):
    delta = true - est
    lhs = np.linalg.norm(g * est - delta, axis=-1) / (1 + g[..., 0])  # (..., n)
    return np.all(lhs <= H_[..., None], axis=-1)


def evaluate_bounds(A_tilde, B_tilde, gamma, r: Radii, *, A_true=None, B_true=None) -> BoundsResult:
    """Corollary 1 eps, the Perron-Frobenius certificate, and (with truth) coverage.

    A_tilde (..., n, n), B_tilde (..., n, m); gamma and the radii broadcast
    against the batch shape (...). SPEC section 3:
    eps_A = sqrt(sum_ij (|gamma A~_ij| + r_A)^2) (B: j <= m),
    rho_upper_bound = rho(|(1+gamma) A~| + r_A 11^T), stable_certified = rho_ub < 1,
    coverage = fraction of entries with |true - (1+gamma) est| <= r,
    thm1_holds = every row has ||gamma est_i - (true_i - est_i)|| / (1+gamma) <= H.
    """
    A = np.asarray(A_tilde, dtype=float)
    B = np.asarray(B_tilde, dtype=float)
    g = np.asarray(gamma, dtype=float)[..., None, None]
    rA = np.asarray(r.r_A, dtype=float)[..., None, None]
    rB = np.asarray(r.r_B, dtype=float)[..., None, None]
    eps_A = np.sqrt(np.sum((np.abs(g * A) + rA) ** 2, axis=(-2, -1)))
    eps_B = np.sqrt(np.sum((np.abs(g * B) + rB) ** 2, axis=(-2, -1)))
    rho = spectral_radius(np.abs((1 + g) * A) + rA)
    out = BoundsResult(eps_A=eps_A, eps_B=eps_B, rho_upper_bound=rho, stable_certified=rho < 1)
    if A_true is not None:
        A_true = np.asarray(A_true, dtype=float)
        out.coverage_A = _coverage(A_true, A, g, rA)
        out.thm1_holds_A = _thm1(A_true, A, g, np.asarray(r.H_A, dtype=float))
    if B_true is not None:
        B_true = np.asarray(B_true, dtype=float)
        out.coverage_B = _coverage(B_true, B, g, rB)
        out.thm1_holds_B = _thm1(B_true, B, g, np.asarray(r.H_B, dtype=float))
    return out
