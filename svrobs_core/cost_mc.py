"""Monte Carlo estimate of the observer cost J (docs/science.md#6-observer-cost-j).

The model and batching conventions are those of :mod:`svrobs_core.cost`.
:func:`mc_cost` simulates one batch of cells with one noise
stream; :func:`mc_cost_shared` simulates a grid (repetitions x estimators /
gammas) where the cells of a repetition share that repetition's stream (the
experiment runner's case), drawing it once and simulating the plant once.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import ArrayLike

from .array_types import FloatArray
from .cost import CostCells, horizon_steps
from .errors import DimensionError


def _steps(horizon: int, runs: int) -> tuple[int, int]:
    """(T, runs) checked: a positive integer horizon and at least 2 runs."""
    T, runs = horizon_steps(horizon), int(runs)
    if runs < 2:
        raise ValueError("runs must be at least 2 (for a standard error)")
    return T, runs


@np.errstate(over="ignore", invalid="ignore")  # near the double range: inf/NaN, not warnings
def mc_cost(
    A: ArrayLike,
    B: ArrayLike,
    A_tilde: ArrayLike,
    B_tilde: ArrayLike,
    *,
    L: ArrayLike,
    C: ArrayLike | None,
    sigma_u: ArrayLike,
    sigma_w: ArrayLike,
    sigma_v: ArrayLike,
    horizon: int,
    rng: np.random.Generator,
    runs: int,
) -> tuple[FloatArray, FloatArray]:
    """Monte Carlo mean and standard error of (1/T) sum_k ||e_k||^2 over ``runs``
    simulations, vectorised across runs. -> (mean, se), each (...)

    Simulates the plant and the observer themselves (not the e recursion):
    ``s = [x; x~]``, ``s_{k+1} = [[A, 0], [L C, A~ - L C]] s_k + [[B, I, 0],
    [B~, 0, L]] [u_k; w_k; v_k]``, ``s_0 = 0``, ``e_k = x~_k - x_k`` for
    k = 1..T. Each run's statistic is ``(1/T) sum_{k=1..T} ||e_k||^2``;
    ``mean`` is their average, ``se = std(ddof=1) / sqrt(runs)``.

    Order of draws (reproducibility): for k = 0, 1, ..., T-1, one call
    ``z = rng.standard_normal(batch + (runs, m + n + p))`` and
    ``u_k = sigma_u z[..., :m]``, ``w_k = sigma_w z[..., m:m+n]``,
    ``v_k = sigma_v z[..., m+n:]`` (all three are always drawn, also when a
    sigma is 0). Since numpy's Generator fills arrays in C order from one
    stream, this is the same as one draw of shape (T,) + batch + (runs, m+n+p);
    the implementation draws several steps at once to save calls. ``batch``
    is the broadcast batch shape of the arguments (``()`` for one cell).
    """
    T, runs = _steps(horizon, runs)
    c = CostCells(
        A, B, A_tilde, B_tilde, L=L, C=C, sigma_u=sigma_u, sigma_w=sigma_w, sigma_v=sigma_v
    )
    n, m, p, batch = c.n, c.m, c.p, c.batch
    q = m + n + p

    def tp(M: FloatArray) -> FloatArray:
        return np.swapaxes(M, -1, -2)

    LC = c.L @ c.C
    zero = np.zeros(batch + (n, n))
    # augmented transition and input matrices, batch + (2n, 2n) / (q, 2n)
    top = np.concatenate([np.broadcast_to(c.A, batch + (n, n)), zero], axis=-1)
    bot = np.concatenate(
        [np.broadcast_to(LC, batch + (n, n)), np.broadcast_to(c.At - LC, batch + (n, n))], axis=-1
    )
    Acal_T = tp(np.concatenate([top, bot], axis=-2))  # batch+(2n,2n)
    su = np.broadcast_to(c.su, batch)[..., None, None]
    sw = np.broadcast_to(c.sw, batch)[..., None, None]
    sv = np.broadcast_to(c.sv, batch)[..., None, None]
    Bx = np.concatenate(
        [
            su * np.broadcast_to(c.B, batch + (n, m)),
            sw * np.broadcast_to(np.eye(n), batch + (n, n)),
            np.zeros(batch + (n, p)),
        ],
        axis=-1,
    )
    Be = np.concatenate(
        [
            su * np.broadcast_to(c.Bt, batch + (n, m)),
            np.zeros(batch + (n, n)),
            sv * np.broadcast_to(c.L, batch + (n, p)),
        ],
        axis=-1,
    )
    Bcal_T = tp(np.concatenate([Bx, Be], axis=-2))  # batch+(q,2n)
    cells = int(np.prod(batch, dtype=np.int64))
    chunk = max(1, min(T, (4 * 2**20) // max(1, cells * runs * max(q, 2 * n))))  # ~32 MB
    s = np.zeros(batch + (runs, 2 * n))
    acc = np.zeros(batch + (runs,))
    k = 0
    while k < T:
        h = min(chunk, T - k)
        Z = rng.standard_normal((h,) + batch + (runs, q))
        # noise input for h steps at once, then turned in place into the states
        # s_{k+1..k+h}: S[i] = S[i-1] Acal^T + N[i]
        S = Z @ Bcal_T  # (h, *batch, runs, 2n)
        del Z
        S[0] += s @ Acal_T
        for i in range(1, h):
            S[i] += S[i - 1] @ Acal_T
        s = S[-1].copy()
        E = S[..., n:] - S[..., :n]
        acc += np.einsum("h...i,h...i->...", E, E)
        k += h
    return _mean_se(acc / T)


@np.errstate(over="ignore", invalid="ignore")  # near the double range: inf/NaN, not warnings
def mc_cost_shared(
    A: ArrayLike,
    B: ArrayLike,
    A_tilde: ArrayLike,
    B_tilde: ArrayLike,
    *,
    L: ArrayLike,
    C: ArrayLike | None,
    sigma_u: ArrayLike,
    sigma_w: ArrayLike,
    sigma_v: ArrayLike,
    horizon: int,
    rngs: Sequence[np.random.Generator],
    runs: int,
) -> tuple[FloatArray, FloatArray]:
    """:func:`mc_cost` for a grid of cells (R, E) where the E cells of row r share
    the noise of ``rngs[r]`` (common random numbers). -> (mean, se), each (R, E)

    Cell (r, e) gets the statistic :func:`mc_cost` gives for that cell alone
    with ``rng = rngs[r]`` (same draws in the same order: per row one
    ``standard_normal`` stream of shape (T, runs, m+n+p), split into u, w, v as
    in :func:`mc_cost`); only the arithmetic is arranged differently (equal to
    ~1e-13 relative), so a row's noise is drawn once for all its cells.

    A (n, n), B (n, m), C (p, n) or None (one true system); A_tilde
    (R, E, n, n), B_tilde (R, E, n, m), L (R, E, n, p); scalar sigmas;
    ``rngs``: R generators, each used only for its own row.

    Simulation (plant and observer, as :func:`mc_cost`). The plant
    ``x_{k+1} = A x_k + B u_k + w_k`` is the same for every cell of a row and
    runs once per row. Each observer is followed through its error
    ``e = x~ - x`` (the change of variables ``x~ = e + x`` in the observer
    equation, so the recorded error needs no extra pass):

        e_{k+1} = F e_k + G [x_k; z_k],  F = A~ - L C,
        G [x; z] = (F + L C) x + B~ u + L v - (A x + B u + w)

    ``G [x_k; z_k]`` for a block of steps is one BLAS product per cell, the
    recursion one (n, n) x (n, runs) product per cell and step (runs in the
    last axis). Every cell is computed with the same shapes whatever the grid
    (the block length depends only on ``runs`` and the sizes), so a cell's
    numbers do not depend on which other cells (estimators, gammas,
    repetitions) are computed with it.
    """
    T, runs = _steps(horizon, runs)
    c = CostCells(
        A, B, A_tilde, B_tilde, L=L, C=C, sigma_u=sigma_u, sigma_w=sigma_w, sigma_v=sigma_v
    )
    if c.xbatch != () or c.C.ndim != 2 or c.su.ndim or c.sw.ndim or c.sv.ndim:
        raise DimensionError("A", "B, C must be one true system and the sigmas scalars")
    n, m, p = c.n, c.m, c.p
    q = m + n + p
    shape = c.batch
    if len(shape) != 2:
        raise DimensionError("A_tilde", f"B_tilde and L must have a batch (R, E), got {shape}")
    R, E = shape
    rngs = list(rngs)
    if len(rngs) != R:
        raise ValueError(f"need one generator per row: {len(rngs)} for {R} rows")
    su, sw, sv = float(c.su), float(c.sw), float(c.sv)
    At = np.broadcast_to(c.At, shape + (n, n))
    Bt = np.broadcast_to(c.Bt, shape + (n, m))
    Lc = np.broadcast_to(c.L, shape + (n, p))
    LC = Lc @ c.C
    F = np.ascontiguousarray(At - LC)
    W = n + q  # [x; z], z = [u; w; v]
    xs, us, ws, vs = slice(0, n), slice(n, n + m), slice(n + m, n + m + n), slice(n + m + n, W)
    Mx = np.zeros((n, W))  # plant: x <- A x + su B u + sw w
    Mx[:, xs], Mx[:, us], Mx[:, ws] = c.A, su * c.B, sw * np.eye(n)
    G = np.zeros(shape + (n, W))  # observer error input
    G[..., xs] = (F + LC) - c.A
    G[..., us] = su * Bt - su * c.B
    G[..., ws] = -sw * np.eye(n)
    G[..., vs] = sv * Lc
    # steps per block: fixed by runs and sizes only (never by R or E), so the
    # grouping of the sums over k is the same for every grid
    h_max = max(1, min(T, (2**17) // (runs * W)))
    acc = np.zeros((R, E, n, runs))
    for r, g in enumerate(rngs):  # a row at a time: its blocks stay in cache
        acc[r] = _mc_row(Mx, G[r : r + 1], F[r : r + 1], g, T=T, h_max=h_max, runs=runs)[0]
    return _mean_se(acc.sum(axis=2) / T)  # per run (R, E, runs)


def _mean_se(per_run: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Mean and standard error over the runs (the last axis) of each run's statistic."""
    mean = per_run.mean(axis=-1)
    se = per_run.std(axis=-1, ddof=1) / np.sqrt(per_run.shape[-1])
    return mean, se


