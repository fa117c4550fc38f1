"""A second evaluation of the costs where rounding could have ruined the first
(docs/science.md#61-exact-finite-horizon-j_exact).

The doubling of :func:`svrobs_core.cost.exact_cost` carries a first-order bound on
its rounding error (:class:`DoublingRounding`). Where that bound exceeds ``SUSPECT_RTOL`` of the value (a
strongly non-normal system: its powers grow by orders of magnitude before they
decay, and the covariances cancel), each suspect cell is evaluated again by other
recursions, with other rounding:

* ``J_exact`` by the step-by-step recursion ``Sigma_{k+1} = Acal Sigma_k Acal^T + Q``;
* ``J_stationary`` (the Kronecker solves of :func:`svrobs_core.cost.stationary_cost`)
  by the squared Smith iteration ``S_2t = S_t + P_t S_t P_t^T``, ``P_2t = P_t^2``.

A value that its second evaluation does not confirm to ``AGREE_RTOL`` is dropped
with :data:`REASON_ROUNDING`. The bound is loose (norms, not the matrices), so most
suspect cells are confirmed; the second evaluations run on those cells only.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from .array_types import Array, BoolArray, FloatArray

U = np.finfo(float).eps / 2  # unit roundoff
SUSPECT_RTOL = 1e-8
SLOW_RHO = 1e-3
AGREE_RTOL = 1e-8
REASON_ROUNDING = (
    "rounding: two evaluations in doubles disagree (a strongly non-normal system, "
    "whose covariances cancel)"
)
# the Smith iteration's steps: 2^60 time steps, converged for rho <= 1 - 1e-17
_SMITH_STEPS = 60


class DoublingRounding:
    """First-order bounds on the absolute error (Frobenius) of each block of each
    power, Sigma and W that :func:`svrobs_core.cost.exact_cost` computes, from the
    norms of the blocks each product multiplies: a computed product ``fl(X Y)`` is
    within ``gamma_k |X| |Y|`` of ``X Y``, whose Frobenius norm is at most ``gamma_k
    ||X|| ||Y||`` (Higham, Accuracy and Stability of Numerical Algorithms, section
    3.5). Block by block (power ``[[Pa, 0], [Pr, Pf]]``, covariance ``[[Mx, Mxe],
    [Mxe^T, Me]]``), so that the e block's error is not charged with the x block's
    size where the coupling ``Pr`` is small. ``ops``: the doubling's layout (its
    ``norm`` of blocks). A few norms per doubling step."""

    def __init__(self, ops: Any, n: int) -> None:
        self.ops = ops
        self.g = 2 * (2 * n + 2) * U  # two products of inner size up to 2n, and the sums

    def norms(self, blocks: tuple[Any, ...]) -> tuple[Any, ...]:
        """Each block's Frobenius norm (0 for a block not kept). -> (S, N|1) each"""
        return tuple(0.0 if b is None else self.ops.norm((b,), (1,)) for b in blocks)

    def square(self, P: tuple[Any, ...], eP: tuple[Array, ...]) -> tuple[Array, ...]:
        """The errors of the squared power's blocks ``(Pa^2, Pr Pa + Pf Pr, Pf^2)``."""
        (a, r, f), (ea, er, ef), g = self.norms(P), eP, self.g
        return (
            2 * a * ea + g * a * a,
            r * ea + (a + f) * er + r * ef + g * (r * a + f * r),
            2 * f * ef + g * f * f,
        )

    def join(
        self,
        P: tuple[Any, ...],
        eP: tuple[Array, ...],
        Ma: tuple[Any, ...],
        eMa: tuple[Array, ...],
        Mb: tuple[Any, ...],
        eMb: tuple[Array, ...],
        t_b: int,
    ) -> tuple[Array, ...]:
        """The (S, N) errors of the blocks (xx, xe, ee) of (Sigma, W) of segment a
        (power P, stacked Ma) followed by segment b (Mb, length t_b): ``Ma + P Mb
        P^T``, and ``t_b Sigma_a`` in W (see ``cost._join``)."""
        (a, r, f), (ea, er, ef), g = self.norms(P), eP, self.g
        x, xe, e = self.norms(Mb)
        ex, exe, ee = eMb
        # the blocks of P Mb P^T (cost._congruence) and their errors
        c_xx = a * a * x
        c_xe = a * (x * r + xe * f)
        c_ee = r * r * x + 2 * r * f * xe + f * f * e
        e_xx = 2 * a * x * ea + a * a * ex + g * c_xx
        e_xe = ea * (x * r + xe * f) + a * (ex * r + x * er + exe * f + xe * ef) + g * c_xe
        e_ee = (
            2 * er * (x * r + xe * f)
            + 2 * ef * (xe * r + e * f)
            + r * r * ex
            + 2 * r * f * exe
            + f * f * ee
            + g * c_ee
        )
        out = []
        for m, em, c, ec in zip(self.norms(Ma), eMa, (c_xx, c_xe, c_ee), (e_xx, e_xe, e_ee)):
            err = em + ec + 2 * U * (m + c)
            # W_{a+b} also takes t_b Sigma_a, with its error (stack index 1 is W)
            w = err[1:] + t_b * (em[:1] + 2 * U * m[:1])
            out.append(np.concatenate([err[:1], w], axis=0))
        return tuple(out)


