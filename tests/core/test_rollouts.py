"""Multi-rollout collection and seeding (SPEC section 1) against a naive simulator."""

import numpy as np

from svrobs_core.rollouts import collect, rng_for, seed_key
from svrobs_core.systems import resolve_system

S = resolve_system("paper-stable")


def naive(system, sigma_w, N, T0, seed, key, data, x0_std=0.0):
    """One rollout at a time, one step at a time, drawing in the documented order."""
    g = np.random.Generator(np.random.PCG64(np.random.SeedSequence(seed, spawn_key=key)))
    n, m = system.n, system.m
    x0 = g.standard_normal((n, N)) * x0_std if x0_std > 0 else np.zeros((n, N))
    u = g.standard_normal((m, T0, N)) * system.sigma_u
    w = g.standard_normal((n, T0, N)) * sigma_w
    traj = []
    for i in range(N):
        x = [x0[:, i]]
        for k in range(T0):
            x.append(system.A @ x[k] + system.B @ u[:, k, i] + w[:, k, i])
        traj.append(x)
    ks = range(1, T0) if data == "all" else [T0 - 1]
    Zc = [np.concatenate([traj[i][k], u[:, k, i]]) for k in ks for i in range(N)]
    Fc = [traj[i][k + 1] for k in ks for i in range(N)]
    return np.array(Zc).T, np.array(Fc).T


def test_all_data_matches_naive_simulation_and_sample_count():
    key = seed_key(0, 1, 7, 3)
    Z, F = collect(S, 1.0, 7, 11, 42, [key], "all")
    Zn, Fn = naive(S, 1.0, 7, 11, 42, key, "all")
    assert Z.shape == (1, 4, 70) and F.shape == (1, 3, 70)  # N0 = (T0-1) N
    np.testing.assert_allclose(Z[0], Zn, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(F[0], Fn, rtol=1e-12, atol=1e-12)


def test_final_data_and_random_initial_state():
    key = seed_key(1, 0, 5, 0)
    Z, F = collect(S, 0.1, 5, 6, 7, [key], "final", x0_std=2.0)
    Zn, Fn = naive(S, 0.1, 5, 6, 7, key, "final", x0_std=2.0)
    assert Z.shape == (1, 4, 5)
    np.testing.assert_allclose(Z[0], Zn, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(F[0], Fn, rtol=1e-12, atol=1e-12)


def test_batching_does_not_change_a_repetitions_numbers():
    keys = [seed_key(0, 0, 20, r) for r in range(6)]
    Z, F = collect(S, 1.0, 20, 11, 5, keys)
    for r in (0, 3, 5):
        Z1, F1 = collect(S, 1.0, 20, 11, 5, [keys[r]])
        assert np.array_equal(Z1[0], Z[r]) and np.array_equal(F1[0], F[r])


def test_keys_and_seeds_give_distinct_streams():
    a = rng_for(0, seed_key(0, 0, 10, 0)).standard_normal(4)
    assert not np.array_equal(a, rng_for(1, seed_key(0, 0, 10, 0)).standard_normal(4))
    assert not np.array_equal(a, rng_for(0, seed_key(0, 0, 10, 1)).standard_normal(4))
    assert not np.array_equal(a, rng_for(0, seed_key(0, 0, 10, 0), (1,)).standard_normal(4))
    assert np.array_equal(a, rng_for(0, seed_key(0, 0, 10, 0)).standard_normal(4))
