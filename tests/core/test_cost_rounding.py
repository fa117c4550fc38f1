"""The costs on strongly non-normal systems against mpmath at 50-60 digits
(docs/science.md#61-exact-finite-horizon-j_exact): a value is given only where it is right; where
rounding ruins it, it is null with its reason."""

from __future__ import annotations

import mpmath as mp
import numpy as np
import pytest

from svrobs_core import parse_spec, run_spec
from svrobs_core.cost import exact_cost, stationary_cost
from svrobs_core.cost_check import REASON_ROUNDING, suspect, unconfirmed
from svrobs_core.norms import stability_radius

# rho(A) = 0.99003, powers peaking near 1e8: every J_exact in doubles is garbage
NON_NORMAL = [
    [-4440.198116009997, -3941.6716137324065, 7341.86735388213],
    [-5402.890704806929, -2845.4082526097422, 5021.24263896199],
    [-5680.170002864558, -3992.621205889931, 7286.796368619739],
]
B_NN = [[-1.6796945788401643], [1.9504916026999646], [0.9166191525408893]]
NOISE = dict(sigma_u=1.0, sigma_w=1.0, sigma_v=0.1)


def system(rng: np.random.Generator, scale: float) -> np.ndarray:
    """Q T Q^T with eigenvalues 0.99, 0.6, -0.4 and off-diagonal entries of ``scale``."""
    T = np.triu(rng.standard_normal((3, 3)) * scale, 1)
    T[np.diag_indices(3)] = [0.99, 0.6, -0.4]
    Q, _ = np.linalg.qr(rng.standard_normal((3, 3)))
    return Q @ T @ Q.T


def mp_matrices(A, B, At, Bt, L, C):
    """(Acal, Q) in mpmath, every difference and product formed there."""
    n = A.shape[0]
    m = mp.matrix
    F = m(At.tolist()) - m(L.tolist()) * m(C.tolist())
    dA = m(At.tolist()) - m(A.tolist())
    Acal = mp.zeros(2 * n)
    for i in range(n):
        for j in range(n):
            Acal[i, j], Acal[n + i, j], Acal[n + i, n + j] = A[i, j], dA[i, j], F[i, j]
    G = np.block(
        [
            [NOISE["sigma_u"] * B, NOISE["sigma_w"] * np.eye(n), np.zeros((n, C.shape[0]))],
            [-NOISE["sigma_u"] * (B - Bt), -NOISE["sigma_w"] * np.eye(n), NOISE["sigma_v"] * L],
        ]
    )
    Gm = mp.matrix(G.tolist())
    return Acal, Gm * Gm.T


def mp_exact(A, B, At, Bt, L, C, T=200) -> float:
    with mp.workdps(50):
        Acal, Q = mp_matrices(A, B, At, Bt, L, C)
        n, S, tot = A.shape[0], mp.zeros(2 * A.shape[0]), mp.mpf(0)
        for _ in range(T):
            S = Acal * S * Acal.T + Q
            tot += sum(S[n + i, n + i] for i in range(n))
        return float(tot / T)


def mp_stationary(A, B, At, Bt, L, C) -> float:
    with mp.workdps(60):
        Acal, Q = mp_matrices(A, B, At, Bt, L, C)
        k = Acal.rows
        K = mp.eye(k * k) - mp.matrix(
            [
                [Acal[i, a] * Acal[j, b] for a in range(k) for b in range(k)]
                for i in range(k)
                for j in range(k)
            ]
        )
        x = mp.lu_solve(K, mp.matrix([Q[i, j] for i in range(k) for j in range(k)]))
        n = A.shape[0]
        return float(sum(x[(n + i) * k + n + i] for i in range(n)))


def cells(rng, scale):
    A = system(rng, scale)
    B = rng.standard_normal((3, 1))
    At = A + 1e-4 * rng.standard_normal((3, 3))
    Bt = B + 1e-4 * rng.standard_normal((3, 1))
    return A, B, At, Bt, 0.05 * np.eye(3), np.eye(3)


@pytest.mark.parametrize("scale", [0.0, 1.0, 10.0, 100.0, 1000.0])
def test_each_cost_is_given_only_where_a_second_evaluation_confirms_it(scale):
    rng = np.random.default_rng(int(scale) + 11)
    for _ in range(2):
        A, B, At, Bt, L, C = cells(rng, scale)
        J, err = exact_cost(A, B, At, Bt, L=L, C=C, **NOISE, return_error=True)
        Js = stationary_cost(A, B, At, Bt, L=L, C=C, **NOISE)
        bad_J, bad_s = unconfirmed(
            A, B, At[None], Bt[None], L=L[None], C=C, **NOISE, horizon=200,
            J=np.atleast_1d(J), err=np.atleast_1d(err), J_stat=np.atleast_1d(Js),
        )  # fmt: skip
        truth = mp_exact(A, B, At, Bt, L, C)
        if np.isfinite(J) and not bad_J[0]:
            assert J == pytest.approx(truth, rel=1e-6), (scale, float(err))
        if np.isfinite(J) and not suspect(np.atleast_1d(J), np.atleast_1d(err))[0]:
            assert abs(J - truth) <= err  # the bound holds where it is not loose
        if np.isfinite(Js) and not bad_s[0]:
            assert Js == pytest.approx(mp_stationary(A, B, At, Bt, L, C), rel=1e-6), scale
        if scale >= 1000.0:  # every digit lost: dropped (or beyond the doubles)
            assert bad_J[0] or not np.isfinite(J)


