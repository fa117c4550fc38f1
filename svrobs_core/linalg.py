"""Batched linear solves that never raise: NaN for the cells that cannot be solved.

``numpy.linalg.solve`` raises ``LinAlgError`` for a whole batch as soon as one
matrix of it is singular or holds a NaN, which deep in a solver would turn
one degenerate cell (an overflowing iteration, a singular C) into a failed
unit. :func:`solve` gives NaN for those cells and the exact numpy result,
bit for bit, for the others (docs/spec.md#notes-why-a-field-is-null: nulls with a reason, not
exceptions).
"""

from __future__ import annotations

import numpy as np


def solve(M, B) -> np.ndarray:
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
            return np.linalg.solve(M, B)
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
        for idx in np.argwhere(ok):
            idx = tuple(idx)
            try:
                X[idx] = np.linalg.solve(Ms[idx], Bs[idx])
            except np.linalg.LinAlgError:
                ok[idx] = False
    return np.where(ok[..., None, None], X, np.nan)
