"""Tests of svrobs_core.uncertainty (docs/uncertainty.md).

Oracles: the formulas re-written here with explicit inverses, slogdet and
loops; Monte Carlo coverage on a 2-state system used nowhere else; the
bootstrap re-simulated here in plain loops with numpy's own SeedSequence and
lstsq; eigenvalues of matrices sampled from a certified box.
"""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest

from svrobs_core import estimators as est
from svrobs_core import gains, kalman
from svrobs_core import uncertainty as unc
from svrobs_core.rollouts import gram_data
from svrobs_core.seeding import rng_for, seed_key
from svrobs_core.systems import resolve_system

# A system used only here: 2 states, 1 input, ||A||, ||B|| < M = 1.2.
TOY = resolve_system(
    {
        "name": "toy-2x1",
        "A": [[0.6, 0.25], [-0.15, 0.45]],
        "B": [[0.3], [1.0]],
        "sigma_u": 1.0,
        "sigma_v": 0.2,
    }
)
TOY_M = 1.2
TOY_THETA = np.concatenate([TOY.A, TOY.B], axis=1)


def _ref_box(G, theta, *, sigma_w, delta, lam, S, lambda0=1.0, shrink=0.0):
    """The formulas of docs/uncertainty.md for one cell, with inverses and slogdet."""
    n, d = theta.shape
    if lam > 0:
        V = G + lam * np.eye(d)
        logdet = np.linalg.slogdet(np.eye(d) + G / lam)[1]
        beta = sigma_w * math.sqrt(logdet + 2 * math.log(n / delta)) + math.sqrt(lam) * S
    else:
        V = G
        logdet = np.linalg.slogdet(np.eye(d) + G / lambda0)[1]
        factor = 1 + lambda0 / min(np.linalg.eigvalsh(G))
        beta = sigma_w * math.sqrt(factor * (logdet + 2 * math.log(n / delta)))
    Vi = np.linalg.inv(V)
    R = np.empty((n, d))
    for i in range(n):
        for j in range(d):
            R[i, j] = beta * math.sqrt(Vi[j, j]) + shrink * abs(theta[i, j])
    eps_A = math.sqrt(n) * beta * math.sqrt(max(np.linalg.eigvalsh(Vi[:n, :n])))
    eps_B = math.sqrt(n) * beta * math.sqrt(max(np.linalg.eigvalsh(Vi[n:, n:])))
    eps_A += shrink * np.linalg.norm(theta[:, :n], 2)
    eps_B += shrink * np.linalg.norm(theta[:, n:], 2)
    return beta, R, eps_A, eps_B, V


@pytest.mark.parametrize("n,m", [(2, 1), (3, 2)])
def test_self_normalized_radii_match_the_formula(n, m):
    rng = np.random.default_rng(7 + n)
    d = n + m
    Z = rng.standard_normal((4, d, 30)) * rng.uniform(0.5, 3, (4, d, 1))
    G = Z @ np.swapaxes(Z, -1, -2)
    theta = rng.standard_normal((4, 3, n, d))
    lam = np.array([0.0, 0.3, 12.0])  # OLS, two ridges
    shrink = np.array([0.2, 0.0, 0.0])  # cell 0 is shrunk-ols
    sw = rng.uniform(0.1, 2.0, (4, 1))
    S = 1.7
    box = unc.self_normalized_box(
        G[:, None], theta, sigma_w=sw, delta=0.05, lam=lam, S=S, lambda0=2.0, shrink=shrink
    )
    assert box.ok.all()
    for r in range(4):
        for e in range(3):
            beta, R, eA, eB, _ = _ref_box(
                G[r],
                theta[r, e],
                sigma_w=sw[r, 0],
                delta=0.05,
                lam=lam[e],
                S=S,
                lambda0=2.0,
                shrink=shrink[e],
            )
            if shrink[e] == 0:
                assert box.beta[r, e] == pytest.approx(beta, rel=1e-10)
            np.testing.assert_allclose(box.R_A[r, e], R[:, :n], rtol=1e-9)
            np.testing.assert_allclose(box.R_B[r, e], R[:, n:], rtol=1e-9)
            assert box.eps_A[r, e] == pytest.approx(eA, rel=1e-9)
            assert box.eps_B[r, e] == pytest.approx(eB, rel=1e-9)
    assert box.r_A.shape == (4, 3)
    np.testing.assert_array_equal(box.r_A, box.R_A.max(axis=(-2, -1)))


