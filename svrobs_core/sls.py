"""SLS sub-optimal observer J_opt (docs/science.md#8-sls-sub-optimal-observer-j_opt).

The program (paper, section 5, "Results on Sub-Optimal Observer Analysis")::

    J_opt = min  F ||Phi_w||_H2 + ||Phi_w K - Phi_v||_H2
            s.t. ||Phi_w||_H2 <= C_bound
                 Phi_w (zI - A_tilde) + Phi_v C = I        (see "Sign convention")
                 Phi_w, Phi_v strictly proper FIR of length T_fir

with the FIR truncation ``Phi(z) = sum_{t=1..T_fir} Phi[t] z^-t`` and
``||Phi||_H2 = sqrt(sum_t ||Phi[t]||_F^2)``.

Sign convention (docs/science.md#8-sls-sub-optimal-observer-j_opt)
-----------------------------------------------------------------
The paper defines ``Phi_w = (zI - A_tilde + LC)^-1`` and ``Phi_v = Phi_w L``
(used in Lemma 3 / Theorem 3, whose cost term is ``Phi_w K - Phi_v =
Phi_w (K - L)``, zero at ``L = K``). Those definitions satisfy
``Phi_w (zI - A_tilde + LC) = I``, i.e. ``Phi_w (zI - A_tilde) + Phi_v C = I``.
The paper's SLS program writes the affine constraint with ``- Phi_v C``;
expanding it in z^-t gives the recursion
``Phi_w[t+1] = Phi_w[t] A_tilde + Phi_v[t] C``. Under that literal reading
the feasible ``Phi_v`` of a static gain L is ``-Phi_w L``, so the objective
term becomes ``Phi_w (K + L)``: it does not vanish at ``L = K`` and is
inconsistent with Theorem 3 (the impulse response of the paper's own
``(Phi_w, Phi_w L)`` violates the literal constraints; see the tests).

We therefore implement the reading consistent with the paper's definitions::

    Phi_w[1]   = I
    Phi_w[t+1] = Phi_w[t] A_tilde - Phi_v[t] C          (t = 1..T_fir-1)
    0          = Phi_w[T_fir] A_tilde - Phi_v[T_fir] C   (FIR terminal condition)

so a static gain L with nilpotent ``A_tilde - LC`` gives exactly
``Phi_w[t] = (A_tilde - LC)^(t-1)``, ``Phi_v[t] = (A_tilde - LC)^(t-1) L``, and
the objective equals ``F ||Phi_w||_H2 + ||Phi_w (K - L)||_H2`` (Theorem 3's
terms). Equivalently: the paper's literal program with ``Phi_v`` replaced by
``-Phi_v``; only the sign of the ``Phi_v`` term in the objective differs.

Feasibility: the terminal condition forces the error dynamics to be
deadbeat within T_fir steps, so the program is feasible only when every
unobservable mode of ``(A_tilde, C)`` is at 0 and T_fir is at least the
observability index (always, for T_fir >= 1, when C = I). Otherwise the
status is ``"infeasible"``. ``||Phi_w||_H2 >= ||Phi_w[1]||_F = sqrt(n)``, so
``C_bound < sqrt(n)`` is always infeasible and ``J_opt >= F sqrt(n)``.

Performance: one cvxpy problem per (n, p, T_fir, bounded) is compiled with
``cp.Parameter`` for A_tilde, C, K, F, C_bound (DPP) and cached per thread;
later cells only set parameter values and re-solve with Clarabel.
"""

from __future__ import annotations

import math
import threading
import time
import warnings
from dataclasses import dataclass
from typing import TYPE_CHECKING

import cvxpy as cp
import numpy as np
from numpy.typing import ArrayLike

from .array_types import Array, FloatArray
from .errors import check_matrix

if TYPE_CHECKING:
    from .cost_bound import TrueSystemNorms

SQRT2 = math.sqrt(2.0)

#: cvxpy statuses for which J_opt is reported as a number.
SOLVED_STATUSES = ("optimal", "optimal_inaccurate")

#: reasons returned by :func:`jopt_upper_bound` where the bound is null.
REASON_CONDITION = "J_opt bound: condition eps_A*||(zI-A+KC)^-1||_Hinf <= 1/2 fails"
REASON_UNDEFINED = "J_opt bound: undefined input (NaN/inf, e.g. unstable transfer matrix)"


