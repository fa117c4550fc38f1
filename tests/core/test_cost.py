"""Observer cost J (docs/science.md#6-observer-cost-j): exact finite horizon vs an independent
naive 2n covariance propagation and vs Monte Carlo; stationary vs scipy's
Lyapunov solver on the full augmented system and vs the long-horizon limit."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.linalg as sla

from svrobs_core.cost import exact_cost, optimal_cost, stationary_cost
from svrobs_core.cost_mc import mc_cost, mc_cost_shared
from svrobs_core.norms import REASON_UNSTABLE

A_S = np.array([[0.9, 0.01, 0.0], [0.01, 0.9, 0.01], [0.0, 0.01, 0.9]])
A_U = A_S + 0.11 * np.eye(3)  # 1.01 on the diagonal
B_P = np.array([[1.0], [1.5], [2.0]])
SU, SW, SV = 1.0, 1.0, 0.1
NOISE = dict(sigma_u=SU, sigma_w=SW, sigma_v=SV)
NOISE_W07 = dict(NOISE, sigma_w=0.7)


def kalman(A, C, sw, sv):
    n, p = A.shape[0], C.shape[0]
    P = sla.solve_discrete_are(A.T, C.T, sw**2 * np.eye(n), sv**2 * np.eye(p))
    return A @ P @ C.T @ np.linalg.inv(C @ P @ C.T + sv**2 * np.eye(p)), P


def augmented(A, B, At, Bt, L, C, su, sw, sv):
    """s = [x; e]: transition and input matrix (independent of the code under test)."""
    n, p = A.shape[0], C.shape[0]
    Acal = np.block([[A, np.zeros((n, n))], [-(A - At), At - L @ C]])
    Bcal = np.block(
        [[su * B, sw * np.eye(n), np.zeros((n, p))], [-su * (B - Bt), -sw * np.eye(n), sv * L]]
    )
    return Acal, Bcal


def naive_exact(A, B, At, Bt, L, C, su, sw, sv, T):
    n = A.shape[0]
    Acal, Bcal = augmented(A, B, At, Bt, L, C, su, sw, sv)
    S = np.zeros((2 * n, 2 * n))
    tot = 0.0
    for _ in range(T):
        S = Acal @ S @ Acal.T + Bcal @ Bcal.T
        tot += np.trace(S[n:, n:])
    return tot / T


def perturbed_cells(rng, A, B, C, K, count, dA=0.02, dB=0.05, dL=0.05):
    n, m, p = A.shape[0], B.shape[1], C.shape[0]
    At = A + dA * rng.standard_normal((count, n, n))
    Bt = B + dB * rng.standard_normal((count, n, m))
    L = K + dL * rng.standard_normal((count, n, p))
    return At, Bt, L


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


SYSTEMS = {
    "stable": (A_S, B_P, np.eye(3), 200),
    "unstable": (A_U, B_P, np.eye(3), 50),
    "partial": partial_system() + (200,),
}


# ------------------------------------------------------------- exact vs naive
@pytest.mark.parametrize("name", list(SYSTEMS))
def test_exact_equals_naive_propagation(name):
    A, B, C, T = SYSTEMS[name]
    K, _ = kalman(A, C, SW, SV)
    rng = np.random.default_rng(1)
    At, Bt, L = perturbed_cells(rng, A, B, C, K, 6)
    got = exact_cost(A, B, At, Bt, L=L, C=C, **NOISE, horizon=T)
    assert got.shape == (6,)
    for i in range(6):
        ref = naive_exact(A, B, At[i], Bt[i], L[i], C, SU, SW, SV, T)
        assert got[i] == pytest.approx(ref, rel=1e-10)


@pytest.mark.parametrize("T", [1, 2, 3, 5, 8, 13, 64, 100, 127, 255])
def test_exact_every_horizon(T):
    rng = np.random.default_rng(T)
    K, _ = kalman(A_S, np.eye(3), SW, SV)
    At, Bt, L = perturbed_cells(rng, A_S, B_P, np.eye(3), K, 2)
    got = exact_cost(A_S, B_P, At, Bt, L=L, C=np.eye(3), **NOISE, horizon=T)
    ref = [naive_exact(A_S, B_P, At[i], Bt[i], L[i], np.eye(3), SU, SW, SV, T) for i in range(2)]
    np.testing.assert_allclose(got, ref, rtol=1e-10)


def test_exact_batch_broadcasting_and_per_cell_sigmas():
    rng = np.random.default_rng(2)
    K, _ = kalman(A_S, np.eye(3), SW, SV)
    At, Bt, L = perturbed_cells(rng, A_S, B_P, np.eye(3), K, 6)
    At, Bt, L = At.reshape(2, 3, 3, 3), Bt.reshape(2, 3, 3, 1), L.reshape(2, 3, 3, 3)
    sw = np.array([[0.1], [1.0]])  # (2, 1) broadcasts over cells
    got = exact_cost(
        A_S, B_P, At, Bt, L=L, C=np.eye(3), sigma_u=SU, sigma_w=sw, sigma_v=SV, horizon=37
    )
    assert got.shape == (2, 3)
    for i in range(2):
        for j in range(3):
            ref = naive_exact(
                A_S, B_P, At[i, j], Bt[i, j], L[i, j], np.eye(3), SU, sw[i, 0], SV, 37
            )
            assert got[i, j] == pytest.approx(ref, rel=1e-10)
    one = exact_cost(
        A_S,
        B_P,
        At[1, 2],
        Bt[1, 2],
        L=L[1, 2],
        C=np.eye(3),
        sigma_u=SU,
        sigma_w=1.0,
        sigma_v=SV,
        horizon=37,
    )
    assert one.shape == () and float(one) == pytest.approx(got[1, 2], rel=1e-13)


def test_exact_large_state_uses_matmul_layout():
    rng = np.random.default_rng(3)
    n, m, p = 14, 2, 5
    A = rng.standard_normal((n, n))
    A *= 0.9 / np.abs(np.linalg.eigvals(A)).max()
    B, C = rng.standard_normal((n, m)), rng.standard_normal((p, n))
    K, _ = kalman(A, C, SW, SV)
    At, Bt, L = perturbed_cells(rng, A, B, C, K, 3, dA=0.01, dB=0.01, dL=0.01)
    got = exact_cost(A, B, At, Bt, L=L, C=C, **NOISE, horizon=45)
    for i in range(3):
        assert got[i] == pytest.approx(
            naive_exact(A, B, At[i], Bt[i], L[i], C, SU, SW, SV, 45), rel=1e-10
        )


def test_optimal_cost_is_kalman_predictor_error():
    """J* (A~=A, B~=B, L=K): e is the Kalman predictor error, whose stationary
    covariance is the DARE solution P (an oracle independent of the code)."""
    for A, B, C, _ in (SYSTEMS["stable"], SYSTEMS["partial"], SYSTEMS["unstable"]):
        K, P = kalman(A, C, SW, SV)
        Jstar = optimal_cost(A, B, K, C, **NOISE, horizon=200)
        assert float(Jstar) == pytest.approx(
            naive_exact(A, B, A, B, K, C, SU, SW, SV, 200), rel=1e-10
        )
        if np.abs(np.linalg.eigvals(A)).max() < 1:
            st = stationary_cost(A, B, A, B, L=K, C=C, **NOISE)
            assert float(st) == pytest.approx(np.trace(P), rel=1e-9)
        # long horizon -> trace P, also for the unstable A (the error is decoupled;
        # T stays moderate so that the x block, ~1.024^(2T), does not overflow)
        assert float(optimal_cost(A, B, K, C, **NOISE, horizon=4096)) == pytest.approx(
            np.trace(P), rel=1e-3
        )


# ------------------------------------------------------------- stationary
@pytest.mark.parametrize("name", ["stable", "partial"])
def test_stationary_equals_scipy_augmented_lyapunov(name):
    A, B, C, _ = SYSTEMS[name]
    n = A.shape[0]
    K, _ = kalman(A, C, SW, SV)
    rng = np.random.default_rng(4)
    At, Bt, L = perturbed_cells(rng, A, B, C, K, 5)
    got, why = stationary_cost(A, B, At, Bt, L=L, C=C, **NOISE, return_reason=True)
    assert list(why) == [None] * 5
    for i in range(5):
        Acal, Bcal = augmented(A, B, At[i], Bt[i], L[i], C, SU, SW, SV)
        X = sla.solve_discrete_lyapunov(Acal, Bcal @ Bcal.T)
        assert got[i] == pytest.approx(np.trace(X[n:, n:]), rel=1e-9)


def test_stationary_is_long_horizon_limit():
    K, _ = kalman(A_S, np.eye(3), SW, SV)
    rng = np.random.default_rng(5)
    At, Bt, L = perturbed_cells(rng, A_S, B_P, np.eye(3), K, 4)
    st = stationary_cost(A_S, B_P, At, Bt, L=L, C=np.eye(3), **NOISE)
    gaps = [
        np.abs(exact_cost(A_S, B_P, At, Bt, L=L, C=np.eye(3), **NOISE, horizon=T) / st - 1).max()
        for T in (10**3, 10**4, 10**6)
    ]
    assert gaps[0] > gaps[1] > gaps[2] and gaps[2] < 1e-5
    # the finite-horizon transient decays like 1/T
    assert gaps[1] == pytest.approx(gaps[0] / 10, rel=0.05)


def test_stationary_unstable_is_nan_with_reason():
    K, _ = kalman(A_U, np.eye(3), SW, SV)
    rng = np.random.default_rng(6)
    At, Bt, L = perturbed_cells(rng, A_U, B_P, np.eye(3), K, 3)
    val, why = stationary_cost(A_U, B_P, At, Bt, L=L, C=np.eye(3), **NOISE, return_reason=True)
    assert np.isnan(val).all() and list(why) == [REASON_UNSTABLE] * 3
    # stable A but unstable observer F = A~ - L C
    Ks, _ = kalman(A_S, np.eye(3), SW, SV)
    L = np.stack([Ks, Ks - 1.2 * np.eye(3)])  # F = A~ - L ~ 1.2 I + ...
    val, why = stationary_cost(A_S, B_P, A_S, B_P, L=L, C=np.eye(3), **NOISE, return_reason=True)
    assert np.isfinite(val[0]) and np.isnan(val[1])
    assert list(why) == [None, REASON_UNSTABLE]
    one, w1 = stationary_cost(A_S, B_P, A_S, B_P, L=L[1], C=np.eye(3), **NOISE, return_reason=True)
    assert np.isnan(one) and w1 == REASON_UNSTABLE
    # the exact finite-horizon cost stays defined
    assert np.isfinite(
        exact_cost(A_U, B_P, At, Bt, L=L[:1], C=np.eye(3), **NOISE, horizon=50)
    ).all()


# ------------------------------------------------------------- Monte Carlo
@pytest.mark.parametrize("name", list(SYSTEMS))
def test_exact_within_4_se_of_monte_carlo(name):
    A, B, C, T = SYSTEMS[name]
    K, _ = kalman(A, C, SW, SV)
    rng = np.random.default_rng(7)
    At, Bt, L = perturbed_cells(rng, A, B, C, K, 2)
    J = exact_cost(A, B, At, Bt, L=L, C=C, **NOISE, horizon=T)
    for i in range(2):
        mean, se = mc_cost(
            A,
            B,
            At[i],
            Bt[i],
            L=L[i],
            C=C,
            **NOISE,
            horizon=T,
            rng=np.random.default_rng(100 + i),
            runs=1500,
        )
        assert mean.shape == () and se > 0
        assert abs(mean - J[i]) < 4 * se, (name, i, mean, se, J[i])


def test_monte_carlo_batch_of_cells():
    K, _ = kalman(A_S, np.eye(3), SW, SV)
    rng = np.random.default_rng(8)
    At, Bt, L = perturbed_cells(rng, A_S, B_P, np.eye(3), K, 3)
    kw = dict(L=L, C=np.eye(3), **NOISE, horizon=60)
    J = exact_cost(A_S, B_P, At, Bt, **kw)
    mean, se = mc_cost(A_S, B_P, At, Bt, **kw, rng=np.random.default_rng(9), runs=800)
    assert mean.shape == se.shape == (3,)
    assert (np.abs(mean - J) < 4 * se).all()


def test_monte_carlo_documented_draw_order():
    """A plain re-implementation of the documented draw order (one
    standard_normal((runs, m+n+p)) per step: u, w, v) with the plant and the
    observer written out gives the same numbers."""
    A, B, C = partial_system()
    n, m, p = 4, 2, 2
    K, _ = kalman(A, C, SW, SV)
    At, Bt, L = perturbed_cells(np.random.default_rng(10), A, B, C, K, 1)
    At, Bt, L = At[0], Bt[0], L[0]
    T, runs = 23, 7
    mean, se = mc_cost(
        A, B, At, Bt, L=L, C=C, **NOISE_W07, horizon=T, rng=np.random.default_rng(11), runs=runs
    )
    rng = np.random.default_rng(11)
    x = np.zeros((runs, n))
    xt = np.zeros((runs, n))
    acc = np.zeros(runs)
    for _ in range(T):
        z = rng.standard_normal((runs, m + n + p))
        u, w, v = SU * z[:, :m], 0.7 * z[:, m : m + n], SV * z[:, m + n :]
        y = x @ C.T + v
        xt = xt @ At.T + u @ Bt.T + (y - xt @ C.T) @ L.T
        x = x @ A.T + u @ B.T + w
        acc += np.sum((xt - x) ** 2, axis=1)
    per_run = acc / T
    assert float(mean) == pytest.approx(per_run.mean(), rel=1e-12)
    assert float(se) == pytest.approx(per_run.std(ddof=1) / np.sqrt(runs), rel=1e-10)


@pytest.mark.parametrize("name", list(SYSTEMS))
def test_shared_noise_monte_carlo_equals_one_cell_at_a_time(name):
    """mc_cost_shared on an (R, E) grid = mc_cost per cell with row r's generator
    (same documented draws; the cells of a row share them)."""
    A, B, C = SYSTEMS[name][:3]
    K, _ = kalman(A, C, SW, SV)
    R, E, T, runs = 3, 4, 37, 50
    At, Bt, L = perturbed_cells(np.random.default_rng(12), A, B, C, K, R * E)
    n, m, p = A.shape[0], B.shape[1], C.shape[0]
    At, Bt, L = At.reshape(R, E, n, n), Bt.reshape(R, E, n, m), L.reshape(R, E, n, p)
    mean, se = mc_cost_shared(
        A,
        B,
        At,
        Bt,
        L=L,
        C=C,
        **NOISE_W07,
        horizon=T,
        rngs=[np.random.default_rng(40 + r) for r in range(R)],
        runs=runs,
    )
    assert mean.shape == se.shape == (R, E)
    for r in range(R):
        for e in range(E):
            m1, s1 = mc_cost(
                A,
                B,
                At[r, e],
                Bt[r, e],
                L=L[r, e],
                C=C,
                **NOISE_W07,
                horizon=T,
                rng=np.random.default_rng(40 + r),
                runs=runs,
            )
            assert mean[r, e] == pytest.approx(float(m1), rel=1e-10)
            assert se[r, e] == pytest.approx(float(s1), rel=1e-8)


def test_shared_noise_monte_carlo_does_not_depend_on_the_other_cells():
    """A cell's numbers are the same to the bit whichever other cells (estimators,
    gammas, repetitions) are computed with it."""
    K, _ = kalman(A_S, np.eye(3), SW, SV)
    At, Bt, L = perturbed_cells(np.random.default_rng(16), A_S, B_P, np.eye(3), K, 12)
    At, Bt, L = At.reshape(3, 4, 3, 3), Bt.reshape(3, 4, 3, 1), L.reshape(3, 4, 3, 3)
    T, runs = 45, 64

    def rngs(rows):
        return [np.random.default_rng(50 + r) for r in rows]

    full = mc_cost_shared(
        A_S, B_P, At, Bt, L=L, C=np.eye(3), **NOISE, horizon=T, rngs=rngs(range(3)), runs=runs
    )
    part = mc_cost_shared(
        A_S,
        B_P,
        At[1:, 2:3],
        Bt[1:, 2:3],
        L=L[1:, 2:3],
        C=np.eye(3),
        **NOISE,
        horizon=T,
        rngs=rngs([1, 2]),
        runs=runs,
    )
    for a, b in zip(full, part):
        assert np.array_equal(a[1:, 2:3], b)


def test_shared_noise_monte_carlo_agrees_with_exact():
    K, _ = kalman(A_S, np.eye(3), SW, SV)
    At, Bt, L = perturbed_cells(np.random.default_rng(13), A_S, B_P, np.eye(3), K, 4)
    At, Bt, L = At.reshape(2, 2, 3, 3), Bt.reshape(2, 2, 3, 1), L.reshape(2, 2, 3, 3)
    kw = dict(L=L, C=np.eye(3), **NOISE, horizon=60)
    J = exact_cost(A_S, B_P, At, Bt, **kw)
    rngs = [np.random.default_rng(14), np.random.default_rng(15)]
    mean, se = mc_cost_shared(A_S, B_P, At, Bt, **kw, rngs=rngs, runs=1500)
    assert (np.abs(mean - J) < 4 * se).all()
    with pytest.raises(ValueError):
        mc_cost_shared(
            A_S,
            B_P,
            At,
            Bt,
            L=L,
            C=np.eye(3),
            **NOISE,
            horizon=60,
            rngs=[np.random.default_rng(14)],
            runs=100,
        )


def test_bad_arguments():
    with pytest.raises(ValueError):
        exact_cost(A_S, B_P, A_S, B_P, L=np.eye(2), C=np.eye(3), **NOISE)
    with pytest.raises(ValueError):
        exact_cost(A_S, B_P, A_S, B_P, L=np.eye(3), C=np.eye(3), **NOISE, horizon=0)
    with pytest.raises(ValueError):
        mc_cost(
            A_S,
            B_P,
            A_S,
            B_P,
            L=np.eye(3),
            C=np.eye(3),
            **NOISE,
            horizon=10,
            rng=np.random.default_rng(0),
            runs=1,
        )