def test_spectral_bound_is_attained_and_below_the_issue_bound():
    """eps_A is the max of ||Delta_A|| over {||Delta_i||_V <= beta}: the worst Delta
    built in the proof reaches it, random Deltas on the set stay below it, and it
    is below the simpler sqrt(n) beta / sqrt(lambda_min(V))."""
    rng = np.random.default_rng(3)
    n, m = 3, 1
    d = n + m
    Z = rng.standard_normal((d, 40)) * np.array([[1.0], [2.0], [0.5], [3.0]])
    G = Z @ Z.T
    theta = rng.standard_normal((n, d))
    box = unc.self_normalized_box(G, theta, sigma_w=1.0, delta=0.01, lam=0.5, S=2.0)
    beta, _, eA, eB, V = _ref_box(G, theta, sigma_w=1.0, delta=0.01, lam=0.5, S=2.0)
    Vi = np.linalg.inv(V)
    w, X = np.linalg.eigh(Vi[:n, :n])
    v = Vi[:, :n] @ X[:, -1]
    row = beta * v / math.sqrt(v @ V @ v)
    worst = np.tile(row, (n, 1))
    assert np.linalg.norm(worst[:, :n], 2) == pytest.approx(float(box.eps_A), rel=1e-9)
    Lc = np.linalg.cholesky(V)
    for _ in range(200):  # random points of the product of ellipsoids
        y = rng.standard_normal((n, d))
        y *= beta * rng.uniform(0, 1, (n, 1)) / np.linalg.norm(y, axis=1, keepdims=True)
        delta = np.linalg.solve(Lc.T, y.T).T  # ||delta_i||_V = ||y_i|| <= beta
        assert np.linalg.norm(delta[:, :n], 2) <= box.eps_A * (1 + 1e-12)
        assert np.linalg.norm(delta[:, n:], 2) <= box.eps_B * (1 + 1e-12)
        assert np.all(np.abs(delta) <= np.concatenate([box.R_A, box.R_B], -1) * (1 + 1e-12))
    issue = math.sqrt(n) * beta / math.sqrt(min(np.linalg.eigvalsh(V)))
    assert box.eps_A <= issue and box.eps_B <= issue


def test_ols_constant_is_at_most_the_issue_constant_when_gram_dominates_lambda0():
    rng = np.random.default_rng(11)
    Z = rng.standard_normal((3, 200))
    G = Z @ Z.T
    assert min(np.linalg.eigvalsh(G)) >= 1.0
    box = unc.self_normalized_box(G, np.zeros((2, 3)), sigma_w=1.3, delta=0.02, lam=0.0, S=1.0)
    logdet = np.linalg.slogdet(np.eye(3) + G)[1]
    issue = 1.3 * math.sqrt(2 * logdet + 4 * math.log(2 / 0.02))
    assert float(box.beta) <= issue


def test_singular_gram_gives_nan_with_reason():
    Z = np.ones((3, 5))  # rank one
    box = unc.self_normalized_box(Z @ Z.T, np.zeros((2, 3)), sigma_w=1.0, delta=0.1, lam=0.0, S=1)
    assert np.isnan(box.R_A).all() and np.isnan(box.eps_A)
    assert box.reason[()] == unc.REASON_SINGULAR and not box.ok
    ridge = unc.self_normalized_box(Z @ Z.T, np.zeros((2, 3)), sigma_w=1.0, delta=0.1, lam=1.0, S=1)
    assert ridge.ok and np.isfinite(ridge.R_A).all()