@dataclass(kw_only=True)
class SLSResult:
    """Outcome of one SLS program.

    J_opt: optimal value, NaN unless ``status`` is in :data:`SOLVED_STATUSES`.
    status: the cvxpy status ("optimal", "optimal_inaccurate", "infeasible",
        "unbounded", ...), ``"solver_error"`` when the solver raised, or
        ``"invalid_input"`` when an input was NaN/inf.
    solve_time: wall-clock seconds of this call (parameter update + cvxpy
        solve; includes the one-off compilation on the first call of a shape).
    Phi_w: (T_fir, n, n), ``Phi_w[t-1]`` is the coefficient of z^-t; None unless solved.
    Phi_v: (T_fir, n, p), same indexing; None unless solved.
    L: (n, p) ``Phi_v[1]``, the first Markov parameter. With ``Phi_w[1] = I``
        this equals the static gain whenever the optimal response is generated
        by one (``Phi_v = Phi_w L``); in general the SLS observer is dynamic
        (``L(z) = Phi_w^-1 Phi_v``) and this is only its leading term.
    """

    J_opt: float
    status: str
    solve_time: float
    Phi_w: FloatArray | None = None
    Phi_v: FloatArray | None = None
    L: FloatArray | None = None


@dataclass(kw_only=True)
class _Compiled:
    problem: cp.Problem
    A: cp.Parameter
    C: cp.Parameter
    K: cp.Parameter
    F: cp.Parameter
    C_bound: cp.Parameter | None
    Phi_w: cp.Variable  # (T_fir*n, n): block t-1 holds Phi_w[t]
    Phi_v: cp.Variable  # (T_fir*n, p)


_local = threading.local()


def _build(n: int, p: int, T: int, bounded: bool) -> _Compiled:
    A = cp.Parameter((n, n), name="A_tilde")
    C = cp.Parameter((p, n), name="C")
    K = cp.Parameter((n, p), name="K")
    F = cp.Parameter(nonneg=True, name="F")
    Cb = cp.Parameter(name="C_bound") if bounded else None
    Pw = cp.Variable((T * n, n), name="Phi_w")
    Pv = cp.Variable((T * n, p), name="Phi_v")
    s = cp.Variable(name="h2_Phi_w")
    # Right-multiplying the stacked blocks applies A / C to every block at once:
    # block t of S is Phi_w[t] A - Phi_v[t] C.
    S = Pw @ A - Pv @ C
    cons = [
        Pw[:n] == np.eye(n),
        S[-n:] == 0,
        # cvxpy's stubs lack its atoms' re-exports (norm, vec)
        cp.norm(cp.vec(Pw, order="F"), 2) <= s,  # type: ignore[attr-defined]
    ]
    if T > 1:
        cons.append(Pw[n:] == S[:-n])
    if bounded:
        cons.append(s <= Cb)
    obj = F * s + cp.norm(cp.vec(Pw @ K - Pv, order="F"), 2)  # type: ignore[attr-defined]  # as above
    prob = cp.Problem(cp.Minimize(obj), cons)
    if not prob.is_dpp():  # pragma: no cover - guards the parameterised fast path
        raise RuntimeError("SLS program is not DPP; re-solves would recompile")
    return _Compiled(problem=prob, A=A, C=C, K=K, F=F, C_bound=Cb, Phi_w=Pw, Phi_v=Pv)


def _compiled(n: int, p: int, T: int, bounded: bool) -> _Compiled:
    cache: dict[tuple[int, int, int, bool], _Compiled] | None = getattr(_local, "cache", None)
    if cache is None:
        cache = _local.cache = {}
    key = (n, p, T, bounded)
    if key not in cache:
        cache[key] = _warm(_build(n, p, T, bounded), n, p)
    return cache[key]


def _warm(pr: _Compiled, n: int, p: int) -> _Compiled:
    """Solve a freshly compiled program once with fixed values, result discarded.

    cvxpy's first solve of a DPP program canonicalises it with the parameter
    values in place; later solves map the parameters through the cached
    reduction. The two give problem data that differ in the last bits, so
    without this the J_opt of a cell would depend on whether it was the first
    solve of its process: after it every cell takes the
    cached path, and its J_opt is the same however the grid is split."""
    pr.A.value = 0.5 * np.eye(n)
    pr.C.value = np.eye(p, n)
    pr.K.value = np.zeros((n, p))
    pr.F.value = 1.0
    if pr.C_bound is not None:
        pr.C_bound.value = 1e3
    try:
        pr.problem.solve(solver=cp.CLARABEL)  # type: ignore[no-untyped-call]  # cvxpy: untyped
    except (cp.error.SolverError, ValueError, ArithmeticError):  # pragma: no cover
        pass
    return pr


def clear_cache() -> None:
    """Drop this thread's compiled problems."""
    _local.cache = {}


