"""Rollouts stored back to back (docs/datasets.md#the-data-model): a few float64
blocks, each holding whole rollouts one after the other, and the row where each
rollout starts. A parsed file costs its numbers and 8 bytes a rollout, not an array
object a rollout: the view of one rollout is made when it is asked for
(``stack[i]``), and the checks, statistics and regressors of the parse run block by
block.

The statistics are those of a fold over the rollouts one by one (each rollout's sum,
then the running sum of those in rollout order), to the bit: the rollouts of one
length in a block are summed together along their rows, as numpy sums the rows of
one rollout's array.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable, Iterator, Sequence
from typing import overload

import numpy as np

# values of one gathered group of rollouts (their copy, and a temporary as large)
GROUP_VALUES = 1 << 18
# rollouts whose sums are folded, or lengths checked, at a time
FOLD_ROLLOUTS = 1 << 14


class RolloutStack(Sequence[np.ndarray]):
    """Rollout i is rows ``bounds[i] - less * i`` to ``bounds[i + 1] - less * (i + 1)``
    of the blocks put end to end (``less`` 1: the inputs of states stacked with
    ``bounds``, one row fewer a rollout, sharing them); block b holds rollouts
    ``first[b]:first[b + 1]``. Every block is a C-contiguous float64 array of
    ``width`` columns. Nothing writes to the blocks once stacked."""

    __slots__ = ("blocks", "bounds", "first", "width", "less")

    def __init__(
        self,
        blocks: list[np.ndarray],
        bounds: np.ndarray,
        first: np.ndarray,
        width: int,
        less: int = 0,
    ) -> None:
        self.blocks, self.bounds, self.first = blocks, bounds, first
        self.width, self.less = width, less
        if len(first) != len(blocks) + 1 or first[0] != 0 or first[-1] != len(bounds) - 1:
            raise ValueError("first does not count the rollouts of the blocks")
        rows = np.diff(self.bounds[first] - less * first)
        for b, block in enumerate(blocks):
            if block.shape != (rows[b], width):
                raise ValueError(f"block {b} of shape {block.shape} does not hold its rollouts")

    @classmethod
    def of_lengths(cls, blocks: list[np.ndarray], lengths, per_block, width: int) -> RolloutStack:
        """``lengths``: the rows of each rollout; ``per_block``: the rollouts of each block."""
        return cls(blocks, running(lengths), running(per_block), width)

    @classmethod
    def of_arrays(cls, arrays: Sequence[np.ndarray], width: int) -> RolloutStack:
        """One block per rollout: the arrays themselves (C-contiguous float64)."""
        return cls.of_lengths(list(arrays), [len(a) for a in arrays], [1] * len(arrays), width)

    @classmethod
    def of_equal(cls, block: np.ndarray, rollouts: int) -> RolloutStack:
        """``rollouts`` rollouts of equal length in one block."""
        rows, width = block.shape
        return cls.of_lengths([block], [rows // max(rollouts, 1)] * rollouts, [rollouts], width)

    def fewer_rows(self, blocks: list[np.ndarray], width: int) -> RolloutStack:
        """The stack of ``blocks`` holding one row fewer of each rollout than this one,
        block by block (the inputs of these states)."""
        return RolloutStack(blocks, self.bounds, self.first, width, less=1)

    def edges(self, lo: int, hi: int) -> np.ndarray:
        """The rows where rollouts ``lo..hi`` start (``hi``: where ``hi - 1`` ends)."""
        edges = self.bounds[lo : hi + 1]
        return edges - self.less * np.arange(lo, hi + 1) if self.less else edges

    def __len__(self) -> int:
        return len(self.bounds) - 1

    @overload
    def __getitem__(self, i: int) -> np.ndarray: ...

    @overload
    def __getitem__(self, i: slice) -> list[np.ndarray]: ...

    def __getitem__(self, i: int | slice) -> np.ndarray | list[np.ndarray]:
        if isinstance(i, slice):
            return [self[j] for j in range(*i.indices(len(self)))]
        count = len(self)
        if not -count <= i < count:
            raise IndexError(f"rollout {i} of {count}")
        i %= count
        b = int(np.searchsorted(self.first, i, side="right")) - 1
        row0 = self.edges(int(self.first[b]), int(self.first[b]))[0]
        start, stop = self.edges(i, i + 1) - row0
        return self.blocks[b][start:stop]

    def __iter__(self) -> Iterator[np.ndarray]:
        for b, block in enumerate(self.blocks):
            edges = self.edges(int(self.first[b]), int(self.first[b + 1]))
            for start, stop in itertools.pairwise((edges - edges[0]).tolist()):
                yield block[start:stop]

    def __add__(self, other: Sequence[np.ndarray]) -> list[np.ndarray]:
        return [*self, *other]

    @property
    def lengths(self) -> np.ndarray:
        """The rows of each rollout."""
        return np.diff(self.bounds) - self.less

    @property
    def rows(self) -> int:
        return int(self.bounds[-1]) - self.less * len(self)

    def groups(self) -> Iterator[tuple[np.ndarray, np.ndarray]]:
        """(rollout indices, their rows as one (k, length, width) array) for the
        rollouts of each length of each block, at most GROUP_VALUES values at a time
        (one rollout may be more): the rows of each rollout as an array of its own."""
        for b, block in enumerate(self.blocks):
            r0, r1 = int(self.first[b]), int(self.first[b + 1])
            edges = self.edges(r0, r1)
            starts, lengths = edges[:-1] - edges[0], np.diff(edges)
            for length in np.unique(lengths).tolist():
                idx = np.flatnonzero(lengths == length)
                step = max(GROUP_VALUES // max(length * self.width, 1), 1)
                for at in range(0, len(idx), step):
                    part = idx[at : at + step]
                    yield r0 + part, _rows(block, starts[part], length)


def first_misshapen(X: RolloutStack, U: RolloutStack) -> int | None:
    """The first rollout with fewer than 2 states, or inputs other than one row
    fewer than its states (None: none); FOLD_ROLLOUTS rollouts at a time."""
    for lo in range(0, len(X), FOLD_ROLLOUTS):
        hi = min(lo + FOLD_ROLLOUTS, len(X))
        states, inputs = np.diff(X.edges(lo, hi)), np.diff(U.edges(lo, hi))
        bad = np.flatnonzero((states < 2) | (inputs != states - 1))
        if len(bad):
            return lo + int(bad[0])
    return None


def running(counts) -> np.ndarray:
    """0 and the running sums of ``counts`` (int64)."""
    out = np.zeros(len(counts) + 1, dtype=np.int64)
    np.cumsum(np.asarray(counts, dtype=np.int64), out=out[1:])
    return out


def _rows(block: np.ndarray, starts: np.ndarray, length: int) -> np.ndarray:
    """Rows ``start:start + length`` of the block for each start, as (k, length,
    width): a view when they follow one another, else a copy."""
    first = int(starts[0])
    if (np.diff(starts) == length).all():
        return block[first : first + len(starts) * length].reshape(
            len(starts), length, block.shape[1]
        )
    return block[starts[:, None] + np.arange(length)]


def _fold(stack: RolloutStack, reduce: Callable[[np.ndarray], np.ndarray]) -> np.ndarray:
    """``total = zeros; total += reduce(rollout)`` over the rollouts in order, where
    ``reduce`` sums a group's rows (axis 1)."""
    each = np.empty((len(stack), stack.width))
    for idx, group in stack.groups():
        each[idx] = reduce(group)
    total = np.zeros(stack.width)
    for at in range(0, len(each), FOLD_ROLLOUTS):
        # the running sum is sequential: (total + each[at]) + each[at + 1] ...
        total = np.cumsum(np.vstack([total, each[at : at + FOLD_ROLLOUTS]]), axis=0)[-1]
    return total