def test_a_radius_that_overflows_says_so_not_that_the_estimate_is_non_finite():
    """λ0 = 5e-324 (the smallest subnormal): log det(I + G/λ0) overflows with a finite
    estimate and noise level; the reason names the cause. A NaN estimate keeps its own."""
    rng = np.random.default_rng(3)
    Z = rng.standard_normal((3, 50))
    theta = np.zeros((2, 3))
    tiny = unc.self_normalized_box(
        Z @ Z.T, theta, sigma_w=1.0, delta=0.1, lam=0.0, S=1.0, lambda0=5e-324
    )
    assert np.isnan(tiny.eps_A) and tiny.reason[()] == unc.REASON_OVERFLOW
    fine = unc.self_normalized_box(Z @ Z.T, theta, sigma_w=1.0, delta=0.1, lam=0.0, S=1.0)
    assert fine.reason[()] is None and np.isfinite(fine.eps_A)
    bad = unc.self_normalized_box(
        Z @ Z.T, theta + np.nan, sigma_w=1.0, delta=0.1, lam=0.0, S=1.0, lambda0=5e-324
    )
    assert bad.reason[()] == unc.REASON_NONFINITE
    noise = unc.self_normalized_box(Z @ Z.T, theta, sigma_w=np.inf, delta=0.1, lam=0.0, S=1.0)
    assert noise.reason[()] == unc.REASON_NONFINITE


def test_norm_above_S_is_noted():
    G = np.eye(2) * 100
    theta = np.array([[3.0, 0.0], [0.0, 0.1]])
    box = unc.self_normalized_box(G, theta[None], sigma_w=1.0, delta=0.1, lam=[0.1], S=1.0)
    assert "norm > S" in box.notes[0] and box.ok.all()


def _toy_data(R, N, T0, sigma_w, seed=5):
    keys = [seed_key(0, 0, N, r) for r in range(R)]
    G, P, Z, F = gram_data(TOY, sigma_w, N, T0, seed=seed, keys=keys, keep_data=True)
    return keys, G, P, Z, F


def _inside(theta, box):
    err = np.abs(theta - TOY_THETA)
    return np.all(err[..., :2] <= box.R_A, axis=(-2, -1)) & np.all(
        err[..., 2:] <= box.R_B, axis=(-2, -1)
    )


def test_simultaneous_coverage_of_the_self_normalized_box():
    """500 repetitions: every entry of A and of B inside at once, >= 1 - delta - 3 SE."""
    R, N, T0, sw, delta = 500, 15, 6, 0.5, 0.1
    N0 = (T0 - 1) * N
    _, G, P, Z, F = _toy_data(R, N, T0, sw)
    gammas = [0.05, 0.5]
    theta = np.concatenate(
        [
            est.fit_ols(Z, F)[:, None],
            est.svr_from_gram(G, P, N0, gammas, loss_scale="sum"),
            est.svr_from_gram(G, P, N0, gammas[:1], loss_scale="mean"),
        ],
        axis=1,
    )
    lam = np.array([0.0, *gammas, gammas[0] * N0])
    box = unc.self_normalized_box(
        G[:, None], theta, sigma_w=sw, delta=delta, lam=lam, S=math.sqrt(2) * TOY_M
    )
    inside = _inside(theta, box)
    cover = inside.mean(axis=0)
    se = math.sqrt(delta * (1 - delta) / R)
    assert np.all(cover >= 1 - delta - 3 * se), cover
    # the check has teeth: a box a fifth as wide misses often
    small = unc.BoxResult(box.R_A / 5, box.R_B / 5, box.eps_A, box.eps_B, box.reason, box.notes, 0)
    assert np.all(_inside(theta, small).mean(axis=0) < 1 - delta)
    errA = np.linalg.norm(theta[..., :2] - TOY.A, 2, axis=(-2, -1))
    errB = np.linalg.norm(theta[..., 2:] - TOY.B, 2, axis=(-2, -1))
    assert np.all(np.mean((errA <= box.eps_A) & (errB <= box.eps_B), axis=0) >= 1 - delta - 3 * se)


