"""Measured rollouts, the ARX state built from them, and their regression data
(docs/measured.md#data-model, #arx).

A dataset arrives as ``X: list[(T_i + 1, n)]`` and ``U: list[(T_i, m)]``
float arrays (ragged lengths allowed, ``m = 0`` allowed). Regression samples
are every transition of every rollout, rollout by rollout:
``Z = [x_k; u_k]`` (d x N0), ``F = x_{k+1}`` (n x N0).
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..array_types import BoolArray, FloatArray, IntArray
from ..errors import DimensionError
from ..seeding import generators, seed_key
from .rollout_lists import RolloutLists

SUBSAMPLE_STREAM = (3,)  # repetition r >= 1 draws its rollouts from key (0, 0, N, r) + (3,)


@dataclass(frozen=True, eq=False)
class MeasuredData(RolloutLists):
    """Rollouts of measured states (or outputs) and inputs.

    X[i] (T_i + 1, n) and U[i] (T_i, m) float64, T_i >= 1; ``sample_time`` in
    seconds (None: unknown); ``state_names`` / ``input_names``: channel names
    (default x1..xn, u1..um).
    """

    X: list[FloatArray]
    U: list[FloatArray]
    sample_time: float | None = None
    state_names: tuple[str, ...] = field(default=())
    input_names: tuple[str, ...] = field(default=())

    def __post_init__(self) -> None:
        X = [np.asarray(x, dtype=float) for x in self.X]
        U = [np.asarray(u, dtype=float) for u in self.U]
        if not X or len(X) != len(U):
            raise DimensionError(
                "X",
                f"and U must hold the same number (>= 1) of rollouts, got {len(X)} and {len(U)}",
            )
        n, m = X[0].shape[-1] if X[0].ndim == 2 else -1, U[0].shape[-1] if U[0].ndim == 2 else -1
        for i, (x, u) in enumerate(zip(X, U)):
            if x.ndim != 2 or x.shape[1] != n or x.shape[0] < 2:
                raise DimensionError(f"X[{i}]", f"must be (T + 1, {n}) with T >= 1, got {x.shape}")
            if u.ndim != 2 or u.shape != (x.shape[0] - 1, m):
                raise DimensionError(f"U[{i}]", f"must be ({x.shape[0] - 1}, {m}), got {u.shape}")
            if not (np.isfinite(x).all() and np.isfinite(u).all()):
                raise DimensionError(f"X[{i}]", "and U hold NaN or inf")
        object.__setattr__(self, "X", X)
        object.__setattr__(self, "U", U)
        names = tuple(self.state_names) or tuple(f"x{j + 1}" for j in range(n))
        object.__setattr__(self, "state_names", names)
        object.__setattr__(
            self, "input_names", tuple(self.input_names) or tuple(f"u{j + 1}" for j in range(m))
        )

    @property
    def lengths(self) -> IntArray:
        """T_i: the transitions of each rollout."""
        return np.array([u.shape[0] for u in self.U], dtype=np.int64)

    def take(self, idx: Iterable[int]) -> MeasuredData:
        """The rollouts ``idx`` (in that order)."""
        idx = [int(i) for i in idx]
        return MeasuredData(
            X=[self.X[i] for i in idx],
            U=[self.U[i] for i in idx],
            sample_time=self.sample_time,
            state_names=self.state_names,
            input_names=self.input_names,
        )

    def split(self, holdout: int) -> tuple[MeasuredData, MeasuredData | None]:
        """(training pool, held-out rollouts): the last ``holdout`` rollouts are held out."""
        k = self.rollouts - int(holdout)
        if not 1 <= k <= self.rollouts:
            raise ValueError(f"holdout must be in [0, {self.rollouts - 1}], got {holdout}")
        rest = self.take(range(k, self.rollouts)) if holdout else None
        return self.take(range(k)), rest


@dataclass(frozen=True)
class StateModel:
    """How the model's state is made from the measured channels.

    ``lags`` None: the state is the measured x. (p, q): the ARX state
    ``[y_k .. y_{k-p+1}, u_{k-1} .. u_{k-q}]`` of ny outputs and m inputs;
    its first ny rows of [A B] are estimated, the others are known
    (``A0``, ``B0``, with ``estimated`` the mask of the estimated rows).
    """

    ny: int
    m: int
    lags: tuple[int, int] | None = None

    @property
    def n(self) -> int:
        if self.lags is None:
            return self.ny
        p, q = self.lags
        return p * self.ny + q * self.m

    @property
    def k0(self) -> int:
        """The first time index at which the state is complete."""
        if self.lags is None:
            return 0
        p, q = self.lags
        return max(p - 1, q)

    @property
    def estimated(self) -> BoolArray:
        """(n,) bool: the rows of [A B] that are estimated."""
        out = np.zeros(self.n, dtype=bool)
        out[: self.ny] = True
        return out

    def known_rows(self) -> tuple[FloatArray, FloatArray]:
        """(A0 (n, n), B0 (n, m)): the known rows (shifts, input injection), 0 on the y rows."""
        n, ny, m = self.n, self.ny, self.m
        A0, B0 = np.zeros((n, n)), np.zeros((n, m))
        if self.lags is None:
            return A0, B0
        p, q = self.lags
        for j in range(1, p):  # slot y_{k-j} of x_{k+1} copies slot y_{k-j+1} of x_k
            A0[j * ny : (j + 1) * ny, (j - 1) * ny : j * ny] = np.eye(ny)
        u0 = p * ny
        if q:
            B0[u0 : u0 + m] = np.eye(m)  # slot u_k of x_{k+1} is the input u_k
        for j in range(1, q):  # slot u_{k-j} copies slot u_{k-j+1}
            A0[u0 + j * m : u0 + (j + 1) * m, u0 + (j - 1) * m : u0 + j * m] = np.eye(m)
        return A0, B0

    def full(self, theta_rows: FloatArray) -> FloatArray:
        """The estimated rows (..., ny, n + m) -> the full [A B] (..., n, n + m)."""
        if self.lags is None:
            return theta_rows
        known = np.concatenate(self.known_rows(), axis=1)
        out = np.broadcast_to(known, theta_rows.shape[:-2] + known.shape).copy()
        out[..., : self.ny, :] = theta_rows
        return out

    def state_names(self, names: Sequence[str], inputs: Sequence[str]) -> tuple[str, ...]:
        if self.lags is None:
            return tuple(names)
        p, q = self.lags
        ys = [f"{y}[k-{j}]" if j else f"{y}[k]" for j in range(p) for y in names]
        us = [f"{u}[k-{j}]" for j in range(1, q + 1) for u in inputs]
        return tuple(ys + us)

    def lift(self, data: MeasuredData) -> MeasuredData:
        """The rollouts in the model's state: X_i (T_i - k0 + 1, n), U_i (T_i - k0, m)."""
        if self.lags is None:
            return data
        p, q = self.lags
        k0 = self.k0
        X: list[FloatArray] = []
        U: list[FloatArray] = []
        for y, u in zip(data.X, data.U):  # one slice per lag and rollout; arithmetic is copying
            T = u.shape[0]
            if T <= k0:
                raise DimensionError("X", f"a rollout has {T + 1} samples; the lags need {k0 + 2}")
            cols = [y[k0 - j : T + 1 - j] for j in range(p)]  # y_{k-j}, k = k0..T
            cols += [u[k0 - j : T + 1 - j] for j in range(1, q + 1)]  # u_{k-j}
            X.append(np.concatenate(cols, axis=1) if cols else np.zeros((T - k0 + 1, 0)))
            U.append(u[k0:])
        return MeasuredData(
            X=X,
            U=U,
            sample_time=data.sample_time,
            state_names=self.state_names(data.state_names, data.input_names),
            input_names=data.input_names,
        )


