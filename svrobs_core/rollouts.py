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
    """Draw (x0, u, w) for every key, in the layout the simulation uses.

    Order of draws per key (the reproducibility contract): x0 of shape
    (n, N) if x0_std > 0, then u of shape (m, T0, N), then w of shape
    (n, T0, N), each one ``standard_normal`` call scaled by its sigma.
    Returns x0 (R, n, N), u (R, m, T0, N), w (R, n, T0, N). The Python loop
    is one generator per repetition (the seeding contract needs a generator
    per key); all arithmetic is vectorised.
    """
    R = len(keys)
    x0 = np.zeros((R, n, N))
    u = np.empty((R, m, T0, N))
    w = np.empty((R, n, T0, N))
    for i, key in enumerate(keys):
        g = rng_for(seed, key)
        if x0_std > 0:
            g.standard_normal(out=x0[i])
        g.standard_normal(out=u[i])
        g.standard_normal(out=w[i])
    if x0_std > 0:
        x0 *= x0_std
    u *= sigma_u
    w *= sigma_w
    return x0, u, w


def simulate(A, B, x0, u, w) -> np.ndarray:
    """x_{k+1} = A x_k + B u_k + w_k for all rollouts at once -> x (R, n, T0+1, N).

    Written as elementwise multiply-adds (no BLAS), so every rollout's
    numbers are the same to the bit whatever the batch size.
    """
    R, m, T0, N = u.shape
    n = A.shape[0]
    x = np.empty((R, n, T0 + 1, N))
    x[:, :, 0] = x0
    for k in range(T0):
        xn = w[:, :, k].copy()
        for j in range(n):
            xn += A[None, :, j, None] * x[:, j, None, k]
        for j in range(m):
            xn += B[None, :, j, None] * u[:, j, None, k]
        x[:, :, k + 1] = xn
    return x


def regression_data(x, u, data: str = "all"):
    """Regressors Z = [x_k; u_k] (R, n+m, N0) and targets F = x_{k+1} (R, n, N0).

    ``data="all"``: k = 1..T0-1 of every rollout, N0 = (T0-1) N;
    ``data="final"``: k = T0-1 only, N0 = N. Columns are time-major
    (all rollouts at k = 1, then k = 2, ...).
    """
    R, n, _, N = x.shape
    T0 = u.shape[2]
    k0 = 1 if data == "all" else T0 - 1
    K = T0 - k0
    Z = np.concatenate([x[:, :, k0:T0], u[:, :, k0:T0]], axis=1).reshape(R, -1, K * N)
    F = np.ascontiguousarray(x[:, :, k0 + 1 : T0 + 1]).reshape(R, n, K * N)
    return Z, F


def collect(system, sigma_w, N, T0, seed, keys, data="all", x0_std=0.0):
    """Simulate the rollouts of every key and return (Z, F); SPEC section 1."""
    x0, u, w = draw_noise(
        seed, keys, N=N, T0=T0, n=system.n, m=system.m,
        sigma_u=system.sigma_u, sigma_w=sigma_w, x0_std=x0_std,
    )
    x = simulate(system.A, system.B, x0, u, w)
    return regression_data(x, u, data)
