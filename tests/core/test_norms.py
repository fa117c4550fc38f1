"""H2 / H-infinity norms (docs/science.md#7-cost-bound-theorem-3) against independent
oracles: truncated impulse-response sums, python-control's norm(), scipy."""

from __future__ import annotations

import warnings

import control
import numpy as np
import pytest
import scipy.linalg as sla

from svrobs_core.norms import (
    REASON_NONFINITE,
    REASON_UNSTABLE,
    h2_norm,
    hinf_norm,
    is_schur,
    spectral_radius,
    stability_reason,
    stein_solve,
)


def random_stable(rng, n, rho):
    F = rng.standard_normal((n, n))
    return F * (rho / np.abs(np.linalg.eigvals(F)).max())


def impulse_h2(F, G, H, steps=None):
    """sqrt(sum_k ||H F^k G||_F^2), truncated where F^k is negligible."""
    rho = np.abs(np.linalg.eigvals(F)).max()
    if steps is None:
        steps = int(np.ceil(np.log(1e-20) / np.log(rho))) + 50
    total, M = 0.0, G.copy()
    for _ in range(steps):
        total += np.sum((H @ M) ** 2)
        M = F @ M
    return np.sqrt(total)


def control_hinf(F, G, H, D=None):
    """python-control's H-inf norm. Its Hamiltonian code uses one identity
    of size p for both R = g^2 I_m - D^T D and I_p + D R^-1 D^T, so it is only
    right for square D: pad with zero inputs / outputs (which change no
    singular value) to make the system square."""
    n, m, p = F.shape[0], G.shape[1], H.shape[0]
    D = np.zeros((p, m)) if D is None else D
    q = max(m, p)
    Gp = np.zeros((n, q))
    Gp[:, :m] = G
    Hp = np.zeros((q, n))
    Hp[:p] = H
    Dp = np.zeros((q, q))
    Dp[:p, :m] = D
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return control.norm(control.ss(F, Gp, Hp, Dp, dt=True), "inf", tol=1e-11)


# ---------------------------------------------------------------- H2
@pytest.mark.parametrize("n,m,p", [(1, 1, 1), (3, 1, 3), (3, 3, 3), (4, 2, 1), (5, 3, 2)])
def test_h2_equals_impulse_response_sum(n, m, p):
    rng = np.random.default_rng(10 * n + m + p)
    for rho in (0.3, 0.9, 0.99):
        F = random_stable(rng, n, rho)
        G = rng.standard_normal((n, m))
        H = rng.standard_normal((p, n))
        assert h2_norm(F, G, H) == pytest.approx(impulse_h2(F, G, H), rel=1e-10)


def test_h2_batched_matches_single_and_python_control():
    rng = np.random.default_rng(1)
    Fs = np.stack([random_stable(rng, 3, r) for r in np.linspace(0.2, 0.97, 6)]).reshape(2, 3, 3, 3)
    G = rng.standard_normal((3, 2))  # shared
    H = rng.standard_normal((2, 3, 4, 3))  # batched, 4 outputs
    got = h2_norm(Fs, G, H)
    assert got.shape == (2, 3)
    for i in range(2):
        for j in range(3):
            one = h2_norm(Fs[i, j], G, H[i, j])
            assert got[i, j] == pytest.approx(float(one), rel=1e-12)
            ref = control.norm(control.ss(Fs[i, j], G, H[i, j], np.zeros((4, 2)), dt=True), 2)
            assert got[i, j] == pytest.approx(ref, rel=1e-9)


def test_h2_large_n_uses_smith_and_is_right():
    rng = np.random.default_rng(2)
    n = 14  # n*n > 144: squared Smith iteration
    F = random_stable(rng, n, 0.95)
    G = rng.standard_normal((n, 2))
    H = rng.standard_normal((3, n))
    assert h2_norm(F, G, H) == pytest.approx(impulse_h2(F, G, H), rel=1e-9)
    W = sla.solve_discrete_lyapunov(F, G @ G.T)
    assert h2_norm(F, G, H) == pytest.approx(np.sqrt(np.trace(H @ W @ H.T)), rel=1e-9)


