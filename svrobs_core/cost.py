"""Observer cost J (docs/science.md#6-observer-cost-j): exact finite horizon and stationary.

Model (docs/science.md#6-observer-cost-j). True system and observer on the estimates:

    x_{k+1}  = A x_k + B u_k + w_k,              y_k = C x_k + v_k
    x~_{k+1} = A~ x~_k + B~ u_k + L (y_k - C x~_k)

``u ~ N(0, sigma_u^2 I_m)``, ``w ~ N(0, sigma_w^2 I_n)``, ``v ~ N(0, sigma_v^2 I_p)``,
``x_0 = x~_0 = 0``. The error ``e = x~ - x`` obeys

    e_{k+1} = F e_k - dA x_k - dB u_k + L v_k - w_k,   F = A~ - L C,
    dA = A - A~,  dB = B - B~,

i.e. ``s = [x; e]`` is driven by the block lower-triangular
``Acal = [[A, 0], [-dA, F]]``. The cost is ``J = (1/T) sum_{k=1..T} E||e_k||^2``
(exact, finite horizon T) or its limit (stationary).

Batching: every argument may carry leading batch dimensions ``...``; they
broadcast against each other (the usual case is one true system ``A, B, C``
and sigmas shared by a batch of cells ``A~ (..., n, n)``, ``B~ (..., n, m)``,
``L (..., n, p)``). Results have the broadcast batch shape (0-d arrays for a
single cell). ``B`` / ``B~`` given as 1-D vectors are read as columns;
``C=None`` means ``I_n``.

Work per cell. The x block of the covariance depends only on the true system,
so it is computed once (batch size 1) and shared. The exact cost does not step
through the T time steps: with zero initial state the process has
time-invariant statistics, so for segment lengths a, b

    Sigma_{a+b} = Sigma_a + Acal^a Sigma_b Acal^aT
    W_{a+b}     = W_a + b Sigma_a + Acal^a W_b Acal^aT,   W_t = sum_{k<=t} Sigma_k

(``Sigma_t = Cov s_t``), and ``J = trace(e block of W_T) / T`` follows by binary
doubling in ~2 log2(T) steps of a few n x n products per cell (each exact up
to rounding; for T = 200, about 170 products instead of ~1400 for the
step-by-step recursion). Small products are evaluated with the batch in the
last axis ("structure of arrays"), which is ~5x faster in numpy than stacked
``matmul`` on 3 x 3 matrices.

Monte Carlo estimates of the same J: :mod:`svrobs_core.cost_mc`.
"""

from __future__ import annotations

from typing import Any, Literal, TypeAlias, overload

import numpy as np
from numpy.typing import ArrayLike

from .array_types import Array, FloatArray
from .cost_check import DoublingRounding
from .cost_check import U as _U
from .errors import check_matrix
from .norms import REASON_UNSTABLE, schur_stable, stability_radius, stability_reason, stein_solve

REASON_STATIONARY_LOST = (
    "not computable in doubles (its Stein equation is singular to working precision "
    "or its covariance overflows)"
)

# Up to this state dimension the batched small products are done with the
# batch in the last axis; above it with stacked matmul (BLAS per matrix).
_SOA_MAX_N = 12


