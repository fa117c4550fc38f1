"""Theorem 3 cost bound (docs/science.md#7-cost-bound-theorem-3), recomputed inside the test from
python-control / scipy norms."""

from __future__ import annotations

import warnings

import control
import numpy as np
import pytest
import scipy.linalg as sla

from svrobs_core.cost import exact_cost
from svrobs_core.cost_bound import (
    REASON_A_UNSTABLE,
    REASON_F_UNSTABLE,
    TrueSystemNorms,
    theorem3_bound,
    true_system_norms,
)
from svrobs_core.norms import REASON_NONFINITE

A_S = np.array([[0.9, 0.01, 0.0], [0.01, 0.9, 0.01], [0.0, 0.01, 0.9]])
A_U = A_S + 0.11 * np.eye(3)
B_P = np.array([[1.0], [1.5], [2.0]])
SU, SW, SV = 1.0, 1.0, 0.1
NOISE = dict(sigma_u=SU, sigma_w=SW, sigma_v=SV)


def kalman(A, C, sw, sv):
    n, p = A.shape[0], C.shape[0]
    P = sla.solve_discrete_are(A.T, C.T, sw**2 * np.eye(n), sv**2 * np.eye(p))
    return A @ P @ C.T @ np.linalg.inv(C @ P @ C.T + sv**2 * np.eye(p))


def ctl_hinf(F, G, H, D):
    """python-control H-inf, padded to a square D (see test_norms.control_hinf)."""
    n, m, p = F.shape[0], G.shape[1], H.shape[0]
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


def ctl_h2(F, G):
    n, m = G.shape
    return control.norm(control.ss(F, G, np.eye(n), np.zeros((n, m)), dt=True), 2)


def stacked_hinf(A, G):
    """||[(zI-A)^-1 G; I]||_Hinf built by hand: outputs n + q, inputs q."""
    n, q = G.shape
    H = np.vstack([np.eye(n), np.zeros((q, n))])
    D = np.vstack([np.zeros((n, q)), np.eye(q)])
    return ctl_hinf(A, G, H, D)


def partial_system():
    A = np.array(
        [
            [0.8, 0.2, 0.0, 0.05],
            [-0.1, 0.85, 0.1, 0.0],
            [0.0, 0.1, 0.7, 0.2],
            [0.05, 0.0, -0.2, 0.75],
        ]
    )
    B = np.array([[1.0, 0.0], [0.5, 0.2], [0.0, 1.0], [0.3, -0.4]])
    C = np.array([[1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.5]])
    return A, B, C


@pytest.mark.parametrize("which", ["stable", "partial"])
def test_true_system_norms_match_python_control(which):
    A, B, C = (A_S, B_P, np.eye(3)) if which == "stable" else partial_system()
    K = kalman(A, C, SW, SV)
    tn = true_system_norms(A, B, C, K)
    assert tn.hinf_PhiA_B == pytest.approx(stacked_hinf(A, B), rel=1e-6)
    assert tn.hinf_PhiA_K == pytest.approx(stacked_hinf(A, K), rel=1e-6)
    Fk = A - K @ C
    n = A.shape[0]
    assert tn.h2_closed == pytest.approx(ctl_h2(Fk, np.eye(n)), rel=1e-9)
    assert tn.hinf_closed == pytest.approx(
        ctl_hinf(Fk, np.eye(n), np.eye(n), np.zeros((n, n))), rel=1e-6
    )
    assert tn.open_reason is None and tn.closed_reason is None
    assert isinstance(tn.hinf_PhiA_B, float)


@pytest.mark.parametrize("which", ["stable", "partial"])
def test_theorem3_recomputed_from_python_control(which):
    A, B, C = (A_S, B_P, np.eye(3)) if which == "stable" else partial_system()
    n, p = A.shape[0], C.shape[0]
    K = kalman(A, C, SW, SV)
    rng = np.random.default_rng(1)
    cells = 4
    At = A + 0.02 * rng.standard_normal((cells, n, n))
    L = K + 0.05 * rng.standard_normal((cells, n, p))
    eps_A = rng.uniform(0.05, 0.3, cells)
    eps_B = rng.uniform(0.05, 0.3, cells)
    tn = true_system_norms(A, B, C, K)
    res = theorem3_bound(At, L, C, K, eps_A=eps_A, eps_B=eps_B, sigma_u=SU, sigma_v=SV, norms=tn)
    assert res.J_b.shape == (cells,)
    assert list(res.reason) == [None] * cells
    hB, hK = stacked_hinf(A, B), stacked_hinf(A, K)
    for i in range(cells):
        F = At[i] - L[i] @ C
        h_w = ctl_h2(F, np.eye(n))
        h_dk = ctl_h2(F, K - L[i])
        eps_L = np.linalg.svd(K - L[i], compute_uv=False)[0]
        e1, e2 = max(eps_A[i], eps_B[i]), max(eps_A[i], eps_L)
        ref = h_dk * SV + np.sqrt(2) * e1 * h_w * hB * SU + np.sqrt(2) * e2 * h_w * hK * SV
        assert res.J_b[i] == pytest.approx(ref, rel=1e-6)
        assert res.eps_L[i] == pytest.approx(eps_L, rel=1e-12)
        assert res.h2_Phi_w[i] == pytest.approx(h_w, rel=1e-9)
        assert res.h2_Phi_dK[i] == pytest.approx(h_dk, rel=1e-9)
        assert res.term_v[i] + res.term_u[i] + res.term_K[i] == pytest.approx(res.J_b[i])
    one = theorem3_bound(
        At[2], L[2], C, K, eps_A=eps_A[2], eps_B=eps_B[2], sigma_u=SU, sigma_v=SV, norms=tn
    )
    assert one.reason is None and float(one.J_b) == pytest.approx(res.J_b[2], rel=1e-12)