def _ref_bootstrap(theta, names, gammas, keys, *, sigma_w, N, T0, B, seed, x0_std, delta, joint):
    """Algorithm 2 in plain loops: numpy's own SeedSequence, lstsq, explicit ridge."""
    R, E, n, d = theta.shape
    m = d - n
    out_R = np.empty((R, E, n, d))
    out_eA = np.empty((R, E))
    out_eB = np.empty((R, E))
    for r in range(R):
        draws = []
        for b in range(B):
            g = rng_for(seed, tuple(keys[r]), (2, b))
            x0 = g.standard_normal((n, N)) * x0_std if x0_std > 0 else np.zeros((n, N))
            u = g.standard_normal((m, T0, N)) * TOY.sigma_u
            w = g.standard_normal((n, T0, N))
            draws.append((x0, u, w))
        for e in range(E):
            A, Bm = theta[r, e, :, :n], theta[r, e, :, n:]
            devs = []
            for x0, u, w in draws:
                x = [x0]
                for k in range(T0):
                    x.append(A @ x[k] + Bm @ u[:, k] + sigma_w * w[:, k])
                cols_z, cols_f = [], []
                for k in range(1, T0):
                    for j in range(N):
                        cols_z.append(np.concatenate([x[k][:, j], u[:, k, j]]))
                        cols_f.append(x[k + 1][:, j])
                Zt, Ft = np.array(cols_z), np.array(cols_f)
                if names[e] == "ols":
                    th = np.linalg.lstsq(Zt, Ft, rcond=None)[0].T
                else:
                    th = np.linalg.solve(Zt.T @ Zt + gammas[e] * np.eye(d), Zt.T @ Ft).T
                devs.append(th - theta[r, e])
            dv = np.array(devs)
            out_eA[r, e] = np.quantile([np.linalg.norm(x[:, :n], 2) for x in dv], 1 - delta)
            out_eB[r, e] = np.quantile([np.linalg.norm(x[:, n:], 2) for x in dv], 1 - delta)
            if joint:
                s = np.sqrt(np.mean(dv**2, axis=0))
                t = [np.max(np.abs(x) / s) for x in dv]
                out_R[r, e] = np.quantile(t, 1 - delta) * s
            else:
                out_R[r, e] = np.quantile(np.abs(dv), 1 - delta, axis=0)
    return out_R, out_eA, out_eB


@pytest.mark.parametrize("joint,x0_std", [(True, 0.0), (False, 0.7)])
def test_bootstrap_matches_an_independent_resimulation(joint, x0_std):
    N, T0, sw, B = 6, 4, 0.4, 25
    keys, G, P, Z, F = _toy_data(2, N, T0, sw)
    theta = np.concatenate(
        [est.fit_ols(Z, F)[:, None], est.svr_from_gram(G, P, (T0 - 1) * N, [0.3])], axis=1
    )
    kw = {"sigma_w": sw, "N": N, "T0": T0, "seed": 9, "x0_std": x0_std, "delta": 0.1}
    box = unc.bootstrap_box(
        theta,
        estimators=[("ols", None), ("svr", 0.3)],
        sigma_u=TOY.sigma_u,
        keys=keys,
        boot_reps=B,
        joint=joint,
        **kw,
    )
    R_ref, eA, eB = _ref_bootstrap(theta, ["ols", "svr"], [None, 0.3], keys, B=B, joint=joint, **kw)
    np.testing.assert_allclose(box.R_A, R_ref[..., :2], rtol=1e-12)
    np.testing.assert_allclose(box.R_B, R_ref[..., 2:], rtol=1e-12)
    np.testing.assert_allclose(box.eps_A, eA, rtol=1e-12)
    np.testing.assert_allclose(box.eps_B, eB, rtol=1e-12)


def test_bootstrap_is_bit_reproducible_and_batch_independent(monkeypatch):
    N, T0, sw = 12, 5, 0.3
    keys, G, P, Z, F = _toy_data(3, N, T0, sw)
    theta = np.concatenate(
        [est.fit_ols(Z, F)[:, None], est.shrunk_ols(est.fit_ols(Z, F), [0.1])], 1
    )
    kw = {
        "estimators": [("ols", None), ("shrunk-ols", 0.1)],
        "sigma_w": sw,
        "sigma_u": 1.0,
        "N": N,
        "T0": T0,
        "seed": 1,
        "delta": 0.05,
        "boot_reps": 30,
    }
    full = unc.bootstrap_box(theta, keys=keys, **kw)
    again = unc.bootstrap_box(theta, keys=keys, **kw)
    np.testing.assert_array_equal(full.R_A, again.R_A)
    monkeypatch.setattr(unc, "BOOT_CHUNK_BYTES", 1)  # one dataset per chunk
    one = unc.bootstrap_box(theta[1:2], keys=keys[1:2], **kw)
    np.testing.assert_array_equal(one.R_A, full.R_A[1:2])
    np.testing.assert_array_equal(one.R_B, full.R_B[1:2])
    np.testing.assert_array_equal(one.eps_A, full.eps_A[1:2])