# --------------------------------------------------------------------------
# argument handling
# --------------------------------------------------------------------------
class CostCells:
    """Validated, broadcast arguments of one cost call."""

    A: FloatArray
    B: FloatArray
    At: FloatArray
    Bt: FloatArray
    L: FloatArray
    C: FloatArray
    su: FloatArray
    sw: FloatArray
    sv: FloatArray

    def __init__(
        self,
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
    ) -> None:
        A = np.asarray(A, dtype=float)
        B = np.asarray(B, dtype=float)
        At = np.asarray(A_tilde, dtype=float)
        Bt = np.asarray(B_tilde, dtype=float)
        L = np.asarray(L, dtype=float)
        if B.ndim == 1:
            B = B[:, None]
        if Bt.ndim == 1:
            Bt = Bt[:, None]
        A = check_matrix("A", A, ("n", "n"))
        n = A.shape[-1]
        if C is None:
            C = np.eye(n)
        C = np.asarray(C, dtype=float)
        if L.ndim == 1:
            L = L[:, None]
        if C.ndim == 1:
            C = C[None, :]
        m, p = B.shape[-1], C.shape[-2]
        for name, arr, shape in (
            ("B", B, (n, m)),
            ("A_tilde", At, (n, n)),
            ("B_tilde", Bt, (n, m)),
            ("L", L, (n, p)),
            ("C", C, (p, n)),
        ):
            check_matrix(name, arr, shape)
        su = np.asarray(sigma_u, dtype=float)
        sw = np.asarray(sigma_w, dtype=float)
        sv = np.asarray(sigma_v, dtype=float)
        self.n, self.m, self.p = n, m, p
        self.A, self.B, self.At, self.Bt, self.L, self.C = A, B, At, Bt, L, C
        self.su, self.sw, self.sv = su, sw, sv
        # batch shape of the true-system part (x block) and of the whole call
        self.xbatch = np.broadcast_shapes(A.shape[:-2], B.shape[:-2], su.shape, sw.shape)
        self.batch = np.broadcast_shapes(
            self.xbatch, At.shape[:-2], Bt.shape[:-2], L.shape[:-2], C.shape[:-2], sv.shape
        )

    # derived per-cell matrices (numpy broadcasting, AoS layout)
    def F(self) -> FloatArray:
        F: FloatArray = self.At - self.L @ self.C
        return F

    def dA(self) -> FloatArray:
        dA: FloatArray = self.A - self.At
        return dA

    def dB(self) -> FloatArray:
        dB: FloatArray = self.B - self.Bt
        return dB

    def Q_blocks(self) -> tuple[FloatArray, FloatArray, FloatArray]:
        """Noise covariance of s = [x; e] per step, blocks (xx, xe, ee)."""
        B, dB, L, n = self.B, self.dB(), self.L, self.n
        su2 = (self.su**2)[..., None, None]
        sw2 = (self.sw**2)[..., None, None]
        sv2 = (self.sv**2)[..., None, None]
        I = np.eye(n)
        T = np.swapaxes
        Qxx = su2 * (B @ T(B, -1, -2)) + sw2 * I
        Qxe = -su2 * (B @ T(dB, -1, -2)) - sw2 * I
        Qee = su2 * (dB @ T(dB, -1, -2)) + sw2 * I + sv2 * (L @ T(L, -1, -2))
        return Qxx, Qxe, Qee


# --------------------------------------------------------------------------
# batched small products in two layouts
# --------------------------------------------------------------------------
# blocks (xx, xe, ee) of a 2n x 2n matrix; xe is None where it is not needed
_Blocks: TypeAlias = tuple[Any, ...]


class _Layout:
    """Batched small matrices in one of two layouts.

    ``soa=True``: stored as (r, c, S, N), batch N in the last axis (products
    by einsum); ``soa=False``: stored as (S, N, r, c) (stacked matmul, BLAS
    per matrix). S is a stack axis (Sigma and W of a segment).
    """

    def __init__(self, batch: tuple[int, ...], soa: bool) -> None:
        self.batch = batch
        self.N = int(np.prod(batch, dtype=np.int64))
        self.soa = soa
        self._mat = (0, 1) if soa else (-2, -1)  # the matrix axes
        self._lead = (slice(None),) * 2 if soa else ()  # index prefix up to the stack axis

    def put(self, X: ArrayLike) -> Array:
        """(..., r, c) with batch broadcastable to self.batch -> the layout, batch N or 1."""
        X = np.asarray(X, dtype=float)
        r, c = X.shape[-2:]
        if int(np.prod(X.shape[:-2], dtype=np.int64)) == 1:
            return X.reshape(r, c, 1, 1) if self.soa else X.reshape(1, 1, r, c)
        X = np.broadcast_to(X, self.batch + (r, c)).reshape(self.N, r, c)
        if self.soa:
            return np.ascontiguousarray(np.moveaxis(X, 0, -1))[:, :, None, :]
        return X.reshape(1, self.N, r, c)

    def mm(self, a: Array, b: Array) -> Array:
        out: Array = np.einsum("ik...,kj...->ij...", a, b) if self.soa else a @ b
        return out

    def t(self, a: Array) -> Array:
        return np.swapaxes(a, *self._mat)

    def stack(self, x: Array, y: Array) -> Array:
        x, y = np.broadcast_arrays(x, y)
        return np.concatenate([x, y], axis=len(self._lead))

    def part(self, x: Array, i: int) -> Array:
        return x[self._lead + (slice(i, i + 1),)]

    def addto_w(self, new: Array, t: int, Ma: Array) -> None:
        new[self._lead + (1,)] += t * Ma[self._lead + (0,)]

    def trace(self, x: Array) -> Array:
        tr: Array = np.trace(x, axis1=self._mat[0], axis2=self._mat[1])  # -> (S, N)
        return tr

    def get(self, v: Array) -> Array:
        """(S=1, N|1) -> batch shape."""
        return np.broadcast_to(v[0], (self.N,)).reshape(self.batch)

    def norm(self, blocks: _Blocks, counts: tuple[int, ...] = (1, 2, 1)) -> Array:
        """Frobenius norm of a block matrix from its blocks (xx, xe, ee), ``counts``
        times each (the xe block twice in a symmetric matrix; None: a zero block). -> (S, N|1)"""
        sq = sum(k * np.sum(b * b, axis=self._mat) for b, k in zip(blocks, counts) if b is not None)
        out: Array = np.sqrt(sq)
        return out