def test_theorem3_with_true_model_and_gain_is_zero():
    """A~ = A, L = K, eps = 0: every term vanishes (J_b = 0 while J = J* > 0,
    the paper's bound only measures the excess over the optimal observer)."""
    K = kalman(A_S, np.eye(3), SW, SV)
    tn = true_system_norms(A_S, B_P, np.eye(3), K)
    res = theorem3_bound(
        A_S, K, np.eye(3), K, eps_A=0.0, eps_B=0.0, sigma_u=SU, sigma_v=SV, norms=tn
    )
    assert float(res.J_b) == 0.0
    assert float(exact_cost(A_S, B_P, A_S, B_P, L=K, C=np.eye(3), **NOISE)) > 0


def test_theorem3_null_for_unstable_system_U():
    K = kalman(A_U, np.eye(3), SW, SV)
    tn = true_system_norms(A_U, B_P, np.eye(3), K)
    assert np.isnan(tn.hinf_PhiA_B) and np.isnan(tn.hinf_PhiA_K)
    assert tn.open_reason == REASON_A_UNSTABLE
    assert tn.closed_reason is None and np.isfinite(tn.h2_closed)  # A - KC is stable
    rng = np.random.default_rng(2)
    At = A_U + 0.02 * rng.standard_normal((3, 3, 3))
    res = theorem3_bound(
        At,
        np.broadcast_to(K, (3, 3, 3)),
        np.eye(3),
        K,
        eps_A=np.full(3, 0.1),
        eps_B=np.full(3, 0.1),
        sigma_u=SU,
        sigma_v=SV,
        norms=tn,
    )
    assert np.isnan(res.J_b).all()
    assert list(res.reason) == [REASON_A_UNSTABLE] * 3
    # the H2 factors themselves are fine: only the true-system H-inf is undefined
    assert np.isfinite(res.h2_Phi_w).all()


def test_theorem3_unstable_observer_and_missing_gain():
    K = kalman(A_S, np.eye(3), SW, SV)
    tn = true_system_norms(A_S, B_P, np.eye(3), K)
    L = np.stack([K, K - 1.3 * np.eye(3), np.full((3, 3), np.nan)])
    res = theorem3_bound(
        np.broadcast_to(A_S, (3, 3, 3)),
        L,
        np.eye(3),
        K,
        eps_A=np.full(3, 0.1),
        eps_B=np.full(3, 0.1),
        sigma_u=SU,
        sigma_v=SV,
        norms=tn,
    )
    assert np.isfinite(res.J_b[0]) and np.isnan(res.J_b[1:]).all()
    assert list(res.reason) == [None, REASON_F_UNSTABLE, REASON_NONFINITE]


def test_theorem3_paper_cell_sanity():
    """On the paper's S system, a bound for a model near the truth: J_b is
    finite and positive, and Delta J = J_b - J can be formed."""
    K = kalman(A_S, np.eye(3), SW, SV)
    tn = true_system_norms(A_S, B_P, np.eye(3), K)
    assert isinstance(tn, TrueSystemNorms)
    rng = np.random.default_rng(3)
    At = A_S + 0.01 * rng.standard_normal((5, 3, 3))
    Bt = B_P + 0.01 * rng.standard_normal((5, 3, 1))
    L = K + 0.02 * rng.standard_normal((5, 3, 3))
    eps_A = np.linalg.norm(A_S - At, 2, axis=(1, 2)) * 1.5
    eps_B = np.linalg.norm(B_P - Bt, 2, axis=(1, 2)) * 1.5
    res = theorem3_bound(
        At, L, np.eye(3), K, eps_A=eps_A, eps_B=eps_B, sigma_u=SU, sigma_v=SV, norms=tn
    )
    J = exact_cost(A_S, B_P, At, Bt, L=L, C=np.eye(3), **NOISE)
    dJ = res.J_b - J
    assert np.isfinite(dJ).all() and (res.J_b > 0).all()