def _extremes(stack: RolloutStack) -> tuple[np.ndarray, np.ndarray]:
    """(min, max) of each column over every rollout, as the fold ``lo =
    np.minimum(lo, x.min(axis=0))`` over the rollouts gives them: the values are
    the same in any order, the sign of a zero extreme is not (then the fold is run)."""
    lo, hi = np.full(stack.width, np.inf), np.full(stack.width, -np.inf)
    for block in stack.blocks:
        if len(block):
            lo, hi = np.minimum(lo, block.min(axis=0)), np.maximum(hi, block.max(axis=0))
    zero = (lo == 0) | (hi == 0)
    if zero.any() and _signed_zeros(stack, zero):
        lo, hi = np.full(stack.width, np.inf), np.full(stack.width, -np.inf)
        for x in stack:
            if len(x):
                lo, hi = np.minimum(lo, x.min(axis=0)), np.maximum(hi, x.max(axis=0))
    return lo, hi


def _signed_zeros(stack: RolloutStack, columns: np.ndarray) -> bool:
    """Whether one of ``columns`` holds both 0.0 and -0.0."""
    plus = np.zeros(int(columns.sum()), dtype=bool)
    minus = np.zeros_like(plus)
    for block in stack.blocks:
        values = block[:, columns]
        negative = np.signbit(values)
        plus |= ((values == 0) & ~negative).any(axis=0)
        minus |= ((values == 0) & negative).any(axis=0)
    return bool((plus & minus).any())


