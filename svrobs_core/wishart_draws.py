"""Datasets and bootstrap resamples drawn as Wishart scatter matrices
(docs/science.md#15-wishart-draws, docs/performance.md#wishart-draws).

Every statistic the service computes from a dataset of N rollouts depends on
their noise only through its scatter matrix, so above the noise dimension q the
N rollouts are replaced by the q columns of Bartlett's factor of that matrix:
the same law, at q columns and q (q + 1) / 2 random numbers.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from .array_types import FloatArray

# How a dataset's noise is drawn (docs/science.md#15-wishart-draws): its N
# rollouts' noise, or a factor of that noise's scatter matrix drawn at once.
DRAWS = ("rollouts", "wishart")
DEFAULT_DRAWS = "rollouts"


def noise_dim(*, n: int, m: int, T0: int, x0_std: float) -> int:
    """Standard normals of one rollout: x0 (n, if x0_std > 0), then u and w of every step."""
    return (m + n) * T0 + (n if x0_std > 0 else 0)


def dataset_columns(N: Any, *, n: int, m: int, T0: int, x0_std: float, draws: str) -> Any:
    """Columns simulated per dataset (or resample) of N rollouts (N an int or an array):
    N, or with ``"wishart"`` at most the noise dimension (:class:`WishartDraw`)."""
    if draws == "rollouts":
        return N
    return np.minimum(N, noise_dim(n=n, m=m, T0=T0, x0_std=x0_std))


def dataset_draws(N: Any, *, n: int, m: int, T0: int, x0_std: float, draws: str) -> Any:
    """Random numbers one dataset (or resample) of N rollouts draws (N an int or an array):
    q N, or with ``"wishart"`` above q = :func:`noise_dim` the q (q + 1) / 2 of
    :class:`WishartDraw`."""
    q = noise_dim(n=n, m=m, T0=T0, x0_std=x0_std)
    Nc = dataset_columns(N, n=n, m=m, T0=T0, x0_std=x0_std, draws=draws)
    return np.where(Nc < N, q * (q + 1) // 2, q * np.asarray(N))


class WishartDraw:
    """One key's pseudo-noise: q columns whose scatter matrix has the law of N rollouts'.

    With xi_r (q) the standard normals of rollout r (:func:`noise_dim`), every
    statistic of the data is a function of S = sum_r xi_r xi_r^T ~ Wishart(I_q, N).
    Bartlett's decomposition draws S = L L^T directly (N >= q): in this order,
    L_ii^2 ~ chi^2(N - i) for i = 0..q-1, then the strictly lower entries ~ N(0, 1) in
    row-major order. The columns of L are the pseudo-rollouts, rows laid out as
    a rollout's draws: x0 (n) if x0_std > 0, then u and w (m+n, T0). Called as
    ``fill(g, x0b, draw, x0_std)`` on buffers of q columns; True when it filled x0.
    """

    def __init__(self, q: int, N: int) -> None:
        self.df = N - np.arange(q, dtype=float)
        self.L = np.zeros((q, q))
        # flat positions in L (row-major): faster to assign than pairs of index arrays
        self.diag = np.arange(q) * (q + 1)
        self.lower = np.flatnonzero(np.tri(q, k=-1, dtype=bool))
        self.normals = np.empty(q * (q - 1) // 2)

    def __call__(
        self, g: np.random.Generator, x0b: FloatArray, draw: FloatArray, x0_std: float
    ) -> bool:
        L = self.L
        flat = L.reshape(-1)
        flat[self.diag] = np.sqrt(g.chisquare(self.df))
        g.standard_normal(out=self.normals)
        flat[self.lower] = self.normals
        k = x0b.shape[0] if x0_std > 0 else 0
        if k:
            x0b[...] = L[:k]
        draw[...] = L[k:].reshape(draw.shape)
        return k > 0


Fill = Callable[[np.random.Generator, FloatArray, FloatArray, float], bool]


def filler(
    N: int, fill: Fill, *, n: int, m: int, T0: int, x0_std: float, draws: str
) -> tuple[int, Fill]:
    """(columns, fill function) of a dataset of N rollouts: N and the rollouts'
    ``fill``, or with ``"wishart"`` above q the q columns of a :class:`WishartDraw`."""
    Nc = int(dataset_columns(N, n=n, m=m, T0=T0, x0_std=x0_std, draws=draws))
    return Nc, (fill if Nc == N else WishartDraw(Nc, N))