def regression(data: MeasuredData) -> tuple[FloatArray, FloatArray]:
    """(Z (d, N0), F (n, N0)) of every transition, rollout by rollout."""
    x0 = np.concatenate([x[:-1] for x in data.X], axis=0)
    x1 = np.concatenate([x[1:] for x in data.X], axis=0)
    u = np.concatenate(data.U, axis=0)
    return np.ascontiguousarray(np.concatenate([x0, u], axis=1).T), np.ascontiguousarray(x1.T)


def rep_rollouts(seed: int, N: int, reps: Sequence[int], pool: int) -> list[IntArray]:
    """The rollout indices of each repetition of one N (docs/measured.md#data-model).

    Repetition 0: the first N of the pool; r >= 1: N drawn without replacement
    by the generator of key (0, 0, N, r) + SUBSAMPLE_STREAM, sorted."""
    if N > pool:
        raise ValueError(f"N = {N} rollouts requested, the training pool has {pool}")
    out: list[Any] = [None] * len(reps)  # every entry an index array below
    drawn = [i for i, r in enumerate(reps) if r > 0]
    keys = [seed_key(0, 0, N, reps[i]) for i in drawn]
    for i, g in zip(drawn, generators(seed, keys, SUBSAMPLE_STREAM)):  # a generator per key
        out[i] = np.sort(g.choice(pool, size=N, replace=False))
    for i, r in enumerate(reps):
        if r == 0:
            out[i] = np.arange(N)
    return out


class Transitions:
    """The regression samples of a training pool, cut by rollout subsets at once.

    ``Z``, ``F`` of the whole pool (columns rollout by rollout); ``batch(subsets)``
    gives the stacked (Z, F) of subsets with equal sample counts, by one
    fancy-indexing gather (no loop over repetitions for the arithmetic).
    """

    def __init__(self, data: MeasuredData):
        self.Z, self.F = regression(data)
        self.lengths = data.lengths
        self.start = np.concatenate([[0], np.cumsum(self.lengths)[:-1]])

    def samples(self, idx: IntArray) -> int:
        return int(self.lengths[idx].sum())

    def columns(self, idx: IntArray) -> IntArray:
        """The sample columns of the rollouts idx, in order."""
        lens = self.lengths[idx]
        offsets = np.repeat(self.start[idx] - np.concatenate([[0], np.cumsum(lens)[:-1]]), lens)
        cols: IntArray = np.arange(lens.sum()) + offsets
        return cols

    def batch(
        self, subsets: Sequence[IntArray], rows: slice | BoolArray = slice(None)
    ) -> tuple[FloatArray, FloatArray]:
        """(Z (R, d, N0), F (R, n_rows, N0)) of subsets with the same N0."""
        cols = np.stack([self.columns(s) for s in subsets])  # (R, N0)
        Z = np.moveaxis(self.Z[:, cols], 0, 1)
        F = np.moveaxis(self.F[rows][:, cols], 0, 1)
        return np.ascontiguousarray(Z), np.ascontiguousarray(F)
