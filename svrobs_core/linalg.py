"""Batched linear algebra that never raises, and upper bounds rounded outward.

:func:`solve`: batched linear solves, NaN for the cells that cannot be solved.
:func:`up`, :func:`sum_up`, :func:`matvec_up`, :func:`perron_upper_bound`:
bounds evaluated with upward rounding (every operation's result moved one
ulp towards +inf), so that a computed bound is never below the exact value
(docs/uncertainty.md#certificates-on-the-boxes).

``numpy.linalg.solve`` raises ``LinAlgError`` for a whole batch as soon as one
matrix of it is singular or holds a NaN, which deep in a solver would turn
one degenerate cell (an overflowing iteration, a singular C) into a failed
unit. :func:`solve` gives NaN for those cells and the exact numpy result,
bit for bit, for the others (docs/spec.md#notes-why-a-field-is-null: nulls with a reason, not
exceptions).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

from .array_types import Array, FloatArray


def solve(M: ArrayLike, B: ArrayLike) -> Array:
    """``numpy.linalg.solve(M, B)`` batched; NaN where M is singular or M, B are not finite.

    M (..., k, k), B (..., k, r) (a stack of right-hand sides, as numpy's
    ``solve`` with ``B.ndim >= 2``). Cells that can be solved get the same
    bits as numpy gives them (the batch is solved again with the bad cells'
    M replaced by the identity, and every matrix is its own LAPACK call).
    """
    M = np.asarray(M)
    B = np.asarray(B)
    try:
        with np.errstate(all="ignore"):
            out: Array = np.linalg.solve(M, B)
            return out
    except np.linalg.LinAlgError:
        pass
    batch = np.broadcast_shapes(M.shape[:-2], B.shape[:-2])
    Mb = np.broadcast_to(M, batch + M.shape[-2:])
    Bb = np.broadcast_to(B, batch + B.shape[-2:])
    k = M.shape[-1]
    eye = np.eye(k)
    ok = np.isfinite(Mb).all(axis=(-2, -1)) & np.isfinite(Bb).all(axis=(-2, -1))
    s = np.linalg.svd(np.where(ok[..., None, None], Mb, eye), compute_uv=False)
    ok &= s[..., -1] > s[..., 0] * np.finfo(float).eps * k  # numerically singular -> NaN
    Ms = np.where(ok[..., None, None], Mb, eye)
    Bs = np.where(ok[..., None, None], Bb, 0.0)
    try:
        with np.errstate(all="ignore"):
            X = np.linalg.solve(Ms, Bs)
    except np.linalg.LinAlgError:  # an exact zero pivot the SVD did not flag
        X = np.full(np.broadcast_shapes(Ms.shape, Bs.shape), np.nan, dtype=np.result_type(Ms, Bs))
        for where in np.argwhere(ok):
            idx = tuple(where)
            try:
                X[idx] = np.linalg.solve(Ms[idx], Bs[idx])
            except np.linalg.LinAlgError:
                ok[idx] = False
    return np.where(ok[..., None, None], X, np.nan)


def up(x: ArrayLike) -> FloatArray:
    """The next double above x: an upper bound of the exact result of the one
    rounded-to-nearest operation that gave x (NaN stays NaN, inf stays inf)."""
    out: FloatArray = np.nextafter(x, np.inf)
    return out


def down(x: ArrayLike) -> FloatArray:
    """The next double below x (the lower end of an interval, as :func:`up`)."""
    out: FloatArray = np.nextafter(x, -np.inf)
    return out


def sum_up(X: ArrayLike, axis: int = -1) -> FloatArray:
    """An upper bound of the exact sum of X along ``axis``: one rounded-up
    addition per term (a loop over that axis, vectorised over the rest)."""
    X = np.moveaxis(np.asarray(X, dtype=float), axis, -1)
    acc = X[..., 0].copy()
    for j in range(1, X.shape[-1]):
        acc = up(acc + X[..., j])
    return acc


def matvec_up(M: ArrayLike, x: ArrayLike) -> FloatArray:
    """An upper bound of the exact M x for M >= 0, x >= 0 (..., k, k) @ (..., k):
    every product and every partial sum rounded up. -> (..., k)"""
    M = np.asarray(M, dtype=float)
    x = np.asarray(x, dtype=float)
    acc = up(M[..., :, 0] * x[..., None, 0])
    for j in range(1, M.shape[-1]):
        acc = up(acc + up(M[..., :, j] * x[..., None, j]))
    return acc


PERRON_FLOOR = 1e-15  # Perron-vector entries below this share of the largest are raised to it


def perron_upper_bound(M: ArrayLike) -> FloatArray:
    """An upper bound of rho(M) for entrywise nonnegative M (..., k, k), never below it.

    Collatz-Wielandt: rho(M) <= max_i (M x)_i / x_i for every x > 0. The
    bound is the smallest of three such vectors (the computed Perron vector
    with its entries floored at PERRON_FLOOR times the largest, one power
    step from it, and the ones vector, which gives the largest row sum),
    each evaluated with upward rounding (:func:`matvec_up`, then the quotient
    rounded up). Inf where M is not finite or the bound overflows.
    """
    M = np.asarray(M, dtype=float)
    if M.shape[-1] == 0:
        return np.zeros(M.shape[:-2])
    fin = np.isfinite(M).all(axis=(-2, -1))
    Ms = np.where(fin[..., None, None], M, 0.0)
    w, v = np.linalg.eig(Ms)
    top = np.argmax(w.real, axis=-1)
    x = np.abs(np.take_along_axis(v, top[..., None, None], axis=-1)[..., 0])
    with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
        big = x.max(axis=-1, keepdims=True)
        x = np.where(big > 0, x / np.where(big > 0, big, 1.0), 1.0)
        x = np.maximum(x, PERRON_FLOOR)
        step = Ms @ x[..., None]
        step = step[..., 0] / np.maximum(step[..., 0].max(axis=-1, keepdims=True), 1e-300)
        step = np.where(np.isfinite(step), np.maximum(step, PERRON_FLOOR), 1.0)
        best = np.full(M.shape[:-2], np.inf)
        for cand in (x, step, np.ones_like(x)):
            ratio = up(matvec_up(Ms, cand) / cand).max(axis=-1)
            best = np.minimum(best, np.where(np.isnan(ratio), np.inf, ratio))
    return np.where(fin, best, np.inf)