def _mc_row(
    Mx: FloatArray,
    G: FloatArray,
    F: FloatArray,
    g: np.random.Generator,
    *,
    T: int,
    h_max: int,
    runs: int,
) -> FloatArray:
    """One row of :func:`mc_cost_shared` (G (1, E, n, W), F (1, E, n, n)): the sums
    over k of ||e_k||^2 per cell, component and run, (1, E, n, runs). Shapes keep
    the row axis, so each BLAS call is the one a batch of rows makes per row."""
    n, W = Mx.shape
    E, q = G.shape[1], W - n  # z = [u; w; v]
    Xz = np.zeros((1, W, h_max + 1, runs))  # [x_k; z_k] for the block's steps
    Ev = np.zeros((1, E, h_max + 1, n, runs))  # e_k
    acc = np.zeros((1, E, n, runs))
    k = 0
    while k < T:
        h = min(h_max, T - k)
        Xz[0, n:, :h, :] = g.standard_normal((h, runs, q)).transpose(2, 0, 1)
        for i in range(h):
            np.matmul(Mx, Xz[:, :, i, :], out=Xz[:, :n, i + 1, :])
        D = G @ Xz[:, None, :, :h, :].reshape(1, 1, W, h * runs)  # (1, E, n, h runs)
        D = D.reshape(1, E, n, h, runs)
        for i in range(h):
            np.matmul(F, Ev[:, :, i], out=Ev[:, :, i + 1])
            Ev[:, :, i + 1] += D[:, :, :, i]
        err = Ev[:, :, 1 : h + 1]
        acc += np.einsum("rehks,rehks->reks", err, err)
        Ev[:, :, 0] = Ev[:, :, h]
        Xz[:, :n, 0] = Xz[:, :n, h]
        k += h
    return acc


__all__ = ["mc_cost", "mc_cost_shared"]
