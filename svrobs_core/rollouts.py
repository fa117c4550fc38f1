"""Multi-rollout data collection (docs/science.md#1-system-and-data).

Every draw comes from the generator of its seed key (:mod:`svrobs_core.seeding`),
so a repetition's numbers do not depend on how the grid is batched.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence

import numpy as np
from numpy.typing import ArrayLike

from .array_types import Array, FloatArray, IntArray
from .seeding import DEFAULT_RNG, generators
from .systems import SystemSpec
from .wishart_draws import DEFAULT_DRAWS, filler


# ---------------------------------------------------------------------------
# draws, simulation, regression data
# ---------------------------------------------------------------------------
def draw_noise(
    seed: int,
    keys: Sequence[tuple[int, ...]],
    *,
    N: int,
    T0: int,
    n: int,
    m: int,
    sigma_u: float,
    sigma_w: float,
    x0_std: float = 0.0,
    rng: str = DEFAULT_RNG,
) -> tuple[FloatArray, FloatArray, FloatArray]:
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
    for i, g in enumerate(generators(seed, keys, rng=rng)):
        if x0_std > 0:
            g.standard_normal(out=x0[i])
        g.standard_normal(out=u[i])
        g.standard_normal(out=w[i])
    if x0_std > 0:
        x0 *= x0_std
    u *= sigma_u
    w *= sigma_w
    return x0, u, w


def simulate(A: Array, B: Array, *, x0: Array, u: Array, w: Array) -> FloatArray:
    """x_{k+1} = A x_k + B u_k + w_k for all rollouts at once -> x (R, n, T0+1, N).

    A plain reference (elementwise multiply-adds); the runner simulates in
    :func:`gram_data` (same draws, BLAS products, equal to ~1e-15).
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


def sample_count(N: int, T0: int, data: str = "all") -> int:
    """N0 of a dataset of N rollouts: (T0-1) N for ``data="all"``, N for ``"final"``
    (docs/science.md#13-regression-data-the-two-data-modes)."""
    return (T0 - 1) * N if data == "all" else N


def regression_data(x: Array, u: Array, data: str = "all") -> tuple[FloatArray, FloatArray]:
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


def collect(
    system: SystemSpec,
    sigma_w: float,
    N: int,
    T0: int,
    *,
    seed: int,
    keys: Sequence[tuple[int, ...]],
    data: str = "all",
    x0_std: float = 0.0,
    rng: str = DEFAULT_RNG,
) -> tuple[FloatArray | None, FloatArray | None]:
    """Simulate the rollouts of every key and return (Z, F); docs/science.md#1-system-and-data.

    The same numbers as the experiment runner uses (it calls :func:`gram_data`)."""
    _, _, Z, F = gram_data(
        system,
        sigma_w,
        N,
        T0,
        seed=seed,
        keys=keys,
        data=data,
        x0_std=x0_std,
        keep_data=True,
        rng=rng,
    )
    return Z, F


def _draw(g: np.random.Generator, x0b: FloatArray, draw: FloatArray, x0_std: float) -> bool:
    """One key's draws in the documented order: x0 into ``x0b`` if x0_std > 0
    (-> True), then u and w into ``draw`` (m+n, T0, N)."""
    if x0_std > 0:
        g.standard_normal(out=x0b)
    g.standard_normal(out=draw)
    return x0_std > 0


# Working-set size of one chunk of repetitions in :func:`gram_data` (cache-sized).
CHUNK_BYTES = 2 * 2**20


