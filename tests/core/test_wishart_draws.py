"""Wishart draws of datasets and bootstrap resamples (docs/science.md#15-wishart-draws,
docs/uncertainty.md#how-the-resamples-are-drawn).

Oracles: scipy's Wishart sampler for the law of the scatter matrix; the rollouts'
own statistics (two-sample Kolmogorov-Smirnov tests and means within their standard
errors) and their exact expectation, propagated here by the covariance recursion;
the rollouts' bits where N is at most the noise dimension; end to end, the records
of a spec run both ways.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy import stats

from svrobs_core import parse_spec, run_spec
from svrobs_core import uncertainty as unc
from svrobs_core.rollouts import gram_data, resampled_grams
from svrobs_core.seeding import seed_key
from svrobs_core.systems import resolve_system
from svrobs_core.wishart_draws import dataset_columns, noise_dim

# A 2-state, 1-input system used only here, and a second one driven by the same noise.
A1 = np.array([[0.7, 0.2], [-0.1, 0.5]])
B1 = np.array([[0.4], [1.0]])
A2 = np.array([[0.95, 0.0], [0.3, 0.2]])
B2 = np.array([[1.0], [-0.5]])
S1, S2 = 0.6, 1.3  # their noise levels
SIGMA_U, T0 = 0.8, 3


def _systems():
    return np.array(
        [
            [
                np.concatenate([A, B, s * np.eye(2)], axis=1)
                for A, B, s in ((A1, B1, S1), (A2, B2, S2))
            ]
        ]
    )


def _grams(N, draws, *, D, x0_std=0.0, data="all", seed=4):
    keys = [seed_key(0, 0, N, r) for r in range(D)]
    G, W = [], []
    for _, g, w, _, _ in resampled_grams(
        seed,
        keys,
        _systems(),
        np.zeros(D, dtype=int),
        sigma_u=SIGMA_U,
        N=N,
        T0=T0,
        data=data,
        x0_std=x0_std,
        draws=draws,
    ):
        G.append(g.copy())
        W.append(w.copy())
    return np.concatenate(G), np.concatenate(W)


def _expected_gram(A, B, s, *, N, x0_std, data, sigma_u=SIGMA_U):
    """E[Z Z^T] of N rollouts: the covariance of x_k propagated step by step."""
    n, m = B.shape
    X = x0_std**2 * np.eye(n)
    out = np.zeros((n + m, n + m))
    k0 = 1 if data == "all" else T0 - 1
    for k in range(T0):
        if k >= k0:
            out[:n, :n] += X
            out[n:, n:] += sigma_u**2 * np.eye(m)
        X = A @ X @ A.T + sigma_u**2 * B @ B.T + s**2 * np.eye(n)
    return N * out


def test_bartlett_factor_has_the_wishart_law():
    """The Gram matrix of the pseudo-noise alone: one system, A = 0, B = 0, so the
    regression columns are the inputs u_k and G is a block of the scatter matrix."""
    q_u, N, D = T0 - 1, 20, 4000  # T0 = 3, data "all": u_1, u_2 of the m = 1 input
    systems = np.zeros((1, 1, 1, 3))  # n = 1, m = 1: [A B s I] = 0
    keys = [seed_key(0, 0, N, r) for r in range(D)]
    G = np.concatenate(
        [
            g[:, 0].copy()
            for _, g, _, _, _ in resampled_grams(
                1,
                keys,
                systems,
                np.zeros(D, dtype=int),
                sigma_u=1.0,
                N=N,
                T0=T0,
                draws="wishart",
            )
        ]
    )
    assert dataset_columns(N, n=1, m=1, T0=T0, x0_std=0.0, draws="wishart") == 6 < N
    # x_k = 0, so G = [[0, 0], [0, u_1^2 + u_2^2]] summed over the rollouts: chi^2(2 N)
    assert np.all(G[:, 0, :] == 0)
    u2 = G[:, 1, 1]
    oracle = stats.wishart(df=N, scale=np.eye(q_u)).rvs(D, random_state=7)
    ref = np.trace(oracle, axis1=-2, axis2=-1)
    assert stats.ks_2samp(u2, ref).pvalue > 1e-3
    assert stats.kstest(u2, stats.chi2(2 * N).cdf).pvalue > 1e-3


@pytest.mark.parametrize("x0_std,data", [(0.0, "all"), (0.9, "final")])
def test_wishart_grams_have_the_rollouts_law(x0_std, data):
    N, D = 40, 3000
    assert dataset_columns(N, n=2, m=1, T0=T0, x0_std=x0_std, draws="wishart") == noise_dim(
        n=2, m=1, T0=T0, x0_std=x0_std
    )
    Gr, Wr = _grams(N, "rollouts", D=D, x0_std=x0_std, data=data)
    Gw, Ww = _grams(N, "wishart", D=D, x0_std=x0_std, data=data)
    for e, (A, B, s) in enumerate(((A1, B1, S1), (A2, B2, S2))):
        exact = _expected_gram(A, B, s, N=N, x0_std=x0_std, data=data)
        for G in (Gr[:, e], Gw[:, e]):
            se = G.std(axis=0) / np.sqrt(D)
            assert np.all(np.abs(G.mean(axis=0) - exact) <= 5 * se + 1e-9)
        # W = sum_k w_k z_k^T: w_k is independent of z_k, so its mean is 0
        for W in (Wr[:, e], Ww[:, e]):
            assert np.all(np.abs(W.mean(axis=0)) <= 5 * W.std(axis=0) / np.sqrt(D))
        for i, j in ((0, 0), (1, 2), (2, 2), (0, 1)):
            assert stats.ks_2samp(Gr[:, e, i, j], Gw[:, e, i, j]).pvalue > 1e-3
        assert stats.ks_2samp(Wr[:, e, 1, 0], Ww[:, e, 1, 0]).pvalue > 1e-3
        eig_r, eig_w = np.linalg.eigvalsh(Gr[:, e])[:, 0], np.linalg.eigvalsh(Gw[:, e])[:, 0]
        assert stats.ks_2samp(eig_r, eig_w).pvalue > 1e-3


def test_at_most_the_noise_dimension_the_draws_are_the_rollouts():
    q = noise_dim(n=2, m=1, T0=T0, x0_std=0.0)
    for N in (3, q):
        Gr, Wr = _grams(N, "rollouts", D=20)
        Gw, Ww = _grams(N, "wishart", D=20)
        np.testing.assert_array_equal(Gr, Gw)
        np.testing.assert_array_equal(Wr, Ww)


@pytest.mark.parametrize("loss_scale", ["sum", "mean"])
def test_bootstrap_boxes_have_the_same_law_under_both_draws(loss_scale):
    """The ridge parameter takes the real sample count (gamma N0 with the mean loss),
    not the pseudo-rollouts' column count: the boxes' spread agrees."""
    R, N = 200, 60
    theta = np.broadcast_to(np.concatenate([A1, B1], axis=1), (R, 2, 2, 3)).copy()
    kw = {
        "estimators": [("ols", None), ("svr", 0.5)],
        "sigma_w": S1,
        "sigma_u": SIGMA_U,
        "N": N,
        "T0": T0,
        "seed": 3,
        "keys": [seed_key(0, 0, N, r) for r in range(R)],
        "delta": 0.1,
        "boot_reps": 40,
        "loss_scale": loss_scale,
    }
    rol = unc.bootstrap_box(theta, draws="rollouts", **kw)
    wis = unc.bootstrap_box(theta, draws="wishart", **kw)
    for e in range(2):
        for a, b in ((rol.eps_A[:, e], wis.eps_A[:, e]), (rol.eps_B[:, e], wis.eps_B[:, e])):
            assert stats.ks_2samp(a, b).pvalue > 1e-3
            se = np.hypot(a.std(), b.std()) / np.sqrt(R)
            assert abs(a.mean() - b.mean()) <= 5 * se


# ---------------------------------------------------------------------------
# the data of a simulated job
# ---------------------------------------------------------------------------
SYSTEM = resolve_system(
    {"name": "wishart-2x1", "A": A1.tolist(), "B": B1.tolist(), "sigma_u": SIGMA_U}
)


def _data(N, draws, *, R, x0_std=0.0, data="all"):
    keys = [seed_key(0, 0, N, r) for r in range(R)]
    return gram_data(
        SYSTEM, S1, N, T0, seed=2, keys=keys, data=data, x0_std=x0_std, keep_data=True, draws=draws
    )


@pytest.mark.parametrize("x0_std,data", [(0.0, "all"), (0.9, "final")])
def test_wishart_data_have_the_rollouts_law(x0_std, data):
    N, R = 40, 3000
    Gr, Pr, _, _ = _data(N, "rollouts", R=R, x0_std=x0_std, data=data)
    Gw, Pw, Zw, Fw = _data(N, "wishart", R=R, x0_std=x0_std, data=data)
    K = T0 - 1 if data == "all" else 1
    q = noise_dim(n=2, m=1, T0=T0, x0_std=x0_std)
    assert Zw.shape == (R, 3, K * q) and Fw.shape == (R, 2, K * q)  # q < N pseudo-rollouts
    np.testing.assert_allclose(Zw @ np.swapaxes(Zw, -1, -2), Gw, rtol=1e-12)
    exact = _expected_gram(A1, B1, S1, N=N, x0_std=x0_std, data=data)
    for G in (Gr, Gw):
        assert np.all(np.abs(G.mean(axis=0) - exact) <= 5 * G.std(axis=0) / np.sqrt(R) + 1e-9)
    for i, j in ((0, 0), (1, 2), (0, 1)):
        assert stats.ks_2samp(Gr[:, i, j], Gw[:, i, j]).pvalue > 1e-3
    for i, j in ((0, 0), (1, 2)):
        assert stats.ks_2samp(Pr[:, i, j], Pw[:, i, j]).pvalue > 1e-3


def test_wishart_data_at_most_the_noise_dimension_are_the_rollouts():
    q = noise_dim(n=2, m=1, T0=T0, x0_std=0.0)
    for N in (2, q):
        for a, b in zip(_data(N, "rollouts", R=5), _data(N, "wishart", R=5)):
            np.testing.assert_array_equal(a, b)


def test_records_have_the_same_law_under_both_draws():
    """Estimates, the sound box and the bootstrap with the residual noise level (its
    N0 is the real sample count, not the pseudo-rollouts' columns) agree in law."""
    base = {
        "systems": [SYSTEM.to_dict()],
        "sigma_w": [S1],
        "N": [60],
        "T0": T0,
        "reps": 300,
        "gamma": [0.5],
        "estimators": ["ols", "svr"],
        "loss_scale": "mean",
        "seed": 8,
    }
    fields = ("rmse_A", "rmse_B", "r_A", "eps_A", "eps_B")
    for bounds in (
        {"bounds_method": "self-normalized"},
        {"bounds_method": "bootstrap", "boot_reps": 20},
    ):
        recs = {}
        for draws in ("rollouts", "wishart"):
            spec = parse_spec({**base, **bounds, "draws": draws})
            recs[draws] = [r for batch in run_spec(spec) for r in batch]
        for est in ("ols", "svr"):
            for f in fields:
                a, b = ([r[f] for r in recs[d] if r["estimator"] == est] for d in recs)
                assert stats.ks_2samp(a, b).pvalue > 1e-3, (bounds, est, f)