def channel_stats(stack: RolloutStack, names: list[str]) -> dict:
    """{name: {mean, std (ddof 0), min, max, count}} over every sample of every rollout
    (two passes: the sum, then the squared deviations about the mean), each channel
    divided by the power of two nearest its largest magnitude first: exact, so the
    same numbers as unscaled where those neither overflow (values near 1e308 summed)
    nor underflow (values near 1e-310 squared)."""
    width, count = stack.width, stack.rows
    if width == 0:
        return {}
    if count == 0:
        return {n: {"mean": None, "std": None, "min": None, "max": None, "count": 0} for n in names}
    with np.errstate(over="ignore", invalid="ignore", under="ignore"):
        lo, hi = _extremes(stack)
        top = np.maximum(np.abs(lo), np.abs(hi))
        usable = np.isfinite(top) & (top > 0)
        scale = np.where(usable, np.ldexp(1.0, np.frexp(np.where(usable, top, 1.0))[1] - 1), 1.0)
        mean_s = _fold(stack, lambda g: (g / scale).sum(axis=1)) / count
        dev = _fold(stack, lambda g: ((g / scale - mean_s) ** 2).sum(axis=1))
        mean, std = mean_s * scale, np.sqrt(dev / count) * scale
    return {
        name: {
            "mean": _finite(mean[j]),
            "std": _finite(std[j]),
            "min": _finite(lo[j]),
            "max": _finite(hi[j]),
            "count": int(count),
        }
        for j, name in enumerate(names)
    }


def _finite(v) -> float | None:
    """A statistic, or None when it overflows (values near 1e308 summed)."""
    v = float(v)
    return v if math.isfinite(v) else None


def first_not_finite(stack: RolloutStack) -> tuple[int, int, int] | None:
    """(rollout, row in it, column) of the first NaN or inf, in rollout and row order."""
    for b, block in enumerate(stack.blocks):
        ok = np.isfinite(block)
        if not ok.all():
            r, c = np.argwhere(~ok)[0]
            r0, r1 = int(stack.first[b]), int(stack.first[b + 1])
            edges = stack.edges(r0, r1) - stack.edges(r0, r0)[0]
            i = int(np.searchsorted(edges, r, side="right")) - 1
            return r0 + i, int(r - edges[i]), int(c)
    return None


def regressors(X: RolloutStack, U: RolloutStack) -> np.ndarray:
    """Z (n + m, transitions): ``[x_k; u_k]`` of every transition, rollout by rollout,
    as :func:`svrobs_core.measured.data.regression` makes it of the rollouts' arrays."""
    states = []
    for b, block in enumerate(X.blocks):
        r0, r1 = int(X.first[b]), int(X.first[b + 1])
        keep = np.ones(len(block), dtype=bool)
        keep[X.edges(r0, r1)[1:] - X.edges(r0, r0)[0] - 1] = False  # each last state
        states.append(block[keep])
    x0, u = np.concatenate(states), np.concatenate(U.blocks)
    return np.ascontiguousarray(np.concatenate([x0, u], axis=1).T)