def suspect(J: FloatArray, err: FloatArray) -> BoolArray:
    """The finite values whose rounding bound exceeds SUSPECT_RTOL of them."""
    with np.errstate(invalid="ignore"):
        out: BoolArray = np.isfinite(J) & ~(err <= SUSPECT_RTOL * np.abs(J))
        return out


def augmented(
    A: FloatArray,
    B: FloatArray,
    A_tilde: FloatArray,
    B_tilde: FloatArray,
    L: FloatArray,
    C: FloatArray,
    sigma_u: FloatArray,
    sigma_w: FloatArray,
    sigma_v: FloatArray,
) -> tuple[FloatArray, FloatArray]:
    """(Acal, Q) of each cell: ``s = [x; e]``, ``s+ = Acal s + noise``, Cov noise = Q
    (docs/science.md#6-observer-cost-j). Each matrix (k, ., .) or one (., .)."""
    # in extended precision where the platform has it (x86: 64-bit significands), so
    # that the inputs' own rounding (A_tilde - L C) is not repeated
    A, B, A_tilde, B_tilde, L, C = (  # type: ignore[assignment]
        np.asarray(M, dtype=np.longdouble) for M in (A, B, A_tilde, B_tilde, L, C)
    )
    k, n = A_tilde.shape[0], A.shape[-1]
    su, sw, sv = (
        np.broadcast_to(np.asarray(s, dtype=np.longdouble), (k,))[:, None, None]
        for s in (sigma_u, sigma_w, sigma_v)
    )
    Ab = np.broadcast_to(A, (k, n, n))
    Bb = np.broadcast_to(B, (k,) + B.shape[-2:])
    top = np.concatenate([Ab, np.zeros((k, n, n), dtype=A.dtype)], axis=-1)
    bottom = np.concatenate([A_tilde - Ab, A_tilde - L @ C], axis=-1)
    Acal = np.concatenate([top, bottom], axis=-2)
    I = np.broadcast_to(np.eye(n, dtype=A.dtype), (k, n, n))
    G = np.concatenate(
        [
            np.concatenate([su * Bb, sw * I, np.zeros((k, n, C.shape[-2]), dtype=A.dtype)], -1),
            np.concatenate([-su * (Bb - B_tilde), -sw * I, sv * L], -1),
        ],
        axis=-2,
    )
    return Acal, G @ np.swapaxes(G, -1, -2)


@np.errstate(over="ignore", invalid="ignore")
def exact_by_steps(Acal: FloatArray, Q: FloatArray, n: int, horizon: int) -> FloatArray:
    """J over ``horizon`` steps by the step-by-step recursion, per cell. -> (k,)"""
    S = np.zeros_like(Q)
    total = np.zeros(Q.shape[0], dtype=Q.dtype)
    At = np.swapaxes(Acal, -1, -2)
    for _ in range(horizon):
        S = Acal @ S @ At + Q
        total += np.trace(S[:, n:, n:], axis1=-2, axis2=-1)
    out: FloatArray = (total / horizon).astype(float)
    return out


