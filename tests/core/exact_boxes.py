"""Reference values of the self-normalized box in 60-digit mpmath (docs/uncertainty.md (b)-(d)).

Independent of svrobs_core: the Gram matrix is formed from the double data in
exact products (mpmath.fdot at 60 digits), inverted and decomposed by
mpmath. Used by tests/core/test_certificates_rigorous.py and bench/certificates_audit.py.
"""

from __future__ import annotations

from dataclasses import dataclass

import mpmath as mp
import numpy as np

DPS = 60

# Ill-conditioned specs (cond(Z Z^T + g I) 1e18-1e19): an unstable fast/slow
# system whose slow direction only the noise excites, and the paper's unstable
# system over a long rollout (bench/certificates_audit.py; the tests trim reps).
FASTSLOW = {
    "systems": [
        {
            "name": "fastslow_unst",
            "A": [[1.02515, 0.02485], [0.02485, 1.02515]],
            "B": [[1.0], [1.0]],
            "sigma_v": 100.0,
        }
    ],
    "sigma_w": [0.001],
    "N": [20],
    "T0": 365,
    "reps": 300,
    "estimators": ["svr"],
    "gamma": [1e-06],
    "bounds_method": "self-normalized",
    "delta": 0.05,
    "margin": 1e-06,
    "stages": ["estimate", "bounds", "gain"],
    "seed": 0,
}
PAPER_T900 = {
    "systems": ["paper-unstable"],
    "sigma_w": [1.0],
    "N": [20],
    "T0": 900,
    "reps": 4,
    "estimators": ["ols", "svr"],
    "gamma": [0.05, 1.0],
    "bounds_method": "self-normalized",
    "delta": 0.05,
    "stages": ["estimate", "bounds", "gain"],
    "seed": 0,
}


@dataclass
class ExactBox:
    beta: float
    R: np.ndarray  # (n, d)
    eps_A: float
    eps_B: float
    cond: float  # cond(V), V = Z Z^T + lam I (lam = 0: Z Z^T)


def gram(Z) -> mp.matrix:
    """Z Z^T of a double (d, N0) array, every product exact, sums to 60 digits."""
    with mp.workdps(DPS):
        rows = [[mp.mpf(float(v)) for v in row] for row in np.asarray(Z, dtype=float)]
        d = len(rows)
        G = mp.matrix(d, d)
        for i in range(d):
            for j in range(i, d):
                G[i, j] = G[j, i] = mp.fdot(rows[i], rows[j])
        return G


def _eig_sym(M):
    E, _ = mp.eigsy(M)
    return sorted(E[i] for i in range(M.rows))


def exact_box(Z, theta, *, sigma_w, delta, lam, S, lambda0=1.0, shrink=0.0) -> ExactBox:
    """The box of one cell: theta (n, d) the centre, lam the ridge parameter (0: OLS)."""
    theta = np.asarray(theta, dtype=float)
    n, d = theta.shape
    with mp.workdps(DPS):
        G = gram(Z)
        eye = mp.eye(d)
        two_log = 2 * mp.log(mp.mpf(n) / mp.mpf(delta))
        sw = mp.mpf(sigma_w)
        if lam > 0:
            lam_ = mp.mpf(lam)
            V = G + lam_ * eye
            logdet = mp.log(mp.det(V)) - d * mp.log(lam_)
            beta = sw * mp.sqrt(logdet + two_log) + mp.sqrt(lam_) * mp.mpf(S)
        else:
            V = G
            l0 = mp.mpf(lambda0)
            logdet = mp.log(mp.det(G + l0 * eye)) - d * mp.log(l0)
            lmin = _eig_sym(G)[0]
            beta = sw * mp.sqrt((1 + l0 / lmin) * (logdet + two_log))
        ev = _eig_sym(V)
        Vi = mp.inverse(V)
        R = np.empty((n, d))
        for i in range(n):
            for j in range(d):
                R[i, j] = float(beta * mp.sqrt(Vi[j, j]) + mp.mpf(shrink) * abs(theta[i, j]))
        WA = Vi[:n, :n]
        eps_A = mp.sqrt(n) * beta * mp.sqrt(_eig_sym(WA)[-1])
        eps_B = mp.mpf(0)
        if d > n:
            WB = Vi[n:, n:]
            eps_B = mp.sqrt(n) * beta * mp.sqrt(_eig_sym(WB)[-1])
        if shrink:
            eps_A += mp.mpf(shrink) * mp.mpf(float(np.linalg.norm(theta[:, :n], 2)))
            eps_B += mp.mpf(shrink) * mp.mpf(float(np.linalg.norm(theta[:, n:], 2)))
        return ExactBox(
            beta=float(beta),
            R=R,
            eps_A=float(eps_A),
            eps_B=float(eps_B),
            cond=float(ev[-1] / ev[0]),
        )


def exact_sigma_bar(Z, F, *, delta, lambda0=1.0):
    """(sigma_bar, D) of the noise bound of measured data (docs/measured.md#sigma-w-estimate)
    on the double data Z (d, N0), F (n, N0), delta1 = delta2 = delta / 4: the exact least
    squares residual, eigenvalues and log det to 60 digits (the chi2 quantile is scipy's).
    sigma_bar is None where D <= 0."""
    from scipy.stats import chi2

    F = np.asarray(F, dtype=float)
    n, N0 = F.shape
    q = delta / 4
    with mp.workdps(DPS):
        G = gram(Z)
        Zm = mp.matrix([[mp.mpf(float(v)) for v in row] for row in np.asarray(Z, dtype=float)])
        Gi = mp.inverse(G)
        rss = mp.mpf(0)
        for i in range(n):
            f = mp.matrix([[mp.mpf(float(v)) for v in F[i]]])
            r = f - (f * Zm.T) * Gi * Zm
            rss += mp.fsum(r[0, k] ** 2 for k in range(N0))
        lam = _eig_sym(G)
        c = 1 + mp.mpf(lambda0) / lam[0]
        logdet = mp.fsum(mp.log(1 + x / lambda0) for x in lam)
        D = mp.mpf(chi2.ppf(q, n * N0)) - n * c * (logdet + 2 * mp.log(n / mp.mpf(q)))
        return (float(mp.sqrt(rss / D)) if D > 0 else None), D


def exact_rho(M) -> mp.mpf:
    """The spectral radius of a small double matrix, to 60 digits."""
    with mp.workdps(DPS):
        A = mp.matrix([[mp.mpf(float(v)) for v in row] for row in np.asarray(M, dtype=float)])
        E = mp.eig(A, left=False, right=False)
        return max(abs(e) for e in E)