def gram_data(
    system: SystemSpec,
    sigma_w: float,
    N: int,
    T0: int,
    *,
    seed: int,
    keys: Sequence[tuple[int, ...]],
    data: str = "all",
    x0_std: float = 0.0,
    keep_data: bool = False,
    rng: str = DEFAULT_RNG,
    draws: str = DEFAULT_DRAWS,
) -> tuple[FloatArray, FloatArray, FloatArray | None, FloatArray | None]:
    """Sufficient statistics of every key's regression data, without forming Z.

    Draws in the documented order (:func:`draw_noise`; u and w of a key come
    from one ``standard_normal`` call of shape (m+n, T0, N), which is the same
    stream as the two calls), then simulates in cache-sized chunks of
    repetitions. Layout of one repetition: a block
    ``Y (2n+m, T0+1, N)`` with rows ``[x_k; u_k; w_k]`` (u, w use the slots
    k < T0), so ``[x_k; u_k; w_k]`` for one k is a matrix with a row stride
    and a step is one small matrix product per repetition,
    ``x_{k+1} = [A B I] [x_k; u_k; w_k]`` (stacked matmul: every repetition
    is its own BLAS call of the same shape, so its bits do not depend on the
    batch). Returns ``(G, P, Z, F)``: ``G = Z Z^T`` (R, d, d) and
    ``P = F Z^T`` (R, n, d), computed by BLAS directly on strided views
    (``Z`` = rows x, u of the time slices k0..T0-1, ``F`` = rows x of
    k0+1..T0: no copy); ``Z, F`` as :func:`regression_data` lays them out
    when ``keep_data`` (else None).

    With ``draws="wishart"`` and N above the noise dimension q, each key's
    N rollouts are q pseudo-rollouts whose statistics have their law
    (:class:`svrobs_core.wishart_draws.WishartDraw`,
    docs/science.md#15-wishart-draws): Z and F then have K q columns, and the
    sample count is still K N.
    """
    n, m = system.n, system.m
    d = n + m
    q = d + n
    M = np.concatenate([system.A, system.B, np.eye(n)], axis=1)  # (n, 2n+m)
    R = len(keys)
    k0 = 1 if data == "all" else T0 - 1
    K = T0 - k0
    N, fill = filler(N, _draw, n=n, m=m, T0=T0, x0_std=x0_std, draws=draws)  # simulated columns
    G = np.empty((R, d, d))
    P = np.empty((R, n, d))
    Z = np.empty((R, d, K * N)) if keep_data else None
    F = np.empty((R, n, K * N)) if keep_data else None
    per_rep = 8 * N * (q * (T0 + 1) + d * T0)
    c = int(max(1, min(R, CHUNK_BYTES // per_rep)))
    Y = np.zeros((c, q, T0 + 1, N))
    draw = np.empty((m + n, T0, N))  # u then w of one key: one contiguous stream block
    x0b = np.empty((n, N))
    gens = generators(seed, keys, rng=rng)
    for s in range(0, R, c):
        e = min(R, s + c)
        h = e - s
        for i in range(h):
            if fill(next(gens), x0b, draw, x0_std):
                np.multiply(x0b, x0_std, out=Y[i, :n, 0])
            Y[i, n:, :T0] = draw
        Yh = Y[:h]
        Yh[:, n:d, :T0] *= system.sigma_u
        Yh[:, d:, :T0] *= sigma_w
        Zv = Yh[:, :d, k0:T0].reshape(h, d, K * N)  # views, row stride (T0+1) N
        Fv = Yh[:, :n, k0 + 1 : T0 + 1].reshape(h, n, K * N)
        Zt = np.swapaxes(Zv, -1, -2)
        # an unstable system may leave the double range: inf / NaN data, noted downstream
        with np.errstate(over="ignore", invalid="ignore"):
            for k in range(T0):
                np.matmul(M, Yh[:, :, k], out=Yh[:, :n, k + 1])
            np.matmul(Zv, Zt, out=G[s:e])
            np.matmul(Fv, Zt, out=P[s:e])
        if keep_data:
            assert Z is not None and F is not None
            Z[s:e] = Zv
            F[s:e] = Fv
    return G, P, Z, F


def resampled_grams(
    seed: int,
    keys: Sequence[tuple[int, ...]],
    systems: ArrayLike,
    owner: ArrayLike,
    *,
    sigma_u: float,
    N: int,
    T0: int,
    data: str = "all",
    x0_std: float = 0.0,
    rng: str = DEFAULT_RNG,
    draws: str = DEFAULT_DRAWS,
    chunk_bytes: int = CHUNK_BYTES,
) -> Iterator[tuple[IntArray, FloatArray, FloatArray, FloatArray, FloatArray]]:
    """Datasets of several systems on shared noise, as sufficient statistics, by chunks.

    Dataset i draws from ``keys[i]`` in the documented order (:func:`draw_noise`:
    x0 if ``x0_std > 0``, then u and w of shape (m+n, T0, N) as one stream) and
    drives each of the E systems ``systems[owner[i], e] = [A_e B_e s_e I]``
    (n, 2n+m) with it: ``x_{k+1} = A_e x_k + B_e sigma_u u_k + s_e w_k``, u, w
    standard normal. Layout and arithmetic are those of :func:`gram_data`
    (one stacked BLAS product per step, every (dataset, system) its own call of
    the same shape, so a dataset's bits do not depend on the chunk).

    With ``draws="wishart"`` and N above the noise dimension q, a dataset's
    N rollouts are replaced by the q pseudo-rollouts of :class:`svrobs_core.wishart_draws.WishartDraw`:
    G and W have the same joint law, at q instead of N columns
    (docs/uncertainty.md#how-the-resamples-are-drawn).

    Yields ``(idx, G, W, Z, F)`` per chunk of datasets ``idx``: ``G = Z Z^T``
    (h, E, d, d), ``W = sum_k w_k z_k^T`` (h, E, n, d) over the regression
    columns (so that ``F Z^T = [A_e B_e] G + s_e W``) and the regression data
    ``Z`` (h, E, d, K Nc), ``F`` (h, E, n, K Nc) of the Nc
    (:func:`dataset_columns`) simulated columns, as views into the chunk's
    buffer (valid until the next chunk is requested).
    """
    systems = np.asarray(systems, dtype=float)
    owner = np.asarray(owner, dtype=np.intp)
    E, n, q = systems.shape[1:]
    m = q - 2 * n
    d = n + m
    D = len(keys)
    k0 = 1 if data == "all" else T0 - 1
    K = T0 - k0
    Nc, fill = filler(N, _draw, n=n, m=m, T0=T0, x0_std=x0_std, draws=draws)
    per_set = 8 * Nc * (E * q * (T0 + 1) + 2 * E * d * d)
    c = int(max(1, min(D, chunk_bytes // per_set)))
    Y = np.zeros((c, E, q, T0 + 1, Nc))
    draw = np.empty((m + n, T0, Nc))
    x0b = np.empty((n, Nc))
    G = np.empty((c, E, d, d))
    W = np.empty((c, E, n, d))
    gens = generators(seed, keys, rng=rng)
    for s in range(0, D, c):
        e_ = min(D, s + c)
        h = e_ - s
        for i in range(h):
            if fill(next(gens), x0b, draw, x0_std):
                Y[i, :, :n, 0] = x0b * x0_std
            draw[:m] *= sigma_u
            Y[i, :, n:, :T0] = draw
        Yh = Y[:h]
        Mh = systems[owner[s:e_]]  # (h, E, n, q)
        Zv = Yh[:, :, :d, k0:T0].reshape(h, E, d, K * Nc)
        Fv = Yh[:, :, :n, k0 + 1 : T0 + 1].reshape(h, E, n, K * Nc)
        Wv = Yh[:, :, d:, k0:T0].reshape(h, E, n, K * Nc)
        Zt = np.swapaxes(Zv, -1, -2)
        with np.errstate(over="ignore", invalid="ignore"):
            for k in range(T0):
                np.matmul(Mh, Yh[:, :, :, k], out=Yh[:, :, :n, k + 1])
            np.matmul(Zv, Zt, out=G[:h])
            np.matmul(Wv, Zt, out=W[:h])
        yield np.arange(s, e_), G[:h], W[:h], Zv, Fv