def sls_observer(
    A_tilde: ArrayLike,
    C: ArrayLike,
    K: ArrayLike,
    F: float,
    *,
    C_bound: float | None,
    T_fir: int = 30,
) -> SLSResult:
    """Solve the FIR SLS program (docs/science.md#8-sls-sub-optimal-observer-j_opt).

    A_tilde (n, n) estimated A; C (p, n); K (n, p) optimal (Kalman predictor)
    gain; F >= 0 the scalar of :func:`sls_F`; C_bound the bound on
    ``||Phi_w||_H2`` (``None`` or ``inf``: no bound); T_fir >= 1.

    Never raises for numerical reasons: infeasibility, solver failure or
    NaN/inf data give ``J_opt = NaN`` with the status. Raises ValueError only
    for wrong shapes, ``T_fir < 1`` or ``F < 0``.
    """
    t0 = time.perf_counter()
    A_tilde = check_matrix("A_tilde", A_tilde, ("n", "n"), batch=False)
    n = A_tilde.shape[0]
    C = check_matrix("C", C, ("p", n), batch=False)
    p = C.shape[0]
    K = check_matrix("K", K, (n, p), batch=False)
    T = int(T_fir)
    if T < 1 or T != T_fir:
        raise ValueError(f"T_fir must be an integer >= 1, got {T_fir!r}")
    F = float(F)
    if F < 0:
        raise ValueError(f"F must be >= 0, got {F}")
    bound = None if C_bound is None else float(C_bound)
    if bound is not None and bound == math.inf:
        bound = None

    finite = all(np.all(np.isfinite(x)) for x in (A_tilde, C, K)) and math.isfinite(F)
    if not finite or (bound is not None and math.isnan(bound)):
        return SLSResult(
            J_opt=math.nan, status="invalid_input", solve_time=time.perf_counter() - t0
        )

    pr = _compiled(n, p, T, bound is not None)
    pr.A.value = A_tilde
    pr.C.value = C
    pr.K.value = K
    pr.F.value = F
    if bound is not None and pr.C_bound is not None:  # a bounded program has the parameter
        pr.C_bound.value = bound
    try:
        with warnings.catch_warnings():  # "Solution may be inaccurate": it is the status
            warnings.filterwarnings("ignore", message="Solution may be inaccurate")
            pr.problem.solve(solver=cp.CLARABEL)  # type: ignore[no-untyped-call]  # cvxpy: untyped
        status = str(pr.problem.status)
    except (cp.error.SolverError, ValueError, ArithmeticError):
        status = "solver_error"
    dt = time.perf_counter() - t0

    if status not in SOLVED_STATUSES or pr.Phi_w.value is None or pr.Phi_v.value is None:
        return SLSResult(J_opt=math.nan, status=status, solve_time=dt)
    value = float(pr.problem.value)
    if not math.isfinite(value):
        return SLSResult(J_opt=math.nan, status=status, solve_time=dt)
    Phi_w = np.array(pr.Phi_w.value).reshape(T, n, n)
    Phi_v = np.array(pr.Phi_v.value).reshape(T, n, p)
    return SLSResult(
        J_opt=value, status=status, solve_time=dt, Phi_w=Phi_w, Phi_v=Phi_v, L=Phi_v[0].copy()
    )


def _out(x: ArrayLike) -> float | FloatArray:
    """0-d -> Python float, else ndarray."""
    x = np.asarray(x, dtype=float)
    return float(x) if x.ndim == 0 else x


def default_C_bound(K: ArrayLike, h2_closed_loop_inv: ArrayLike) -> float | FloatArray:
    """The default ``C_bound = 2 (1 + ||K||) ||(zI - A + KC)^-1||_H2``.

    K (..., n, p) (spectral norm over the last two axes); the caller passes
    the H2 norm of the true closed loop ``(zI - A + KC)^-1`` (NaN propagates).
    Broadcasts; a scalar result is a float.
    """
    K = check_matrix("K", K, ("n", "p"))
    finite = np.isfinite(K).all(axis=(-2, -1))
    # numpy's stubs: the np.bool_ of a 2-D K indexes as a 0-d array does
    where = finite[..., None, None]  # type: ignore[index]
    k_norm = np.linalg.norm(np.where(where, K, 0.0), ord=2, axis=(-2, -1))
    k_norm = np.where(finite, k_norm, np.nan)
    return _out(2.0 * (1.0 + k_norm) * np.asarray(h2_closed_loop_inv, dtype=float))


