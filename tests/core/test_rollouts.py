"""Multi-rollout collection and seeding (docs/science.md#1-system-and-data) against
a naive simulator."""

import numpy as np

from svrobs_core.rollouts import collect, gram_data
from svrobs_core.seeding import MC_STREAM, generators, rng_for, seed_key
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
    Z, F = collect(S, 1.0, 7, 11, seed=42, keys=[key], data="all")
    Zn, Fn = naive(S, 1.0, 7, 11, 42, key, "all")
    assert Z.shape == (1, 4, 70) and F.shape == (1, 3, 70)  # N0 = (T0-1) N
    np.testing.assert_allclose(Z[0], Zn, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(F[0], Fn, rtol=1e-12, atol=1e-12)


def test_final_data_and_random_initial_state():
    key = seed_key(1, 0, 5, 0)
    Z, F = collect(S, 0.1, 5, 6, seed=7, keys=[key], data="final", x0_std=2.0)
    Zn, Fn = naive(S, 0.1, 5, 6, 7, key, "final", x0_std=2.0)
    assert Z.shape == (1, 4, 5)
    np.testing.assert_allclose(Z[0], Zn, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(F[0], Fn, rtol=1e-12, atol=1e-12)


def test_batching_does_not_change_a_repetitions_numbers():
    keys = [seed_key(0, 0, 20, r) for r in range(6)]
    Z, F = collect(S, 1.0, 20, 11, seed=5, keys=keys)
    for r in (0, 3, 5):
        Z1, F1 = collect(S, 1.0, 20, 11, seed=5, keys=[keys[r]])
        assert np.array_equal(Z1[0], Z[r]) and np.array_equal(F1[0], F[r])


def test_keys_and_seeds_give_distinct_streams():
    a = rng_for(0, seed_key(0, 0, 10, 0)).standard_normal(4)
    assert not np.array_equal(a, rng_for(1, seed_key(0, 0, 10, 0)).standard_normal(4))
    assert not np.array_equal(a, rng_for(0, seed_key(0, 0, 10, 1)).standard_normal(4))
    assert not np.array_equal(a, rng_for(0, seed_key(0, 0, 10, 0), (1,)).standard_normal(4))
    assert np.array_equal(a, rng_for(0, seed_key(0, 0, 10, 0)).standard_normal(4))


def test_fast_generators_are_numpys_seedsequence_streams():
    """The vectorised SeedSequence -> PCG64 seeding gives numpy's own streams."""
    keys = [
        seed_key(s, w, N, r)
        for s in (0, 1)
        for w in (0, 2)
        for N in (10, 450)
        for r in (0, 1, 999, 2**32 + 5)
    ]
    for seed in (0, 7, 2**32 + 1, 2**63 - 1):
        for stream in ((), MC_STREAM):
            for fresh in (False, True):
                got = [g.standard_normal(3) for g in generators(seed, keys, stream, fresh=fresh)]
                for k, a in zip(keys, got):
                    ref = np.random.Generator(
                        np.random.PCG64(np.random.SeedSequence(seed, spawn_key=k + stream))
                    ).standard_normal(3)
                    assert np.array_equal(a, ref), (seed, k, stream)
    # fresh generators stay usable side by side
    gs = list(generators(3, keys[:3], fresh=True))
    firsts = [g.standard_normal() for g in gs]
    assert len(set(firsts)) == 3
    assert firsts[0] == rng_for(3, keys[0]).standard_normal()


def test_fast_sfc64_generators_are_numpys_seedsequence_streams():
    """rng = "sfc64": the vectorised seeding gives numpy's SFC64(SeedSequence) streams."""
    keys = [seed_key(s, w, N, r) for s in (0, 1) for w in (0, 2) for N in (10, 450) for r in (0, 7)]
    keys.append((2**40, 3))  # a key entry of more than one 32-bit word: the per-key path
    for seed in (0, 2**63 - 1):
        for stream in ((), MC_STREAM, (2, 17)):
            got = [g.standard_normal(5) for g in generators(seed, keys, stream, rng="sfc64")]
            for k, a in zip(keys, got):
                ref = np.random.Generator(
                    np.random.SFC64(np.random.SeedSequence(seed, spawn_key=k + stream))
                ).standard_normal(5)
                assert np.array_equal(a, ref), (seed, k, stream)
                assert np.array_equal(a, rng_for(seed, k, stream, "sfc64").standard_normal(5))


def test_the_rng_choice_is_deterministic_and_changes_every_draw():
    keys = [seed_key(0, 0, 12, r) for r in range(3)]
    runs = {
        rng: [gram_data(S, 1.0, 12, 11, seed=4, keys=keys, keep_data=True, rng=rng) for _ in "ab"]
        for rng in ("pcg64", "sfc64")
    }
    for (G1, P1, Z1, F1), (G2, P2, Z2, F2) in runs.values():
        assert np.array_equal(Z1, Z2) and np.array_equal(F1, F2)
        assert np.array_equal(G1, G2) and np.array_equal(P1, P2)
    Zp, Zs = runs["pcg64"][0][2], runs["sfc64"][0][2]
    assert not np.isclose(Zp[:, :, 1:], Zs[:, :, 1:]).any()  # every simulated value differs
    Zn, _ = naive(S, 1.0, 12, 11, 4, keys[1], "all")
    np.testing.assert_allclose(Zp[1], Zn, rtol=1e-12, atol=1e-12)  # the default is PCG64


def test_gram_data_is_z_zt_and_f_zt_of_the_rollouts():
    for data, x0_std in (("all", 0.0), ("final", 1.5)):
        keys = [seed_key(1, 0, 13, r) for r in range(5)]
        G, P, Z, F = gram_data(
            S, 0.5, 13, 11, seed=9, keys=keys, data=data, x0_std=x0_std, keep_data=True
        )
        Zn, Fn = zip(*(naive(S, 0.5, 13, 11, 9, k, data, x0_std) for k in keys))
        np.testing.assert_allclose(Z, np.array(Zn), rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(F, np.array(Fn), rtol=1e-12, atol=1e-12)
        for r in range(5):
            np.testing.assert_allclose(G[r], Zn[r] @ Zn[r].T, rtol=1e-12)
            np.testing.assert_allclose(P[r], Fn[r] @ Zn[r].T, rtol=1e-12, atol=1e-12)
        # without the data: the same statistics, bit for bit; any batch gives the same bits
        G2, P2, Z2, F2 = gram_data(S, 0.5, 13, 11, seed=9, keys=keys, data=data, x0_std=x0_std)
        assert Z2 is None and F2 is None
        assert np.array_equal(G, G2) and np.array_equal(P, P2)
        G3, P3, _, _ = gram_data(S, 0.5, 13, 11, seed=9, keys=keys[3:4], data=data, x0_std=x0_std)
        assert np.array_equal(G3[0], G[3]) and np.array_equal(P3[0], P[3])


def test_gram_data_chunks_do_not_change_bits(monkeypatch):
    import svrobs_core.rollouts as ro

    keys = [seed_key(0, 1, 40, r) for r in range(9)]
    G, P, _, _ = gram_data(S, 1.0, 40, 11, seed=2, keys=keys)
    monkeypatch.setattr(ro, "CHUNK_BYTES", 1)  # one repetition per chunk
    G1, P1, _, _ = gram_data(S, 1.0, 40, 11, seed=2, keys=keys)
    assert np.array_equal(G, G1) and np.array_equal(P, P1)