def horizon_steps(horizon: float) -> int:
    """The horizon T as an int; ValueError unless it is a positive integer."""
    T = int(horizon)
    if T < 1 or T != horizon:
        raise ValueError(f"horizon must be a positive integer, got {horizon!r}")
    return T


def _layout(n: int, batch: tuple[int, ...]) -> _Layout:
    return _Layout(batch, soa=n <= _SOA_MAX_N)


def _congruence(ops: _Layout, P: _Blocks, M: _Blocks, need_xe: bool = True) -> _Blocks:
    """Blocks (xx, xe, ee) of P M P^T, P = [[Pa, 0], [Pr, Pf]], M = [[Mx, Mxe], [Mxe^T, Me]]."""
    Pa, Pr, Pf = P
    Mx, Mxe, Me = M
    mm, t = ops.mm, ops.t
    PaMx = mm(Pa, Mx)
    xx = mm(PaMx, t(Pa))
    PrT, PfT = t(Pr), t(Pf)
    V = mm(Pr, Mx) + mm(Pf, t(Mxe))
    Y = mm(Pr, Mxe) + mm(Pf, Me)
    ee = mm(V, PrT) + mm(Y, PfT)
    xe = mm(PaMx, PrT) + mm(mm(Pa, Mxe), PfT) if need_xe else None
    return xx, xe, ee


def _join(
    ops: _Layout, P_a: _Blocks, M_a: _Blocks, M_b: _Blocks, *, t_b: int, need_xe: bool = True
) -> _Blocks:
    """Stacked (Sigma, W) of the concatenation of segment a (power P_a, stacked
    M_a = (Sigma_a, W_a) blocks) followed by segment b (M_b, length t_b)."""
    C = _congruence(ops, P_a, M_b, need_xe)
    out: list[Array | None] = []
    for Ma, Cb in zip(M_a, C):
        if Cb is None:
            out.append(None)
            continue
        new = Ma + Cb  # fresh array (Sigma_a + .., W_a + ..)
        ops.addto_w(new, t_b, Ma)  # W_{a+b} gets the extra t_b * Sigma_a
        out.append(new)
    return tuple(out)


def _square(ops: _Layout, P: _Blocks) -> _Blocks:
    Pa, Pr, Pf = P
    mm = ops.mm
    return mm(Pa, Pa), mm(Pr, Pa) + mm(Pf, Pr), mm(Pf, Pf)