def test_the_rounding_bound_flags_nothing_on_a_well_conditioned_system():
    rng = np.random.default_rng(5)
    A = np.array([[0.9, 0.2, 0.0], [0.0, 0.8, 0.1], [0.0, 0.0, 0.7]])
    B = np.ones((3, 1))
    At = A + 1e-2 * rng.standard_normal((50, 3, 3))
    Bt = B + 1e-2 * rng.standard_normal((50, 3, 1))
    J, err = exact_cost(A, B, At, Bt, L=0.3 * np.eye(3), C=np.eye(3), **NOISE, return_error=True)
    assert not suspect(J, err).any()
    assert np.all(err <= 1e-11 * J)


def test_records_of_a_system_whose_costs_rounding_ruins():
    """J_exact in doubles is 1.9e223 here and J_stationary's equation is singular to
    working precision; 50 digits give 5.2e6, which the Monte Carlo J confirms."""
    spec = parse_spec(
        {
            "systems": [{"name": "nn", "A": NON_NORMAL, "B": B_NN}],
            "sigma_w": [1.0],
            "N": [200],
            "reps": 1,
            "estimators": ["ols"],
            "bounds_method": "self-normalized",
            "stages": ["estimate", "bounds", "gain", "cost"],
            "mc_runs": 400,
        }
    )
    (r,) = [r for batch in run_spec(spec) for r in batch]
    assert r["J_exact"] is None and f"J_exact: {REASON_ROUNDING}" in r["notes"]
    assert r["J_stationary"] is None and "J_stationary: not computable in doubles" in r["notes"]
    A, B = np.array(NON_NORMAL), np.array(B_NN)
    At, Bt, L = (np.array(r[k]) for k in ("A_hat", "B_hat", "L"))
    truth = mp_exact(A, B, At, Bt, L, np.eye(3))
    assert abs(r["J_mc"] - truth) <= 5 * r["J_mc_se"]
    # J* (the true model, L = K): its e block never meets A's huge x block, so its
    # loose bound sends it to the step recursion, which confirms it
    K = np.array(r["K"])
    assert r["J_star"] == pytest.approx(mp_exact(A, B, A, B, K, np.eye(3)), rel=1e-8)


def _flags(A, B, At, Bt, L, C, **noise):
    J, err = exact_cost(A, B, At, Bt, L=L, C=C, **noise, return_error=True)
    Js = stationary_cost(A, B, At, Bt, L=L, C=C, **noise)
    rho = np.fmax(stability_radius(A), stability_radius(At - L @ C))
    bad_J, bad_s = unconfirmed(
        A, B, At[None], Bt[None], L=L[None], C=C, **noise, horizon=200,
        J=np.atleast_1d(J), err=np.atleast_1d(err), J_stat=np.atleast_1d(Js), rho=rho,
    )  # fmt: skip
    return float(J), float(Js), bad_J[0], bad_s[0]


def test_a_stationary_cost_near_the_boundary_is_evaluated_again():
    """F nearly defective at rho = 1 - 1e-7: J_exact is accurate (its bound is tight),
    but the stationary Stein solve is not (here even negative): it is evaluated
    again, and dropped."""
    A, B, At, C = np.diag([0.5, -0.2]), np.ones((2, 1)), np.zeros((2, 2)), np.eye(2)
    Q = np.array([[0.6, -0.8], [0.8, 0.6]])
    L = -(Q @ np.array([[1 - 1e-7, 0.03], [0, 1 - 1e-7]]) @ Q.T)
    noise = dict(sigma_u=1.0, sigma_w=1.0, sigma_v=0.1)
    J, Js, bad_J, bad_s = _flags(A, B, At, B, L, C, **noise)
    assert not bad_J and J == pytest.approx(mp_exact(A, B, At, B, L, C), rel=1e-8)
    assert bad_s  # the doubles gave -2.8e17; 60 digits give 8.2e17


@pytest.mark.parametrize("offset", [1e-13, 1e-10])
def test_the_second_evaluation_does_not_repeat_the_inputs_rounding(offset):
    """L cancels A_tilde nearly exactly through an ill-conditioned C: A_tilde - L C
    loses digits when formed in doubles, in the first evaluation and a second one in
    doubles alike. The second is in extended precision: it disagrees, and both
    values are dropped (they were 1.4e-3 and 2.3e-6 off)."""
    rng = np.random.default_rng(2)
    A, B = np.diag([0.9, 0.5]), np.array([[1.0], [0.5]])
    At = A + 1e-3 * rng.standard_normal((2, 2))
    C = np.array([[1, 0.7], [0.3, 0.21 + offset]])
    L = (At - np.array([[0.99, 0.05], [-0.05, 0.98]])) @ np.linalg.inv(C)
    noise = dict(sigma_u=1.0, sigma_w=1.0, sigma_v=1e-6)
    J, Js, bad_J, bad_s = _flags(A, B, At, B, L, C, **noise)
    truth = mp_exact(A, B, At, B, L, C)
    assert abs(J - truth) > 1e-8 * truth  # the doubles are off
    assert bad_J and bad_s
