"""Multi-rollout data collection and seeding (SPEC section 1).

Every random draw comes from ``Generator(PCG64(SeedSequence(seed,
spawn_key=key)))`` with ``key = (system index, sigma_w index, N, rep)``:
estimators and gammas never enter the key, so they all see the same data,
and a repetition's numbers do not depend on how the grid is batched.
"""

from __future__ import annotations

import numpy as np

DATA_STREAM = ()      # the data generator uses the key itself
MC_STREAM = (1,)      # Monte Carlo cost noise: key + (1,), shared by all estimators


def seed_key(system_idx: int, sigma_w_idx: int, N: int, rep: int) -> tuple[int, int, int, int]:
    return (int(system_idx), int(sigma_w_idx), int(N), int(rep))


def rng_for(seed: int, key: tuple, stream: tuple = DATA_STREAM) -> np.random.Generator:
    """The generator of one (key, stream); SPEC section 1 Decision (randomness)."""
    return np.random.Generator(np.random.PCG64(np.random.SeedSequence(seed, spawn_key=key + stream)))


def draw_noise(seed, keys, *, N, T0, n, m, sigma_u, sigma_w, x0_std=0.0):
    """Draw (x0, u, w) for every key; order per key: x0 (if x0_std > 0), u, w.

    Returns x0 (R, N, n), u (R, N, T0, m), w (R, N, T0, n). The Python loop
    here is one generator call per repetition (the seeding contract needs a
    generator per key); all arithmetic is vectorised.
    """
    R = len(keys)
    x0 = np.zeros((R, N, n))
    u = np.empty((R, N, T0, m))
    w = np.empty((R, N, T0, n))
    for i, key in enumerate(keys):
        g = rng_for(seed, key)
        if x0_std > 0:
            x0[i] = g.standard_normal((N, n)) * x0_std
        u[i] = g.standard_normal((N, T0, m)) * sigma_u
        w[i] = g.standard_normal((N, T0, n)) * sigma_w
    return x0, u, w


def simulate(A, B, x0, u, w) -> np.ndarray:
    """x_{k+1} = A x_k + B u_k + w_k for all rollouts at once -> x (R, N, T0+1, n).

    Written as elementwise multiply-adds (no BLAS), so every rollout's
    numbers are the same to the bit whatever the batch size.
    """
    R, N, T0, m = u.shape
    n = A.shape[0]
    x = np.empty((T0 + 1, R, N, n))
    x[0] = x0
    ut = np.moveaxis(u, 2, 0)
    wt = np.moveaxis(w, 2, 0)
    for k in range(T0):
        xn = wt[k].copy()
        for j in range(n):
            xn += x[k, ..., j, None] * A[:, j]
        for j in range(m):
            xn += ut[k, ..., j, None] * B[:, j]
        x[k + 1] = xn
    return np.moveaxis(x, 0, 2)


def regression_data(x, u, data: str = "all"):
    """Stack regressors Z = [x_k; u_k] (R, n+m, N0) and targets F = x_{k+1} (R, n, N0).

    ``data="all"``: k = 1..T0-1 of every rollout, N0 = (T0-1) N;
    ``data="final"``: k = T0-1 only, N0 = N. Columns are rollout-major.
    """
    T0 = u.shape[2]
    ks = slice(1, T0) if data == "all" else slice(T0 - 1, T0)
    xs = x[:, :, ks]            # (R, N, K, n)
    us = u[:, :, ks]            # (R, N, K, m)
    xn = x[:, :, ks.start + 1 : ks.stop + 1]
    R = x.shape[0]
    Z = np.concatenate([xs, us], axis=-1).reshape(R, -1, xs.shape[-1] + us.shape[-1])
    F = xn.reshape(R, -1, xn.shape[-1])
    return np.ascontiguousarray(Z.transpose(0, 2, 1)), np.ascontiguousarray(F.transpose(0, 2, 1))


def collect(system, sigma_w, N, T0, seed, keys, data="all", x0_std=0.0):
    """Simulate the rollouts of every key and return (Z, F); SPEC section 1."""
    x0, u, w = draw_noise(
        seed, keys, N=N, T0=T0, n=system.n, m=system.m,
        sigma_u=system.sigma_u, sigma_w=sigma_w, x0_std=x0_std,
    )
    x = simulate(system.A, system.B, x0, u, w)
    return regression_data(x, u, data)