def eps_max(eps_A: ArrayLike, eps_B: ArrayLike) -> FloatArray:
    """``eps1 = max(eps_A, eps_B)`` of :func:`sls_F` and :func:`jopt_upper_bound`: null
    (NaN) when either bound is (docs/science.md#8-sls-sub-optimal-observer-j_opt)."""
    out: FloatArray = np.maximum(np.asarray(eps_A, dtype=float), np.asarray(eps_B, dtype=float))
    return out


def sls_F(
    eps1: ArrayLike,
    hinf_AB: ArrayLike,
    hinf_AK: ArrayLike,
    *,
    sigma_u: ArrayLike,
    sigma_v: ArrayLike,
) -> float | FloatArray:
    """``F = sqrt(2) eps1 (||[Phi_A B; I]||_Hinf sigma_u + ||[Phi_A K; I]||_Hinf sigma_v)``.

    Broadcasts over arrays; NaN propagates; a scalar result is a float.
    """
    eps1, hAB, hAK, su, sv = (
        np.asarray(v, dtype=float) for v in (eps1, hinf_AB, hinf_AK, sigma_u, sigma_v)
    )
    return _out(SQRT2 * eps1 * (hAB * su + hAK * sv))


def jopt_upper_bound(
    eps_A: ArrayLike,
    eps1: ArrayLike,
    C_bound: ArrayLike,
    *,
    hinf_AB: ArrayLike,
    hinf_AK: ArrayLike,
    sigma_u: ArrayLike,
    sigma_v: ArrayLike,
    h2_cl_inv: ArrayLike,
    hinf_cl_inv: ArrayLike,
) -> tuple[float | FloatArray, str | None | Array]:
    """The paper's bound on J_opt, where its condition holds.

    ``eps1 (sqrt(2) C_bound (||[Phi_A B; I]||_Hinf sigma_u + ||[Phi_A K; I]||_Hinf sigma_v)
    + 2 ||(zI - A + KC)^-1||_H2 sigma_v)`` when
    ``eps_A ||(zI - A + KC)^-1||_Hinf <= 1/2``
    (docs/science.md#8-sls-sub-optimal-observer-j_opt: the paper's
    ``||zI - A + KC||`` read as the norm of the inverse). The paper states it
    for ``C_bound >= 2 (1 + ||K||) ||(zI - A + KC)^-1||_H2``; this function
    evaluates the formula at the C_bound given and does not check that.

    Returns ``(value, reason)``. Scalar inputs: ``value`` a float (NaN where
    null) and ``reason`` None or one of :data:`REASON_CONDITION`,
    :data:`REASON_UNDEFINED`. Array inputs broadcast: ``value`` an ndarray and
    ``reason`` an object ndarray of the same shape holding None or the reason.
    """
    args = np.broadcast_arrays(
        *[
            np.asarray(v, dtype=float)
            for v in (
                eps_A,
                eps1,
                C_bound,
                hinf_AB,
                hinf_AK,
                sigma_u,
                sigma_v,
                h2_cl_inv,
                hinf_cl_inv,
            )
        ]
    )
    eA, e1, Cb, hAB, hAK, su, sv, h2, hinf = args
    with np.errstate(invalid="ignore", over="ignore"):
        value = e1 * (SQRT2 * Cb * (hAB * su + hAK * sv) + 2.0 * h2 * sv)
        cond_val = eA * hinf
    defined = np.ones(value.shape, dtype=bool)
    for a in args:
        defined &= np.isfinite(a)
    holds = defined & (cond_val <= 0.5)
    value = np.where(holds, value, np.nan)
    reason = np.full(value.shape, None, dtype=object)
    reason[defined & ~holds] = REASON_CONDITION
    reason[~defined] = REASON_UNDEFINED
    if value.ndim == 0:
        return float(value), reason[()]
    return value, reason


def jopt_upper_bound_from_norms(
    eps_A: ArrayLike,
    eps1: ArrayLike,
    C_bound: ArrayLike,
    norms: TrueSystemNorms,
    *,
    sigma_u: ArrayLike,
    sigma_v: ArrayLike,
) -> tuple[float | FloatArray, str | None | Array]:
    """:func:`jopt_upper_bound` with the four norms taken from ``norms``, a
    :class:`~svrobs_core.cost_bound.TrueSystemNorms` (of the true system, or of
    the estimate per cell). -> ``(value, reason)``"""
    return jopt_upper_bound(
        eps_A,
        eps1,
        C_bound,
        hinf_AB=norms.hinf_PhiA_B,
        hinf_AK=norms.hinf_PhiA_K,
        sigma_u=sigma_u,
        sigma_v=sigma_v,
        h2_cl_inv=norms.h2_closed,
        hinf_cl_inv=norms.hinf_closed,
    )