def test_bootstrap_nonfinite_cell_is_null_with_reason():
    keys, G, P, Z, F = _toy_data(2, 8, 4, 0.3)
    theta = est.fit_ols(Z, F)[:, None].copy()
    theta[1, 0, 0, 0] = np.nan
    box = unc.bootstrap_box(
        theta,
        estimators=[("ols", None)],
        sigma_w=0.3,
        sigma_u=1.0,
        N=8,
        T0=4,
        seed=0,
        keys=keys,
        delta=0.1,
        boot_reps=10,
    )
    assert box.ok.tolist() == [[True], [False]]
    assert np.isnan(box.R_A[1]).all() and np.isfinite(box.R_A[0]).all()


def test_noise_level_is_the_residual_estimate():
    keys, G, P, Z, F = _toy_data(1000, 30, 6, 0.7)
    theta = est.fit_ols(Z, F)
    s, reason = unc.noise_level(Z, F, theta)
    assert reason is None
    assert abs(np.mean(s**2) - 0.49) < 4 * np.std(s**2) / math.sqrt(1000)
    s, reason = unc.noise_level(Z[..., :3], F[..., :3], theta)
    assert np.isnan(s).all() and "N0 > d" in reason


def _box_samples(A_hat, R_A, count, rng):
    """All corners of the box, then uniform draws: count matrices (count, n, n)."""
    n = A_hat.shape[0]
    corners = [
        A_hat + np.array(s).reshape(n, n) * R_A
        for s in itertools.product((-1.0, 1.0), repeat=n * n)
    ]
    rest = A_hat + rng.uniform(-1, 1, (count - len(corners), n, n)) * R_A
    return np.concatenate([np.array(corners), rest])


def test_certified_box_holds_for_sampled_matrices():
    """A cell certified by a self-normalized box: 1000 matrices of the box (corners
    included) all have rho(A) < 1 and rho(A - L C) < 1 for the designed L."""
    N, T0, sw = 150, 6, 0.3
    keys, G, P, Z, F = _toy_data(1, N, T0, sw, seed=21)
    theta = est.fit_ols(Z, F)[0]
    box = unc.self_normalized_box(G[0], theta, sigma_w=sw, delta=0.01, lam=0.0, S=1.0)
    A_hat, R_A = theta[:, :2], box.R_A
    assert 0 < unc.rho_upper_bound(A_hat, R_A) < 1
    C = TOY.C
    K_hat = kalman.kalman_gain(A_hat, C, sw, TOY.sigma_v)
    design = gains.design_gain(A_hat, 0.0, None, C, K_hat=K_hat, margin=0.01, R_A=R_A)
    L, g = design.L, design.g_L
    assert design.certified and g <= 0.99 + 1e-12
    assert g == pytest.approx(gains.certificate(L, A_hat, 0.0, None, C=C, R_A=R_A), abs=0)
    samples = _box_samples(A_hat, R_A, 1000, np.random.default_rng(0))
    assert samples.shape == (1000, 2, 2)
    rho_A = np.max(np.abs(np.linalg.eigvals(samples)), axis=-1)
    rho_obs = np.max(np.abs(np.linalg.eigvals(samples - L @ C)), axis=-1)
    assert np.all(rho_A < 1) and np.all(rho_obs <= g) and np.all(rho_obs < 1)
    # the truth is in this box (the event of probability >= 1 - delta happened here)
    assert np.all(np.abs(TOY.A - A_hat) <= R_A)


def test_certificates_are_false_on_nonfinite_boxes():
    A = np.eye(2) * 0.1
    assert unc.rho_upper_bound(A, np.full((2, 2), np.nan)) == np.inf
    g = gains.certificate(np.zeros((2, 2)), A, 0.0, None, C=np.eye(2), R_A=np.full((2, 2), np.nan))
    assert not g < 1