@np.errstate(over="ignore", invalid="ignore")
def stationary_by_smith(Acal: FloatArray, Q: FloatArray, n: int) -> FloatArray:
    """The stationary e block's trace by the squared Smith iteration, per cell. -> (k,)"""
    S, P = Q.copy(), Acal.copy()
    for _ in range(_SMITH_STEPS):
        S_next = S + P @ S @ np.swapaxes(P, -1, -2)
        if np.array_equal(S_next, S):  # converged to the last bit (or NaN: not equal)
            break
        S, P = S_next, P @ P
    out: FloatArray = np.trace(S[:, n:, n:], axis1=-2, axis2=-1).astype(float)
    return out


def unconfirmed(
    A: FloatArray,
    B: FloatArray,
    A_tilde: FloatArray,
    B_tilde: FloatArray,
    *,
    L: FloatArray,
    C: FloatArray,
    sigma_u: float | FloatArray,
    sigma_w: float | FloatArray,
    sigma_v: float | FloatArray,
    horizon: int,
    J: FloatArray,
    err: FloatArray,
    J_stat: FloatArray,
    rho: float | FloatArray = 0.0,
) -> tuple[BoolArray, BoolArray]:
    """(J_exact, J_stationary) cells, bool of J's shape, that a second evaluation
    does not confirm: only the :func:`suspect` ones are evaluated again, and the
    stationary costs of those, of a decision radius ``rho`` (the larger of A's and
    F's) within SLOW_RHO of 1, or below the finite horizon's mean. Each matrix is one
    (n, .) or batched as J."""
    batch, n = J.shape, A.shape[-1]
    bad_exact = np.zeros(batch, dtype=bool)
    bad_stat = np.zeros(batch, dtype=bool)
    sus = suspect(J, err)
    with np.errstate(invalid="ignore"):
        # the stationary solve has no bound of its own: it is evaluated again with a
        # suspect J_exact, near the boundary, or below the finite horizon's mean
        # (Sigma_k grows to its limit, so the limit is at least the mean)
        slow = np.broadcast_to(np.asarray(rho, dtype=float), batch) > 1.0 - SLOW_RHO
        low = J_stat < np.abs(J) * (1.0 - AGREE_RTOL)
        sus_stat = np.isfinite(J_stat) & (sus | slow | low | ~(J_stat >= 0))
    idx = np.flatnonzero(sus | sus_stat)
    if idx.size == 0:
        return bad_exact, bad_stat

    def cells(M: FloatArray) -> FloatArray:
        size = (int(np.prod(batch)),) + M.shape[-2:]  # explicit: m = 0 has no -1
        out: FloatArray = np.broadcast_to(M, batch + M.shape[-2:]).reshape(size)
        return out[idx]

    su, sw, sv = (np.broadcast_to(s, batch).reshape(-1)[idx] for s in (sigma_u, sigma_w, sigma_v))
    Acal, Q = augmented(cells(A), cells(B), cells(A_tilde), cells(B_tilde), cells(L), C, su, sw, sv)
    flat_e, flat_s = bad_exact.reshape(-1), bad_stat.reshape(-1)
    e = sus.reshape(-1)[idx]
    if e.any():
        first = J.reshape(-1)[idx[e]]
        flat_e[idx[e]] = ~confirmed(first, exact_by_steps(Acal[e], Q[e], n, horizon))
    stat = J_stat.reshape(-1)[idx]
    has = sus_stat.reshape(-1)[idx]
    if has.any():
        smith = stationary_by_smith(Acal[has], Q[has], n)
        flat_s[idx[has]] = ~confirmed(stat[has], smith)
    return bad_exact, bad_stat


def confirmed(first: FloatArray, second: FloatArray) -> BoolArray:
    """Whether a second evaluation confirms the first to AGREE_RTOL."""
    with np.errstate(invalid="ignore"):
        out: BoolArray = np.abs(first - second) <= AGREE_RTOL * np.abs(first)
        return out


__all__ = [
    "AGREE_RTOL",
    "DoublingRounding",
    "REASON_ROUNDING",
    "SUSPECT_RTOL",
    "augmented",
    "confirmed",
    "exact_by_steps",
    "stationary_by_smith",
    "suspect",
    "unconfirmed",
]
