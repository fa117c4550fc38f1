"""Observer gains (docs/science.md#4-stable-observer-gain-theorem-2): the certificate
g(L), the certified design and the reuse_gain policy (the Kalman gain K_hat they start from:
:mod:`svrobs_core.kalman`).

Everything here is pure and vectorised over leading batch dimensions ``...``:

* ``certificate``: ``g(L) = max_i sum_j |c_ij| + n r_A``,
  ``c = (1+gamma) A_tilde - L C`` (docs/science.md#42-the-certificate-gl), evaluated
  with outward rounding (never below the exact value).
* ``design_gain``: ``min ||L - K_hat||_F`` s.t. every row sum
  ``sum_j |c_ij| + n r_A <= 1 - margin``. For orthogonal ``C`` (in particular
  ``C = I``) this is an exact, vectorised Euclidean projection of every row of
  ``(1+gamma) A_tilde - K_hat C`` onto an l1 ball (Duchi et al. 2008); for any
  other ``C`` cvxpy + Clarabel solves it cell by cell.
* ``reuse_gains``: the ``reuse_gain`` sweep option along increasing ``N``.

Each takes either the paper's scalar radius ``r_A`` (every entry of A within
``r_A`` of the centre) or, keyword ``R_A``, a per-entry radius matrix
(docs/uncertainty.md): then ``g(L) = max_i sum_j (|c_ij| + (R_A)_ij)`` and row
``i`` of the design has the budget ``1 - margin - sum_j (R_A)_ij``.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from .array_types import Array, BoolArray, FloatArray
from .errors import check_matrix
from .linalg import down, sum_up, up

__all__ = [
    "GainResult",
    "ReuseResult",
    "certificate",
    "design_gain",
    "project_l1_ball",
    "reuse_gains",
]


def _mT(X: Array) -> Array:
    return np.swapaxes(X, -1, -2)


# ---------------------------------------------------------------------------
# Certificate and design (docs/science.md#4-stable-observer-gain-theorem-2)
# ---------------------------------------------------------------------------


@dataclass
class GainResult:
    """Observer gains for a batch of cells.

    L (..., n, p); g_L (...) = certificate(L); certified (...) bool = g_L < 1
    (docs/science.md#102-decisions-beyond-the-paper; NaN g gives False); feasible (...) bool:
    the design's margin constraint could be met (False means the fallback
    min g(L) was used). Cells with a non-finite input (e.g. a NaN K_hat) have
    NaN L and g, certified and feasible False (general-C path: also a cell
    where Clarabel fails outright).
    """

    L: Array
    g_L: Array
    certified: Array
    feasible: Array | None = None


def _scaled_center(A_tilde: ArrayLike, gamma: ArrayLike) -> FloatArray:
    A_tilde = np.asarray(A_tilde, dtype=float)
    gamma = np.asarray(gamma, dtype=float)
    Ct: FloatArray = (1.0 + gamma)[..., None, None] * A_tilde
    return Ct


def certificate(
    L: ArrayLike,
    A_tilde: ArrayLike,
    gamma: ArrayLike,
    r_A: ArrayLike | None,
    *,
    C: ArrayLike,
    R_A: ArrayLike | None = None,
) -> FloatArray:
    """g(L) = max_i sum_j |c_ij| + n r_A with c = (1+gamma) A_tilde - L C. -> (...)

    L (..., n, p), A_tilde (..., n, n), C (p, n) or (..., p, n); gamma and r_A
    broadcast against the batch shape (use gamma = 0 for OLS). With a radius
    matrix ``R_A`` (..., n, n) instead (r_A ignored):
    g(L) = max_i sum_j (|c_ij| + (R_A)_ij).

    Evaluated with outward rounding, so the value is never below the exact g
    of these numbers (``certified = g < 1`` then implies the exact inequality):
    c is enclosed in an interval (the centre and every product of L C rounded
    outward by :func:`svrobs_core.linalg.up` / ``down``), |c| is bounded by the
    larger end, and the row sums are rounded up (docs/uncertainty.md#certificates-on-the-boxes).
    NaN where an input is NaN.
    """
    Ct = _scaled_center(A_tilde, gamma)
    n = Ct.shape[-1]
    L = np.asarray(L, dtype=float)
    C = np.asarray(C, dtype=float)
    with np.errstate(over="ignore", invalid="ignore"):
        # (1 + gamma) A_tilde: two roundings (1 + gamma, the product), one ulp each
        lo, hi = down(down(Ct)), up(up(Ct))
        for k in range(C.shape[-2]):
            prod = L[..., :, k, None] * C[..., k, None, :]
            lo, hi = down(lo - up(prod)), up(hi - down(prod))
        absc = np.maximum(np.abs(lo), np.abs(hi))
        if R_A is not None:
            g: FloatArray = sum_up(up(absc + np.asarray(R_A, dtype=float)), axis=-1).max(axis=-1)
            return g
        radius = up(n * np.asarray(r_A, dtype=float))
        return up(sum_up(absc, axis=-1).max(axis=-1) + radius)


def project_l1_ball(V: ArrayLike, radius: ArrayLike) -> FloatArray:
    """Euclidean projection of every vector V[..., :] onto {w : ||w||_1 <= radius}.

    Exact sort-based algorithm (Duchi, Shalev-Shwartz, Singer & Chandra 2008),
    vectorised over all leading dims; ``radius`` (...) >= 0 broadcasts against
    V.shape[:-1]. Radius 0 gives the zero vector.
    """
    V = np.asarray(V, dtype=float)
    radius = np.broadcast_to(np.asarray(radius, dtype=float), V.shape[:-1])
    d = V.shape[-1]
    a = np.abs(V)
    u = -np.sort(-a, axis=-1)
    cs = np.cumsum(u, axis=-1)
    j = np.arange(1, d + 1)
    cond = u - (cs - radius[..., None]) / j > 0
    k = np.where(cond, j, 0).max(axis=-1).clip(min=1)
    theta = (np.take_along_axis(cs, (k - 1)[..., None], axis=-1)[..., 0] - radius) / k
    W = np.sign(V) * np.maximum(a - theta[..., None], 0.0)
    inside = a.sum(axis=-1) <= radius
    return np.where(inside[..., None], V, W)


def is_orthogonal(C: ArrayLike) -> bool:
    """True when C (or every C of a stack) is square with C^T C = I (to 1e-12): the
    closed-form design applies."""
    return bool(np.all(orthogonal_each(C)))


def orthogonal_each(C: ArrayLike) -> BoolArray:
    """:func:`is_orthogonal` of each matrix of a stack ``(..., p, n)``: a mask ``(...)``."""
    C = np.asarray(C, dtype=float)
    if C.shape[-1] != C.shape[-2]:
        return np.zeros(C.shape[:-2], dtype=bool)
    p = C.shape[-1]
    each: BoolArray = np.all(np.abs(_mT(C) @ C - np.eye(p)) <= 1e-12, axis=(-2, -1))
    return each


def design_gain(
    A_tilde: ArrayLike,
    gamma: ArrayLike,
    r_A: ArrayLike | None,
    C: ArrayLike,
    *,
    K_hat: ArrayLike,
    margin: ArrayLike = 0.01,
    method: str = "auto",
    R_A: ArrayLike | None = None,
) -> GainResult:
    """min ||L - K_hat||_F s.t. sum_j |c_ij(L)| + n r_A <= 1 - margin for all i.

    With a radius matrix ``R_A`` (..., n, n) (r_A ignored, may be None) the
    constraint of row i is sum_j |c_ij(L)| + sum_j (R_A)_ij <= 1 - margin.

    A_tilde (..., n, n), K_hat (..., n, p), C (p, n) or (..., p, n); gamma,
    r_A, margin broadcast against the batch shape. If the constraint is
    infeasible the fallback is ``min_L g(L)`` (ties broken by the L closest to
    K_hat) and ``feasible`` is False; ``certified`` is always ``g(L) < 1``.

    method: "auto" (closed form when C is orthogonal, e.g. C = I, else
    cvxpy), "closed_form" (requires orthogonal C) or "cvxpy" (per cell).
    """
    Ct = _scaled_center(A_tilde, gamma)
    C = np.asarray(C, dtype=float)
    n, p = Ct.shape[-1], C.shape[-2]
    K_hat = check_matrix("K_hat", K_hat, (n, p))
    if R_A is None:
        r_A = np.asarray(r_A, dtype=float)
        rshape = r_A.shape
    else:
        R_A = np.asarray(R_A, dtype=float)
        rshape = R_A.shape[:-2]
    batch = np.broadcast_shapes(
        Ct.shape[:-2], K_hat.shape[:-2], C.shape[:-2], rshape, np.shape(margin)
    )
    Ct = np.broadcast_to(Ct, batch + (n, n))
    K_hat = np.broadcast_to(K_hat, batch + (n, p))
    Cb = np.broadcast_to(C, batch + (p, n))
    if R_A is None:
        rho = np.broadcast_to(1.0 - np.asarray(margin, dtype=float) - n * r_A, batch)
        rows = rho[..., None]  # the same budget for every row
    else:  # one budget per row: (..., n)
        rows = np.asarray(1.0 - np.asarray(margin, dtype=float))[..., None] - R_A.sum(axis=-1)
        rows = np.broadcast_to(rows, batch + (n,))
        rho = rows.min(axis=-1)
    good = (
        np.isfinite(Ct).all(axis=(-1, -2))
        & np.isfinite(K_hat).all(axis=(-1, -2))
        & np.isfinite(Cb).all(axis=(-1, -2))
        & np.isfinite(rows).all(axis=-1)
    )

    orth = is_orthogonal(C)
    if method == "auto":
        method = "closed_form" if orth else "cvxpy"
    if method == "closed_form":
        if not orth:
            raise ValueError("closed_form design needs an orthogonal C (e.g. C = I)")
        feasible = good & (rho >= 0)
        with np.errstate(invalid="ignore"):
            c0 = Ct - K_hat @ Cb
            # infeasible: min g(L) = the largest row of radii (its c = 0); row i may
            # keep sum_j |c_ij| up to that less its own radii (rows - rho), and the
            # nearest to K_hat is its projection there (a scalar r_A: c = 0)
            c = project_l1_ball(c0, np.where(feasible[..., None], rows, rows - rho[..., None]))
            L = (Ct - c) @ _mT(Cb)  # C orthogonal: L C = Ct - c
    elif method == "cvxpy":
        L = np.full(batch + (n, p), np.nan)
        feasible = np.zeros(batch, dtype=bool)
        solver = _CvxpyDesign(n, p, per_row=R_A is not None)
        for ix in np.ndindex(batch):
            if good[ix]:
                budget = rho[ix] if R_A is None else rows[ix]
                L[ix], feasible[ix] = solver.solve(Ct[ix], Cb[ix], K_hat[ix], budget)
    else:
        raise ValueError(f"unknown method {method!r}")

    L = np.where(good[..., None, None], L, np.nan)
    g = certificate(L, Ct, 0.0, r_A, C=Cb, R_A=R_A)
    with np.errstate(invalid="ignore"):
        certified = g < 1.0
    return GainResult(L=L, g_L=g, certified=certified, feasible=feasible & good)


class _CvxpyDesign:
    """The general-C design as parametrised cvxpy problems, solved by Clarabel.

    ``per_row``: one budget per row (a radius matrix); else one scalar budget
    (the paper's scalar radius, the problem exactly as it always was)."""

    def __init__(self, n: int, p: int, per_row: bool = False) -> None:
        import cvxpy

        cp: Any = cvxpy

        self.cp: Any = cp
        self.per_row = per_row
        self.L = cp.Variable((n, p))
        self.Ct = cp.Parameter((n, n))
        self.C = cp.Parameter((p, n))
        self.K = cp.Parameter((n, p))
        self.rho = cp.Parameter(n) if per_row else cp.Parameter()
        rows = cp.sum(cp.abs(self.Ct - self.L @ self.C), axis=1)
        self.main = cp.Problem(cp.Minimize(cp.sum_squares(self.L - self.K)), [rows <= self.rho])
        self.t = cp.Variable()
        if per_row:  # min_L max_i (row_i + offset_i), offset_i = 1 - margin - budget_i >= 0
            self.offset = cp.Parameter(n)
            self.min_g = cp.Problem(cp.Minimize(self.t), [rows + self.offset <= self.t])
        else:
            self.min_g = cp.Problem(cp.Minimize(self.t), [rows <= self.t])

    def _solve(self, problem: Any) -> str:
        """The problem's status, or "solver_error" when Clarabel fails outright."""
        try:
            with warnings.catch_warnings():  # "Solution may be inaccurate": see the status
                warnings.filterwarnings("ignore", message="Solution may be inaccurate")
                problem.solve(solver=self.cp.CLARABEL)
        except (self.cp.error.SolverError, ValueError, ArithmeticError):
            return "solver_error"
        status: str = problem.status
        return status

    def solve(self, Ct: Array, C: Array, K_hat: Array, rho: float | Array) -> tuple[Array, bool]:
        if self.per_row:
            return self._solve_rows(Ct, C, K_hat, np.asarray(rho, dtype=float))
        cp = self.cp
        self.Ct.value, self.C.value, self.K.value = Ct, C, K_hat
        self.rho.value = float(rho)
        status = self._solve(self.main)
        if status in (cp.OPTIMAL, cp.OPTIMAL_INACCURATE):
            return self.L.value, True
        nan = np.full(self.L.shape, np.nan)
        if status not in (cp.INFEASIBLE, cp.INFEASIBLE_INACCURATE):
            return nan, False  # solver failure: NaN gain, not certified
        # fallback: min g(L); then, among the minimisers, the L closest to K_hat
        if self._solve(self.min_g) not in (cp.OPTIMAL, cp.OPTIMAL_INACCURATE):
            return nan, False
        L1 = self.L.value
        self.rho.value = float(np.abs(Ct - L1 @ C).sum(axis=-1).max())
        if self._solve(self.main) in (cp.OPTIMAL, cp.OPTIMAL_INACCURATE):
            L2 = self.L.value
            if np.abs(Ct - L2 @ C).sum(axis=-1).max() <= self.rho.value + 1e-9:
                return L2, False
        return L1, False

    def _solve_rows(
        self, Ct: Array, C: Array, K_hat: Array, budget: FloatArray
    ) -> tuple[Array, bool]:
        """Per-row budgets; the fallback minimises max_i (row_i(L) + offset_i)."""
        cp = self.cp
        self.Ct.value, self.C.value, self.K.value = Ct, C, K_hat
        self.rho.value = budget
        ok = (cp.OPTIMAL, cp.OPTIMAL_INACCURATE)
        status = self._solve(self.main)
        if status in ok:
            return self.L.value, True
        nan = np.full(self.L.shape, np.nan)
        if status not in (cp.INFEASIBLE, cp.INFEASIBLE_INACCURATE):
            return nan, False  # solver failure: NaN gain, not certified
        offset = budget.max() - budget  # shifts that keep the row order of the budgets
        self.offset.value = offset
        if self._solve(self.min_g) not in ok:
            return nan, False
        L1 = self.L.value
        top = float((np.abs(Ct - L1 @ C).sum(axis=-1) + offset).max())
        self.rho.value = top - offset
        if self._solve(self.main) in ok:
            L2 = self.L.value
            if (np.abs(Ct - L2 @ C).sum(axis=-1) + offset).max() <= top + 1e-9:
                return L2, False
        return L1, False


# ---------------------------------------------------------------------------
# reuse_gain (docs/science.md#44-reuse_gain)
# ---------------------------------------------------------------------------


@dataclass(kw_only=True)
class ReuseResult:
    """The reuse_gain choice along the N axis (axis 0).

    L (nN, ..., n, p), g_L (nN, ...) evaluated with each N's own estimate,
    certified (nN, ...) = g_L < 1, reused (nN, ...) True where the previous
    N's gain was kept, source (nN, ...) int: index along N of the design used.
    """

    L: Array
    g_L: Array
    certified: Array
    reused: Array
    source: Array


def reuse_gains(
    L: ArrayLike,
    A_tilde: ArrayLike,
    gamma: ArrayLike,
    r_A: ArrayLike,
    *,
    C: ArrayLike,
    R_A: ArrayLike | None = None,
) -> ReuseResult:
    """reuse_gain policy along increasing N (docs/science.md#44-reuse_gain).

    L (nN, ..., n, p): the gain designed at each N (axis 0 sorted by
    increasing N, same system, sigma_w, estimator, gamma, rep along the rest);
    A_tilde (nN, ..., n, n), gamma and r_A broadcast to (nN, ...); C (p, n).

    At the first N the designed gain is used. At a later N the previously
    chosen gain is kept iff it was certified at the previous N and is still
    certified (g < 1) for the new estimate (A_tilde, gamma, r_A); otherwise
    the gain designed at this N is used. Vectorised over all non-N dims.
    ``R_A`` (nN, ..., n, n): a radius matrix per N instead of r_A.
    """
    L = np.asarray(L, dtype=float)
    Ct = _scaled_center(A_tilde, gamma)
    n, p = L.shape[-2], L.shape[-1]
    rshape = np.shape(r_A) if R_A is None else np.shape(R_A)[:-2]
    batch = np.broadcast_shapes(L.shape[:-2], Ct.shape[:-2], rshape)
    L = np.broadcast_to(L, batch + (n, p))
    Ct = np.broadcast_to(Ct, batch + (n, n))
    if R_A is None:
        r_A = np.broadcast_to(np.asarray(r_A, dtype=float), batch)
        R_rows: Any = [None] * batch[0]
    else:
        R_rows = np.broadcast_to(np.asarray(R_A, dtype=float), batch + (n, n))
        r_A = np.zeros(batch)
    nN = batch[0]

    out_L = np.empty(batch + (n, p))
    g = np.empty(batch)
    reused = np.zeros(batch, dtype=bool)
    source = np.empty(batch, dtype=np.intp)
    with np.errstate(invalid="ignore"):
        for k in range(nN):
            g_new = certificate(L[k], Ct[k], 0.0, r_A[k], C=C, R_A=R_rows[k])
            if k == 0:
                keep = np.zeros(batch[1:], dtype=bool)
                g_prev = np.zeros(batch[1:])
            else:
                g_prev = certificate(out_L[k - 1], Ct[k], 0.0, r_A[k], C=C, R_A=R_rows[k])
                keep = (g[k - 1] < 1.0) & (g_prev < 1.0)
            out_L[k] = np.where(keep[..., None, None], out_L[k - 1] if k else L[k], L[k])
            g[k] = np.where(keep, g_prev, g_new)
            reused[k] = keep
            source[k] = np.where(keep, source[k - 1] if k else 0, k)
        certified = g < 1.0
    return ReuseResult(L=out_L, g_L=g, certified=certified, reused=reused, source=source)