# --------------------------------------------------------------------------
# exact finite-horizon cost
# --------------------------------------------------------------------------
@overload
def exact_cost(
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
    horizon: int = ...,
    return_error: Literal[False] = ...,
) -> FloatArray: ...
@overload
def exact_cost(
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
    horizon: int = ...,
    return_error: Literal[True],
) -> tuple[FloatArray, FloatArray]: ...
@np.errstate(over="ignore", invalid="ignore")  # near the double range: inf/NaN, not warnings
def exact_cost(
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
    horizon: int = 200,
    return_error: bool = False,
) -> FloatArray | tuple[FloatArray, FloatArray]:
    """Mean over k=1..T of E||e_k||^2 by covariance propagation. -> (...)

    Deterministic and exact up to rounding (binary doubling of the augmented
    covariance, see the module doc; agrees with the step-by-step 2n
    recursion to ~1e-14 relative); x_0 = x~_0 = 0. Defined for every system,
    stable or not: an unstable augmented system just gives a large number
    (the x block grows like rho(A)^(2T), so e.g. rho(A) = 1.024 overflows
    only beyond T ~ 15000, giving inf/NaN). Non-finite inputs (e.g. a cell
    without a gain, L = NaN) give NaN. Shapes: A (..., n, n), B (..., n, m),
    A_tilde (..., n, n), B_tilde (..., n, m), L (..., n, p), C (..., p, n) or
    None, sigmas (...). Cost ~ 2 log2(T) batched products per cell: call it
    once for a whole batch of cells, not once per cell (the per-call Python
    overhead is ~1 ms). ``return_error=True`` gives ``(J, err)``, ``err`` a
    first-order bound on the rounding error of ``J``
    (:class:`svrobs_core.cost_check.DoublingRounding`): for a
    strongly non-normal system (entries of 1e3 and more, eigenvalues near 1) the
    doubling, like any recursion in doubles, can lose every digit.
    """
    T = horizon_steps(horizon)
    c = CostCells(
        A, B, A_tilde, B_tilde, L=L, C=C, sigma_u=sigma_u, sigma_w=sigma_w, sigma_v=sigma_v
    )
    ops = _layout(c.n, c.batch)
    Qxx, Qxe, Qee = c.Q_blocks()
    # one-step power Acal = [[A, 0], [-dA, F]]
    P = (ops.put(c.A), ops.put(-c.dA()), ops.put(c.F()))
    Q = (ops.put(Qxx), ops.put(Qxe), ops.put(Qee))
    # block of length 1: Sigma_1 = W_1 = Q   (stacked: index 0 Sigma, 1 W)
    blk = tuple(ops.stack(q, q) for q in Q)
    t_blk = 1
    acc: _Blocks | None = None
    t_acc = 0
    rnd = DoublingRounding(ops, c.n)
    # the inputs' own rounding: dA = A - A~, F = A~ - L C, and the noise covariance
    na, nr, nf = rnd.norms(P)
    nL, nC = rnd.norms((ops.put(c.L), ops.put(c.C)))
    eP: tuple[Any, ...] = (0.0 * na, _U * nr, rnd.g * (nf + nL * nC))
    eQ = rnd.g * sum(rnd.norms(Q))
    e_blk = tuple(np.concatenate([eQ, eQ]) for _ in Q)  # (Sigma_1, W_1) = (Q, Q)
    e_acc = e_blk
    bits = bin(T)[2:][::-1]
    top = len(bits) - 1
    for j, bit in enumerate(bits):
        if bit == "1":
            if acc is None:
                acc, t_acc, e_acc = blk, t_blk, e_blk
            else:
                e_acc = rnd.join(P, eP, blk, e_blk, acc, e_acc, t_acc)
                acc = _join(ops, P, blk, acc, t_b=t_acc, need_xe=(j < top))
                t_acc += t_blk
        if j < top:
            e_blk = rnd.join(P, eP, blk, e_blk, blk, e_blk, t_blk)
            blk = _join(ops, P, blk, blk, t_b=t_blk)
            t_blk *= 2
            eP = rnd.square(P, eP)
            P = _square(ops, P)
    assert acc is not None  # T >= 1 has a 1 bit
    tr = ops.trace(ops.part(acc[2], 1))
    J: FloatArray = ops.get(tr) / T
    if not return_error:
        return J
    # the trace of the e block of W: at most sqrt(n) times its Frobenius error
    err = np.sqrt(c.n) * ops.get(e_acc[2][1:]) / T + 2 * _U * np.abs(J)
    return J, np.where(np.isnan(err), np.inf, err)


def optimal_cost(
    A: ArrayLike,
    B: ArrayLike,
    K: ArrayLike,
    C: ArrayLike | None,
    *,
    sigma_u: ArrayLike,
    sigma_w: ArrayLike,
    sigma_v: ArrayLike,
    horizon: int = 200,
) -> FloatArray:
    """J* (docs/science.md#6-observer-cost-j): exact_cost with A~ = A, B~ = B, L = K. -> (...)

    (With the true model the error is the Kalman predictor error, decoupled
    from x; its stationary value is trace(P), P the DARE solution.)"""
    return exact_cost(
        A, B, A, B, L=K, C=C, sigma_u=sigma_u, sigma_w=sigma_w, sigma_v=sigma_v, horizon=horizon
    )