def test_stein_sylvester_against_sum():
    rng = np.random.default_rng(3)
    F = random_stable(rng, 3, 0.9)
    Fr = random_stable(rng, 2, 0.8)
    Q = rng.standard_normal((3, 2))
    ref = np.zeros((3, 2))
    for k in range(600):
        ref += np.linalg.matrix_power(F, k) @ Q @ np.linalg.matrix_power(Fr, k).T
    X = stein_solve(F, Q, Fr=Fr)
    np.testing.assert_allclose(X, ref, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(X, F @ X @ Fr.T + Q, rtol=1e-12, atol=1e-12)


def test_h2_unstable_is_nan_with_reason():
    rng = np.random.default_rng(4)
    F = np.stack(
        [
            random_stable(rng, 3, 0.5),
            random_stable(rng, 3, 1.2),
            np.diag([1.0, 0.2, 0.1]),
            np.full((3, 3), np.nan),
        ]
    )
    G, H = np.eye(3), np.eye(3)
    val, why = h2_norm(F, G, H, return_reason=True)
    assert np.isfinite(val[0]) and np.isnan(val[1:]).all()
    assert list(why) == [None, REASON_UNSTABLE, REASON_UNSTABLE, REASON_NONFINITE]
    assert list(is_schur(F)) == [True, False, False, False]
    v1, w1 = h2_norm(F[1], G, H, return_reason=True)
    assert np.isnan(v1) and w1 == REASON_UNSTABLE
    assert stability_reason(F[0]) is None


# ---------------------------------------------------------------- H-infinity
@pytest.mark.parametrize("seed", range(6))
def test_hinf_matches_python_control_random(seed):
    rng = np.random.default_rng(100 + seed)
    for _ in range(5):
        n, m, p = rng.integers(1, 6), rng.integers(1, 4), rng.integers(1, 4)
        F = random_stable(rng, n, rng.uniform(0.2, 0.995))
        G = rng.standard_normal((n, m))
        H = rng.standard_normal((p, n))
        D = rng.standard_normal((p, m)) if rng.random() < 0.5 else None
        assert hinf_norm(F, G, H, D) == pytest.approx(control_hinf(F, G, H, D), rel=1e-6)


def test_hinf_lightly_damped_resonance():
    # complex pole pair at radius 0.999: a peak far narrower than the grid spacing
    r, th = 0.999, 1.234
    F = r * np.array([[np.cos(th), -np.sin(th)], [np.sin(th), np.cos(th)]])
    G = np.array([[1.0], [0.0]])
    H = np.array([[0.0, 1.0]])
    assert hinf_norm(F, G, H) == pytest.approx(control_hinf(F, G, H), rel=1e-6)


def test_hinf_stacked_identity_shapes():
    """[Phi_A B; I] as (F=A, G=B, H=[I;0], D=[0;I]): sigma^2 = 1 + ||Phi_A B||^2."""
    A = np.array([[0.9, 0.01, 0], [0.01, 0.9, 0.01], [0, 0.01, 0.9]])
    B = np.array([[1.0], [1.5], [2.0]])
    H = np.vstack([np.eye(3), np.zeros((1, 3))])
    D = np.vstack([np.zeros((3, 1)), np.eye(1)])
    got = hinf_norm(A, B, H, D)
    plain = hinf_norm(A, B, np.eye(3))
    assert got == pytest.approx(np.sqrt(1 + plain**2), rel=1e-12)
    assert got == pytest.approx(control_hinf(A, B, H, D), rel=1e-6)
    # SISO-like direction: the peak of a stable positive system is at w = 0
    assert plain == pytest.approx(np.linalg.norm(np.linalg.solve(np.eye(3) - A, B)), rel=1e-9)


def test_hinf_batched_and_unstable():
    rng = np.random.default_rng(7)
    F = np.stack(
        [random_stable(rng, 3, 0.8), random_stable(rng, 3, 1.05), random_stable(rng, 3, 0.95)]
    )
    G = rng.standard_normal((3, 3, 2))
    H = rng.standard_normal((2, 3))
    val, why = hinf_norm(F, G, H, return_reason=True)
    assert val.shape == (3,)
    assert np.isnan(val[1]) and list(why) == [None, REASON_UNSTABLE, None]
    for i in (0, 2):
        assert val[i] == pytest.approx(float(hinf_norm(F[i], G[i], H)), rel=1e-12)
        assert val[i] == pytest.approx(control_hinf(F[i], G[i], H), rel=1e-6)
    assert np.isnan(hinf_norm(np.diag([1.01, 0.5]), np.eye(2), np.eye(2)))


def test_spectral_radius_batched():
    A = np.array([[[0.5, 1.0], [0.0, -0.7]], [[0.0, 1.0], [-1.0, 0.0]]])
    np.testing.assert_allclose(spectral_radius(A), [0.7, 1.0])
