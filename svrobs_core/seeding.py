"""Seeding: one random generator per (key, stream) (docs/science.md#14-randomness-and-reproducibility,
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

from .array_types import Array

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