j_star = optimal_cost


# --------------------------------------------------------------------------
# stationary cost
# --------------------------------------------------------------------------
@overload
def stationary_cost(
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
    rho_F: ArrayLike | None = ...,
    return_reason: Literal[False] = ...,
) -> FloatArray: ...
@overload
def stationary_cost(
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
    rho_F: ArrayLike | None = ...,
    return_reason: Literal[True],
) -> tuple[FloatArray, Any]: ...
@np.errstate(over="ignore", invalid="ignore")  # near the double range: inf/NaN, not warnings
def stationary_cost(
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
    rho_F: ArrayLike | None = None,
    return_reason: bool = False,
) -> FloatArray | tuple[FloatArray, Any]:
    """Stationary E||e||^2 by discrete Lyapunov; NaN where the augmented system
    is not Schur stable (:func:`svrobs_core.norms.schur_stable`). -> (...)

    Blockwise: ``X = A X A^T + Qxx`` (true system, solved once), the cross
    block ``S = A S F^T + (-A X dA^T + Qxe)`` (Stein-Sylvester, batched) and
    the e block ``E = F E F^T + dA X dA^T - F S^T dA^T - dA S F^T + Qee``
    (batched); ``J = trace E``. The augmented matrix is block triangular, so
    it is Schur stable iff ``rho(A) < 1`` and ``rho(F) < 1``; otherwise the
    value is NaN with reason ``"unstable"`` (``"non-finite input"`` for NaN
    inputs, :data:`svrobs_core.norms.REASON_BOUNDARY` for a radius within
    UNIT_CIRCLE_TOL below 1 or one rounding could put there: stability is decided
    on :func:`svrobs_core.norms.stability_radius`). ``rho_F``: optional precomputed
    ``stability_radius`` of ``F = A~ - L C`` (saves the batched eigenvalue call). ``return_reason=True``
    gives ``(value, reason)``, reason an object array of None / str (a plain
    object for one cell).
    """
    c = CostCells(
        A, B, A_tilde, B_tilde, L=L, C=C, sigma_u=sigma_u, sigma_w=sigma_w, sigma_v=sigma_v
    )
    batch = c.batch

    def tp(M: Array) -> Array:
        return np.swapaxes(M, -1, -2)

    F = c.F()
    rho_A = stability_radius(c.A)  # A's own batch (usually one system)
    if rho_F is None:
        rho_F = stability_radius(F)
    rho_F = np.asarray(rho_F, dtype=float)
    okA, okF = schur_stable(rho_A), schur_stable(rho_F)
    # unstable matrices are replaced by 0 so every solve is well posed; those
    # cells are set to NaN at the end
    A_s = np.where(okA[..., None, None], c.A, 0.0)
    F_s = np.where(okF[..., None, None], F, 0.0)
    Qxx, Qxe, Qee = c.Q_blocks()
    X = stein_solve(A_s, Qxx)  # x block, x batch only
    dA = c.dA()
    S = stein_solve(A_s, -c.A @ X @ tp(dA) + Qxe, Fr=F_s)
    Qe = dA @ X @ tp(dA) - F @ tp(S) @ tp(dA) - dA @ S @ tp(F) + Qee
    E = stein_solve(F_s, Qe)
    J = np.broadcast_to(np.trace(E, axis1=-2, axis2=-1), batch)
    rho = np.broadcast_to(np.fmax(rho_A, rho_F), batch)
    rho = np.where(
        np.isnan(np.broadcast_to(rho_A, batch)) | np.isnan(np.broadcast_to(rho_F, batch)),
        np.nan,
        rho,
    )
    stable = schur_stable(rho)
    lost = stable & ~np.isfinite(J)
    J = np.where(stable, J, np.nan)
    if return_reason:
        reason = stability_reason(None, rho=rho)
        if lost.any():
            reason = np.array(reason, dtype=object)
            reason[lost] = REASON_STATIONARY_LOST
            reason = reason.item() if reason.ndim == 0 else reason
        return J, reason
    return J


__all__ = [
    "REASON_STATIONARY_LOST",
    "REASON_UNSTABLE",
    "exact_cost",
    "j_star",
    "optimal_cost",
    "stationary_cost",
]
