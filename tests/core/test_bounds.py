"""Tests of svrobs_core.bounds (docs/science.md#3-error-bounds-theorem-1-lemma-2-corollary-1).

The formulas are re-written here independently (scalar math, loops) and compared
with the vectorised implementation; coverage and Theorem 1 on hand-made cases.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import scipy.linalg
from hypothesis import given, settings
from hypothesis import strategies as st

from svrobs_core.bounds import Radii, evaluate_bounds, radii

PAPER = {"n": 3, "m": 1, "T0": 11, "sigma_u": 1.0, "sigma_w": 1.0, "M": 1.1, "delta": 0.01}
fl = st.floats


def ref_H(*, n, m, N, N0, T0, sigma_u, sigma_w, gamma, M, delta):
    """Theorem 1 / Lemma 2 as printed in the paper, scalar by scalar."""
    su2, sw2 = sigma_u * sigma_u, sigma_w * sigma_w
    theta_A = (4 * n * (m * M * su2 + sw2)) / (
        N * (n * M ** (2 * T0 - 1) * su2 + M ** (2 * T0 - 2) * sw2)
    )
    theta_B = (4 * m * (n * M ** (2 * T0 - 1) * su2 + (M ** (2 * T0 - 2) + 1) * sw2)) / (N * su2)

    def H(theta, dim):
        a = (theta + dim * gamma * M * M) / ((1 + gamma) * N0)
        return math.sqrt(a) * (1 + math.sqrt(2 * math.log(1 / delta)))

    HA, HB = H(theta_A, n), H(theta_B, m)
    return HA, HB, math.sqrt((1 + gamma) * HA), math.sqrt((1 + gamma) * HB)


@settings(max_examples=150, deadline=None)
@given(
    n=st.integers(1, 6),
    m=st.integers(1, 4),
    N=st.integers(1, 3000),
    T0=st.integers(2, 20),
    sigma_u=fl(0.01, 10),
    sigma_w=fl(0, 10),
    gamma=fl(0, 5),
    M=fl(0.5, 1.5),
    delta=fl(1e-6, 0.99),
    final=st.booleans(),
)
def test_radii_match_the_printed_formulas(n, m, N, T0, sigma_u, sigma_w, gamma, M, delta, final):
    N0 = N if final else (T0 - 1) * N
    p = {
        "n": n,
        "m": m,
        "N": N,
        "N0": N0,
        "T0": T0,
        "sigma_u": sigma_u,
        "sigma_w": sigma_w,
        "gamma": gamma,
        "M": M,
        "delta": delta,
    }
    got = radii(**p)
    for g, e in zip((got.H_A, got.H_B, got.r_A, got.r_B), ref_H(**p), strict=True):
        assert np.shape(g) == ()
        assert math.isclose(float(g), e, rel_tol=1e-12)


def test_radii_vectorise_over_gamma_and_n():
    gam = np.array([0.0, 0.005, 0.01, 0.05, 0.1])
    Ns = np.arange(10, 460, 10)[:, None]
    got = radii(N=Ns, N0=10 * Ns, gamma=gam, **PAPER)
    assert got.H_A.shape == got.r_B.shape == (45, 5)
    for i, N in enumerate(Ns[:, 0]):
        for k, g in enumerate(gam):
            ref = ref_H(N=int(N), N0=10 * int(N), gamma=float(g), **PAPER)
            got_ik = (got.H_A[i, k], got.H_B[i, k], got.r_A[i, k], got.r_B[i, k])
            np.testing.assert_allclose(got_ik, ref, rtol=1e-13)


def test_radii_scaling_and_validation():
    # for fixed N (fixed theta) H ~ 1/sqrt(N0): four times the samples halves it
    a = radii(N=20, N0=100, gamma=0.05, **PAPER)
    b = radii(N=20, N0=400, gamma=0.05, **PAPER)
    np.testing.assert_allclose([b.H_A, b.H_B], [a.H_A / 2, a.H_B / 2], rtol=1e-14)
    # gamma = 0 (ols): r = sqrt(H)
    o = radii(N=20, N0=200, gamma=0.0, **PAPER)
    np.testing.assert_allclose(o.r_A, np.sqrt(o.H_A), rtol=1e-15)
    for bad in ({"delta": 1.0}, {"delta": 0.0}, {"N0": 0}, {"gamma": -0.1}, {"sigma_u": 0.0}):
        kw = {**PAPER, "N": 20, "N0": 200, "gamma": 0.05, **bad}
        with pytest.raises(ValueError):
            radii(**kw)


def _radii(H_A, H_B, r_A, r_B):
    return Radii(*(np.asarray(v, dtype=float) for v in (H_A, H_B, r_A, r_B)))


@settings(max_examples=60, deadline=None)
@given(
    seed=st.integers(0, 2**32 - 1),
    n=st.integers(1, 5),
    m=st.integers(1, 3),
    gamma=fl(0, 2),
    rA=fl(0, 1),
    rB=fl(0, 1),
)
def test_eps_and_rho_match_independent_computation(seed, n, m, gamma, rA, rB):
    rng = np.random.default_rng(seed)
    At = rng.uniform(-1, 1, (4, n, n))
    Bt = rng.uniform(-2, 2, (4, n, m))
    res = evaluate_bounds(At, Bt, gamma, _radii(0.1, 0.1, rA, rB))
    for b in range(4):
        eA = math.sqrt(
            sum((abs(gamma * At[b, i, j]) + rA) ** 2 for i in range(n) for j in range(n))
        )
        eB = math.sqrt(
            sum((abs(gamma * Bt[b, i, j]) + rB) ** 2 for i in range(n) for j in range(m))
        )  # Decision: j <= m
        assert math.isclose(res.eps_A[b], eA, rel_tol=1e-12)
        assert math.isclose(res.eps_B[b], eB, rel_tol=1e-12)
        box = np.abs((1 + gamma) * At[b]) + rA
        rho = max(abs(scipy.linalg.eigvals(box)))
        assert math.isclose(res.rho_upper_bound[b], rho, rel_tol=1e-10, abs_tol=1e-14)
        if rA > 0:  # positive matrix: power iteration converges to the Perron root
            v = np.ones(n)
            for _ in range(500):
                w = box @ v
                v = w / np.linalg.norm(w)
            assert math.isclose(res.rho_upper_bound[b], v @ box @ v, rel_tol=1e-8)
        assert res.stable_certified[b] == (rho < 1)
    assert res.coverage_A is None and res.thm1_holds_B is None


def test_rho_upper_bound_is_sound_and_tight():
    rng = np.random.default_rng(11)
    n, gamma, rA = 3, 0.05, 0.02
    At = rng.uniform(-0.6, 0.6, (n, n))
    res = evaluate_bounds(At, np.zeros((n, 1)), gamma, _radii(0, 0, rA, 0))
    c = (1 + gamma) * At
    boxes = c + rng.uniform(-rA, rA, (20000, n, n))
    signs = rng.choice([-1.0, 1.0], (2000, n, n))
    vertices = c + rA * signs
    rho_in_box = np.abs(np.linalg.eigvals(np.concatenate([boxes, vertices]))).max(axis=-1)
    assert rho_in_box.max() <= res.rho_upper_bound * (1 + 1e-12)
    # the sign-matched vertex sign(c)(|c| + r) has rho <= the bound; for c >= 0 it is equal
    pos = evaluate_bounds(np.abs(At), np.zeros((n, 1)), gamma, _radii(0, 0, rA, 0))
    top = np.abs(c) + rA
    assert math.isclose(pos.rho_upper_bound, max(abs(np.linalg.eigvals(top))), rel_tol=1e-12)
    assert math.isclose(pos.rho_upper_bound, res.rho_upper_bound, rel_tol=1e-12)


def test_stable_certified_by_hand():
    # c = (1 + 0.25) * 0.2 I = 0.25 I; |c| + r 11^T = [[a, r], [r, a]] has rho = a + r
    for sign in (1.0, -1.0):
        At = sign * 0.2 * np.eye(2)
        res = evaluate_bounds(
            np.stack([At, At]), np.zeros((2, 2, 1)), 0.25, _radii(0, 0, np.array([0.1, 0.4]), 0)
        )
        np.testing.assert_allclose(res.rho_upper_bound, [0.45, 1.05], rtol=1e-14)
        assert res.stable_certified.tolist() == [True, False]


def test_coverage_by_hand():
    gamma = 0.5  # centre (1 + gamma) * 0.5 = 0.75, radius 0.25: interval [0.5, 1.0]
    At = np.full((2, 2), 0.5)
    Bt = np.array([[1.0], [-1.0]])  # centres 1.5, -1.5, radius 0.25
    r = _radii(1.0, 1.0, 0.25, 0.25)
    res = evaluate_bounds(
        At,
        Bt,
        gamma,
        r,
        A_true=np.array([[1.0, 0.5], [1.25, 0.0]]),
        B_true=np.array([[1.5], [1.5]]),
    )
    assert res.coverage_A == 0.5  # both ends are inside (closed interval), 1.25 and 0 are not
    assert res.coverage_B == 0.5
    # never clipped: all outside -> 0, all inside -> 1
    res = evaluate_bounds(At, Bt, gamma, r, A_true=np.full((2, 2), 2.0), B_true=Bt * 1.5)
    assert res.coverage_A == 0.0 and res.coverage_B == 1.0
    # ols (gamma = 0): the interval is centred at the estimate itself
    res = evaluate_bounds(At, Bt, 0.0, r, A_true=np.array([[0.75, 0.25], [0.8, 0.2]]), B_true=Bt)
    assert res.coverage_A == 0.5 and res.coverage_B == 1.0


def test_thm1_by_hand():
    gamma = 1.0
    At = np.eye(2)
    # row 0: gamma*At_0 - (A_0 - At_0) = 0; row 1: [0, 1] - [-0.3, 0.6] = [0.3, 0.4],
    # norm 0.5, divided by (1 + gamma): 0.25
    A_true = np.array([[2.0, 0.0], [-0.3, 1.6]])
    Bt = np.array([[1.0], [2.0]])
    B_true = np.array([[2.0], [3.5]])  # row 0: 1 - (2 - 1) = 0; row 1: 2 - (3.5 - 2) = 0.5 -> 0.25
    for H, expect in ((0.26, True), (0.25, True), (0.24, False)):
        res = evaluate_bounds(At, Bt, gamma, _radii(H, H, 1.0, 1.0), A_true=A_true, B_true=B_true)
        assert bool(res.thm1_holds_A) is expect and bool(res.thm1_holds_B) is expect
    # a violation in the first row alone also fails the check
    res = evaluate_bounds(
        At,
        Bt,
        gamma,
        _radii(0.26, 0.26, 1, 1),
        A_true=A_true + np.array([[0.6, 0.0], [0.0, 0.0]]),
        B_true=B_true,
    )
    assert not res.thm1_holds_A
    # ols: ||Delta A_i|| <= H
    res = evaluate_bounds(
        At,
        Bt,
        0.0,
        _radii(0.5, 0.5, 1, 1),
        A_true=At + np.array([[0.3, 0.4], [0.0, 0.5]]),
        B_true=Bt + np.array([[0.5], [-0.5001]]),
    )
    assert res.thm1_holds_A and not res.thm1_holds_B


def test_batched_bounds_equal_slices_bit_for_bit():
    rng = np.random.default_rng(12)
    gam = np.array([0.005, 0.01, 0.05, 0.1])
    H = np.array([0.002, 0.01, 0.05, 0.2])
    r = Radii(H, 2 * H, np.sqrt((1 + gam) * H), np.sqrt((1 + gam) * 2 * H))
    A_true = 0.5 * np.array([[0.9, 0.01, 0], [0.01, 0.9, 0.01], [0, 0.01, 0.9]])
    B_true = np.array([[1.0], [1.5], [2.0]])
    noise = 0.03 * np.arange(5)[:, None, None, None]  # repetition b has noise 0.03 b
    At = A_true / (1 + gam[:, None, None]) + noise * rng.standard_normal((5, 4, 3, 3))
    Bt = B_true / (1 + gam[:, None, None]) + noise * rng.standard_normal((5, 4, 3, 1))
    full = evaluate_bounds(At, Bt, gam, r, A_true=A_true, B_true=B_true)
    fields = (
        "eps_A",
        "eps_B",
        "rho_upper_bound",
        "stable_certified",
        "coverage_A",
        "coverage_B",
        "thm1_holds_A",
        "thm1_holds_B",
    )
    for name in fields:
        assert getattr(full, name).shape == (5, 4), name
    for b in range(5):
        for k in range(4):
            rk = Radii(r.H_A[k], r.H_B[k], r.r_A[k], r.r_B[k])
            one = evaluate_bounds(At[b, k], Bt[b, k], gam[k], rk, A_true=A_true, B_true=B_true)
            for name in fields:
                assert np.array_equal(getattr(one, name), getattr(full, name)[b, k]), name
    # the data were drawn so that every check has both outcomes somewhere (they can fail)
    for name in ("stable_certified", "thm1_holds_A", "thm1_holds_B"):
        assert getattr(full, name).any() and not getattr(full, name).all(), name
    for name in ("coverage_A", "coverage_B"):
        assert getattr(full, name).min() < 1 == getattr(full, name).max(), name
