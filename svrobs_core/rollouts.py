"""Multi-rollout data collection and seeding (docs/science.md#1-system-and-data,
docs/performance.md#generators).

Every random draw comes from ``Generator(BitGen(SeedSequence(seed,
spawn_key=key)))`` with ``key = (system index, sigma_w index, N, rep)``:
estimators and gammas never enter the key, so they all see the same data,
and a repetition's numbers do not depend on how the grid is batched.
``BitGen`` is the spec's ``rng`` (:data:`RNGS`): ``"pcg64"`` (the default,
numpy's PCG64) or ``"sfc64"`` (numpy's SFC64, about a fifth faster per
normal draw); the seeding and the order of draws are the same for both.

Speed. Building one such generator through numpy's Python-level
``SeedSequence`` costs ~45 us, which is a noticeable share of the paper
preset (~100,000 keys). :func:`generators` computes the same bit-generator
states for many keys at once (numpy's SeedSequence hash, vectorised over the
keys, then PCG64's seeding step in exact integer arithmetic or SFC64's
twelve warm-up rounds in uint64 arithmetic) and hands out one generator per
key by setting the state of a reused bit generator. The result is checked
against numpy's own construction at first use (and in the tests); on any
mismatch, e.g. a future numpy with a different seeding, the slow path is used.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from .array_types import Array, FloatArray, IntArray
from .systems import SystemSpec

DATA_STREAM = ()  # the data generator uses the key itself
MC_STREAM = (1,)  # Monte Carlo cost noise: key + (1,), shared by all estimators
DEFAULT_RNG = "pcg64"
# The spec's ``rng`` -> numpy bit generator. A name fixes the draws for good:
# a generator with other draws would get a new name.
RNGS: dict[str, type[np.random.BitGenerator]] = {"pcg64": np.random.PCG64, "sfc64": np.random.SFC64}


def seed_key(system_idx: int, sigma_w_idx: int, N: int, rep: int) -> tuple[int, int, int, int]:
    return (int(system_idx), int(sigma_w_idx), int(N), int(rep))


def _bit_generator(rng: str) -> type[np.random.BitGenerator]:
    try:
        return RNGS[rng]
    except KeyError:
        raise ValueError(f"rng must be one of {sorted(RNGS)}, got {rng!r}") from None


def rng_for(
    seed: int, key: tuple[int, ...], stream: tuple[int, ...] = DATA_STREAM, rng: str = DEFAULT_RNG
) -> np.random.Generator:
    """The generator of one (key, stream) (docs/science.md#14-randomness-and-reproducibility)."""
    return np.random.Generator(
        _bit_generator(rng)(np.random.SeedSequence(seed, spawn_key=key + stream))
    )


# ---------------------------------------------------------------------------
# vectorised SeedSequence -> PCG64 state (numpy's algorithm, numpy >= 1.19)
# ---------------------------------------------------------------------------
_M32 = 0xFFFFFFFF
_INIT_A, _MULT_A = 0x43B0D7E5, 0x931E8875
_INIT_B, _MULT_B = 0x8B51F9DD, 0x58F38DED
_MIX_L, _MIX_R = 0xCA01F9DD, 0x4973F715
_POOL = 4
_PCG_MULT = 0x2360ED051FC65DA44385DF649FCCF645
_M128 = (1 << 128) - 1


def _words(x: int) -> list[int]:
    """numpy's _int_to_uint32_array: little-endian 32-bit words, [0] for 0."""
    x = int(x)
    if x < 0:
        raise ValueError("seed and key entries must be >= 0")
    if x == 0:
        return [0]
    out = []
    while x > 0:
        out.append(x & _M32)
        x >>= 32
    return out


class _Hash:
    """The running hash constant of SeedSequence.mix_entropy (same for every key)."""

    def __init__(self) -> None:
        self.c = _INIT_A

    def mix(self, value: Array) -> Array:
        value = value ^ np.uint32(self.c)
        self.c = (self.c * _MULT_A) & _M32
        value = value * np.uint32(self.c)
        return value ^ (value >> np.uint32(16))


def _mix(x: Array, y: Array) -> Array:
    r: Array = np.uint32(_MIX_L) * x - np.uint32(_MIX_R) * y
    mixed: Array = r ^ (r >> np.uint32(16))
    return mixed


def _pools(entropy: Array) -> Array:
    """SeedSequence pools for entropy arrays (K, L) uint32 -> (K, 4) uint32."""
    K, L = entropy.shape
    h = _Hash()
    zero = np.zeros(K, dtype=np.uint32)
    mixer = [h.mix(entropy[:, i] if i < L else zero) for i in range(_POOL)]
    for i_src in range(_POOL):
        for i_dst in range(_POOL):
            if i_src != i_dst:
                mixer[i_dst] = _mix(mixer[i_dst], h.mix(mixer[i_src]))
    for i_src in range(_POOL, L):
        for i_dst in range(_POOL):
            mixer[i_dst] = _mix(mixer[i_dst], h.mix(entropy[:, i_src]))
    return np.stack(mixer, axis=1)


def _state_words(pools: Array, n64: int) -> Array:
    """SeedSequence.generate_state(n64, uint64) of each pool -> (K, n64) uint64."""
    c = _INIT_B
    words = []
    for i in range(2 * n64):
        v = pools[:, i % _POOL] ^ np.uint32(c)
        c = (c * _MULT_B) & _M32
        v = v * np.uint32(c)
        words.append(v ^ (v >> np.uint32(16)))
    return np.stack(words, axis=1).astype("<u4").view("<u8").astype(np.uint64)


def _pcg64_states(pools: Array) -> list[tuple[int, int]]:
    """generate_state(4, uint64) of each pool, then PCG64's srandom -> [(state, inc)]."""
    w = _state_words(pools, 4)  # (K, 4)
    out = []
    for s_hi, s_lo, i_hi, i_lo in w.tolist():
        initstate = (s_hi << 64) | s_lo
        inc = ((((i_hi << 64) | i_lo) << 1) | 1) & _M128
        state = inc  # step from 0: 0 * mult + inc
        state = (state + initstate) & _M128
        state = (state * _PCG_MULT + inc) & _M128
        out.append((state, inc))
    return out


def _sfc64_states(pools: Array) -> Array:
    """generate_state(3, uint64) of each pool, then SFC64's seeding (counter 1,
    twelve rounds) -> (K, 4) uint64 states [a, b, c, counter]."""
    w = _state_words(pools, 3)
    a, b, c = (np.ascontiguousarray(w[:, i]) for i in range(3))
    d = np.ones_like(a)
    s11, s3, s24, s40 = (np.uint64(v) for v in (11, 3, 24, 40))
    for _ in range(12):
        tmp = a + b + d
        d = d + np.uint64(1)
        a = b ^ (b >> s11)
        b = c + (c << s3)
        c = ((c << s24) | (c >> s40)) + tmp
    return np.stack([a, b, c, d], axis=1)


_STATES: dict[str, Callable[[Array], Any]] = {"pcg64": _pcg64_states, "sfc64": _sfc64_states}


def _fast_states(seed: int, keys: Sequence[tuple[int, ...]], rng: str = DEFAULT_RNG) -> list[Any]:
    """The bit-generator state of every key (PCG64: (state, inc); SFC64: uint64 (4,))."""
    states = _STATES[rng]
    run = _words(seed)
    if len(run) < _POOL:
        run = run + [0] * (_POOL - len(run))
    arr = np.asarray(keys, dtype=object)
    if arr.ndim == 2 and all(0 <= int(v) <= 0xFFFFFFFF for v in (arr.min(), arr.max())):
        # every key entry is one 32-bit word: the entropy arrays are the keys themselves
        ent_arr = np.empty((len(keys), len(run) + arr.shape[1]), dtype=np.uint32)
        ent_arr[:, : len(run)] = run
        ent_arr[:, len(run) :] = np.asarray(keys, dtype=np.int64)
        with np.errstate(over="ignore"):
            return list(states(_pools(ent_arr)))
    ent = [run + [w for k in key for w in _words(k)] for key in keys]
    out: list[Any] = [None] * len(ent)
    by_len: dict[int, list[int]] = {}
    for i, e in enumerate(ent):
        by_len.setdefault(len(e), []).append(i)
    for idx in by_len.values():
        arr = np.array([ent[i] for i in idx], dtype=np.uint32)
        with np.errstate(over="ignore"):
            for i, st in zip(idx, states(_pools(arr))):
                out[i] = st
    return out


def _state_dict(rng: str, st: Any) -> dict[str, Any]:
    if rng == "pcg64":
        return {
            "bit_generator": "PCG64",
            "state": {"state": st[0], "inc": st[1]},
            "has_uint32": 0,
            "uinteger": 0,
        }
    return {"bit_generator": "SFC64", "state": {"state": st}, "has_uint32": 0, "uinteger": 0}


_FAST_OK: dict[str, bool] = {}


def _fast_ok(rng: str = DEFAULT_RNG) -> bool:
    """True when the vectorised seeding reproduces numpy's SeedSequence here."""
    if rng not in _FAST_OK:
        bitgen = _bit_generator(rng)
        try:
            probe = [(0, 1, 450, 3), (1, 0, 10, 999, 1), (2**40, 7)]
            for seed in (0, 12345, 2**63 - 1):
                for key, st in zip(probe, _fast_states(seed, probe, rng)):
                    ref = bitgen(np.random.SeedSequence(seed, spawn_key=key))
                    mine = bitgen(0)
                    mine.state = _state_dict(rng, st)
                    if ref.random_raw(3).tolist() != mine.random_raw(3).tolist():
                        raise ValueError("mismatch")
            _FAST_OK[rng] = True
        except Exception:  # noqa: BLE001  # pragma: no cover - a numpy with another seeding
            _FAST_OK[rng] = False
    return _FAST_OK[rng]


def generators(
    seed: int,
    keys: Sequence[tuple[int, ...]],
    stream: tuple[int, ...] = DATA_STREAM,
    *,
    fresh: bool = False,
    rng: str = DEFAULT_RNG,
) -> Iterator[np.random.Generator]:
    """Yield the generator of each key (the same streams as :func:`rng_for`), fast.

    By default one bit generator is reused and re-seeded per key, so a
    yielded generator is only valid until the next one is requested (draw
    from it, then move on); ``fresh=True`` gives independent generators.
    """
    bitgen = _bit_generator(rng)
    keys = [tuple(int(v) for v in k) + tuple(stream) for k in keys]
    if not keys:
        return
    if not _fast_ok(rng):
        for k in keys:
            yield np.random.Generator(bitgen(np.random.SeedSequence(seed, spawn_key=k)))
        return
    bg: Any = None
    gen: Any = None
    for st in _fast_states(seed, keys, rng):
        if fresh or bg is None:
            bg = bitgen(0)
            gen = np.random.Generator(bg)
        bg.state = _state_dict(rng, st)
        yield gen


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
    """
    n, m = system.n, system.m
    d = n + m
    q = d + n
    M = np.concatenate([system.A, system.B, np.eye(n)], axis=1)  # (n, 2n+m)
    R = len(keys)
    k0 = 1 if data == "all" else T0 - 1
    K = T0 - k0
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
            if _draw(next(gens), x0b, draw, x0_std):
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

    Yields ``(idx, G, W, Z, F)`` per chunk of datasets ``idx``: ``G = Z Z^T``
    (h, E, d, d), ``W = sum_k w_k z_k^T`` (h, E, n, d) over the regression
    columns (so that ``F Z^T = [A_e B_e] G + s_e W``) and the regression data
    ``Z`` (h, E, d, K N), ``F`` (h, E, n, K N) as views into the chunk's buffer
    (valid until the next chunk is requested).
    """
    systems = np.asarray(systems, dtype=float)
    owner = np.asarray(owner, dtype=np.intp)
    E, n, q = systems.shape[1:]
    m = q - 2 * n
    d = n + m
    D = len(keys)
    k0 = 1 if data == "all" else T0 - 1
    K = T0 - k0
    per_set = 8 * N * (E * q * (T0 + 1) + 2 * E * d * d)
    c = int(max(1, min(D, chunk_bytes // per_set)))
    Y = np.zeros((c, E, q, T0 + 1, N))
    draw = np.empty((m + n, T0, N))
    x0b = np.empty((n, N))
    G = np.empty((c, E, d, d))
    W = np.empty((c, E, n, d))
    gens = generators(seed, keys, rng=rng)
    for s in range(0, D, c):
        e_ = min(D, s + c)
        h = e_ - s
        for i in range(h):
            if _draw(next(gens), x0b, draw, x0_std):
                Y[i, :, :n, 0] = x0b * x0_std
            draw[:m] *= sigma_u
            Y[i, :, n:, :T0] = draw
        Yh = Y[:h]
        Mh = systems[owner[s:e_]]  # (h, E, n, q)
        Zv = Yh[:, :, :d, k0:T0].reshape(h, E, d, K * N)
        Fv = Yh[:, :, :n, k0 + 1 : T0 + 1].reshape(h, E, n, K * N)
        Wv = Yh[:, :, d:, k0:T0].reshape(h, E, n, K * N)
        Zt = np.swapaxes(Zv, -1, -2)
        with np.errstate(over="ignore", invalid="ignore"):
            for k in range(T0):
                np.matmul(Mh, Yh[:, :, :, k], out=Yh[:, :, :n, k + 1])
            np.matmul(Zv, Zt, out=G[:h])
            np.matmul(Wv, Zt, out=W[:h])
        yield np.arange(s, e_), G[:h], W[:h], Zv, Fv
