"""H2 and H-infinity norms of discrete transfer matrices H (zI - F)^-1 G (+ D),
batched; unstable F gives NaN (docs/science.md#7-cost-bound-theorem-3).

Every function takes leading batch dimensions ``...`` (numpy broadcasting
between the arguments) and returns an array of the broadcast batch shape (a
0-d array for a single system).

NaN semantics: a transfer matrix whose ``F`` is not Schur stable
(``rho(F) >= 1``) has no finite H2 / H-infinity norm here; its value is NaN and
its reason is :data:`REASON_UNSTABLE`. Stability is decided by
:func:`schur_stable` of :func:`stability_radius`: a computed ``rho(F)`` within
:data:`UNIT_CIRCLE_TOL` of 1, or one that rounding could put there, counts as the
boundary (NaN, :data:`REASON_BOUNDARY`). A non-finite ``F``
(e.g. a gain that could not be designed) gives NaN with
:data:`REASON_NONFINITE`. Callers turn NaN into ``null`` and put the reason in
``notes``: pass ``return_reason=True`` to get ``(value, reason)``, where
``reason`` has the batch shape, dtype object, entries ``None`` (finite value)
or one of the strings (a plain Python object, not an array, for a single
system).
"""

from __future__ import annotations

from typing import Any, Literal, overload

import numpy as np
from numpy.typing import ArrayLike

from .array_types import Array, BoolArray, FloatArray
from .errors import check_matrix
from .linalg import solve as _solve
from .radius_bound import radius_upper_bound

# A matrix counts as Schur stable only when its computed spectral radius is below
# 1 - UNIT_CIRCLE_TOL (docs/science.md#62-stationary-j_stationary). The computed radius of
# a matrix on the unit circle (rho = 1 exactly: a stochastic matrix, det 1 with |trace| < 2)
# lands a few ulps (times the eigenvalue's condition) on either side of 1, and as rho -> 1
# the Stein solves and the H-infinity peak lose accuracy (relative error ~ u / (1 - rho),
# 1e-6 at 1 - 1e-10): such a matrix has no stationary covariance or system norm here.
UNIT_CIRCLE_TOL = 1e-10
REASON_UNSTABLE = "unstable"
REASON_BOUNDARY = (
    f"on the stability boundary (rho not below 1 - {UNIT_CIRCLE_TOL:g} up to rounding)"
)
REASON_NONFINITE = "non-finite input"

# Kronecker (vectorised LU) solves of the Stein equation are used while the
# number of unknowns n*nr is at most this; above it, squared Smith iteration.
_KRON_MAX_UNKNOWNS = 144
# Bytes of temporaries one vectorised chunk may allocate (Kronecker, H-inf grid).
_CHUNK_BYTES = 64 * 2**20


# --------------------------------------------------------------------------
# spectral radius / Schur stability
# --------------------------------------------------------------------------
def spectral_radius(F: ArrayLike) -> FloatArray:
    """max |eig(F)| over the last two axes, batched; NaN where F has a non-finite
    entry. -> (...)"""
    F = np.asarray(F, dtype=float)
    if F.shape[-1] == 0:
        return np.zeros(F.shape[:-2])
    finite = np.isfinite(F).all(axis=(-2, -1))
    Fs = np.where(finite[..., None, None], F, 0.0)
    rho = np.abs(np.linalg.eigvals(Fs)).max(axis=-1)
    return np.where(finite, rho, np.nan)


def stability_radius(F: ArrayLike) -> FloatArray:
    """The radius that decides F's stability: the computed rho(F), or ``1 -
    UNIT_CIRCLE_TOL / 2`` (the boundary) where it is below ``1 - UNIT_CIRCLE_TOL``
    but an upper bound on the exact radius is not (:mod:`svrobs_core.radius_bound`:
    rounding cannot decide); NaN for a non-finite F. -> (...)"""
    rho, hi = radius_upper_bound(F, decide=1.0 - UNIT_CIRCLE_TOL)
    undecided = schur_stable(rho) & ~schur_stable(hi)
    decided: FloatArray = np.where(undecided, 1.0 - UNIT_CIRCLE_TOL / 2, rho)
    return decided


def schur_stable(rho: ArrayLike) -> BoolArray:
    """The computed spectral radius ``rho`` is below ``1 - UNIT_CIRCLE_TOL``: the one
    stability test of every quantity that exists only for a Schur-stable matrix
    (False for NaN). -> (...) bool"""
    with np.errstate(invalid="ignore"):
        stable: BoolArray = np.asarray(rho, dtype=float) < 1.0 - UNIT_CIRCLE_TOL
        return stable


def is_schur(F: ArrayLike) -> BoolArray:
    """:func:`schur_stable` of :func:`stability_radius` (False for non-finite F). -> (...) bool"""
    return schur_stable(stability_radius(F))


def stability_reason(
    F: ArrayLike | None,
    rho: ArrayLike | None = None,
    *,
    unstable: str = REASON_UNSTABLE,
    boundary: str = REASON_BOUNDARY,
) -> Any:
    """Reason array for F: None if :func:`schur_stable`, else ``unstable`` (rho >= 1),
    ``boundary`` (rho within UNIT_CIRCLE_TOL below 1) or REASON_NONFINITE. ``rho``
    may be a precomputed spectral radius. -> (...) object (Python object for a
    single system)."""
    if rho is None:
        assert F is not None, "stability_reason needs F or rho"
        rho = stability_radius(F)
    rho = np.asarray(rho, dtype=float)
    out = np.full(rho.shape, None, dtype=object)
    out[np.isnan(rho)] = REASON_NONFINITE
    with np.errstate(invalid="ignore"):
        out[~schur_stable(rho) & (rho < 1.0)] = boundary
        out[rho >= 1.0] = unstable
    return _unwrap0(out)


def _unwrap0(a: Any) -> Any:
    """0-d object array -> the Python object it holds."""
    if isinstance(a, np.ndarray) and a.ndim == 0 and a.dtype == object:
        return a.item()
    return a


# --------------------------------------------------------------------------
# Stein (discrete Lyapunov / Sylvester) equation, batched
# --------------------------------------------------------------------------
def stein_solve(
    F: ArrayLike, Q: ArrayLike, Fr: ArrayLike | None = None, *, multi_rhs: bool = False
) -> FloatArray:
    """Solve X = F X Fr^T + Q (Fr defaults to F), batched over leading dims.

    F (..., n, n), Fr (..., r, r), Q (..., n, r) -> X (..., n, r); with
    ``multi_rhs=True`` Q is (..., n, r, k), k right-hand sides sharing one
    factorisation, -> (..., n, r, k). The caller guarantees
    rho(F) rho(Fr) < 1 (no check here). Small problems (n*r <= 144) use one
    vectorised LU solve of (I - F kron Fr) vec(X) = vec(Q) per cell; larger
    ones use squared Smith iteration (vectorised).
    """
    F = np.asarray(F, dtype=float)
    Fr = F if Fr is None else np.asarray(Fr, dtype=float)
    Q = np.asarray(Q, dtype=float)
    if multi_rhs:
        return _stein_multi(F, Fr, Q)
    return _stein_multi(F, Fr, Q[..., None])[..., 0]


def _stein_multi(F: FloatArray, Fr: FloatArray, Q: FloatArray) -> FloatArray:
    n, r = F.shape[-1], Fr.shape[-1]
    k = Q.shape[-1]
    batch = np.broadcast_shapes(F.shape[:-2], Fr.shape[:-2], Q.shape[:-3])
    if n * r <= _KRON_MAX_UNKNOWNS:
        return _stein_kron(F, Fr, Q, batch, n=n, r=r, k=k)
    return _stein_smith(F, Fr, Q, batch)


def _stein_kron(
    F: FloatArray,
    Fr: FloatArray,
    Q: FloatArray,
    batch: tuple[int, ...],
    *,
    n: int,
    r: int,
    k: int,
) -> FloatArray:
    nr = n * r
    Nb = int(np.prod(batch, dtype=np.int64))
    Ff = F.reshape(-1, n, n)
    Frf = Fr.reshape(-1, r, r)
    Qf = np.broadcast_to(Q, batch + (n, r, k)).reshape(Nb, nr, k)
    if Ff.shape[0] == 1 and Frf.shape[0] == 1:
        # one operator for the whole batch: factor once, all cells as RHS columns
        M = np.eye(nr) - np.kron(Ff[0], Frf[0])
        X = _solve(M, np.moveaxis(Qf, 0, 1).reshape(nr, Nb * k))
        return np.moveaxis(X.reshape(nr, Nb, k), 1, 0).reshape(batch + (n, r, k))
    Ff = np.broadcast_to(F, batch + (n, n)).reshape(Nb, n, n)
    Frf = np.broadcast_to(Fr, batch + (r, r)).reshape(Nb, r, r)
    out = np.empty((Nb, nr, k))
    step = max(1, _CHUNK_BYTES // (8 * nr * nr * 2))
    diag = np.arange(nr)
    for s in range(0, Nb, step):
        e = min(Nb, s + step)
        # row-major vec: vec(F X Fr^T) = (F kron Fr) vec(X); M = I - F kron Fr
        M = np.einsum("bik,bjl->bijkl", Ff[s:e], Frf[s:e]).reshape(e - s, nr, nr)
        np.negative(M, out=M)
        M[:, diag, diag] += 1.0
        out[s:e] = _solve(M, Qf[s:e])
    return out.reshape(batch + (n, r, k))


def _stein_smith(
    F: FloatArray, Fr: FloatArray, Q: FloatArray, batch: tuple[int, ...], *, max_iter: int = 64
) -> FloatArray:
    """X = sum_i F^i Q Fr^iT by X <- X + P X Pr^T, P <- P^2 (squared Smith)."""
    X = np.array(np.broadcast_to(np.moveaxis(Q, -1, -3), batch + Q.shape[-1:] + Q.shape[-3:-1]))
    P = np.broadcast_to(F, batch + F.shape[-2:])[..., None, :, :]
    Pr = np.broadcast_to(Fr, batch + Fr.shape[-2:])[..., None, :, :]
    for _ in range(max_iter):
        X = X + P @ X @ np.swapaxes(Pr, -1, -2)
        P = P @ P
        Pr = Pr @ Pr
        small = np.abs(P).max() * np.abs(Pr).max()
        if not np.isfinite(small) or small < 1e-18:
            break
    return np.moveaxis(X, -3, -1)


# --------------------------------------------------------------------------
# H2
# --------------------------------------------------------------------------
def _broadcast_sys(
    F: ArrayLike, G: ArrayLike, H: ArrayLike, D: ArrayLike | None = None
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray | None, tuple[int, ...], int, int, int]:
    F = check_matrix("F", F, ("n", "n"))
    n = F.shape[-1]
    G = check_matrix("G", G, (n, "m"))
    H = check_matrix("H", H, ("p", n))
    m, p = G.shape[-1], H.shape[-2]
    shapes = [F.shape[:-2], G.shape[:-2], H.shape[:-2]]
    if D is not None:
        D = check_matrix("D", D, (p, m))
        shapes.append(D.shape[:-2])
    batch = np.broadcast_shapes(*shapes)
    return F, G, H, D, batch, n, m, p


def _finish(
    value: FloatArray, rho: FloatArray, return_reason: bool
) -> FloatArray | tuple[FloatArray, Any]:
    value = np.where(schur_stable(rho), value, np.nan)
    if return_reason:
        reason = np.asarray(stability_reason(None, rho=rho), dtype=object)
        reason[np.isnan(value) & (reason == None)] = REASON_NONFINITE
        return value, _unwrap0(reason)
    return value


@overload
def h2_norm(
    F: ArrayLike,
    G: ArrayLike,
    H: ArrayLike,
    *,
    rho: ArrayLike | None = ...,
    return_reason: Literal[False] = ...,
) -> FloatArray: ...
@overload
def h2_norm(
    F: ArrayLike,
    G: ArrayLike,
    H: ArrayLike,
    *,
    rho: ArrayLike | None = ...,
    return_reason: Literal[True],
) -> tuple[FloatArray, Any]: ...
def h2_norm(
    F: ArrayLike,
    G: ArrayLike,
    H: ArrayLike,
    *,
    rho: ArrayLike | None = None,
    return_reason: bool = False,
) -> FloatArray | tuple[FloatArray, Any]:
    """||H (zI-F)^-1 G||_H2 via the discrete Lyapunov Gramian; NaN unless F is
    :func:`schur_stable`.

    ``||.||_H2^2 = trace(H W H^T)``, ``W = F W F^T + G G^T``. F (..., n, n),
    G (..., n, m), H (..., p, n) -> (...). ``rho``: optional precomputed
    spectral radius of F (skips the eigenvalue computation). With
    ``return_reason=True`` returns ``(value, reason)`` (see module doc).
    """
    F, G, H, _, batch, n, _m, _p = _broadcast_sys(F, G, H)
    if rho is None:
        rho = stability_radius(F)
    rho = np.broadcast_to(np.asarray(rho, dtype=float), batch)
    stable = schur_stable(rho)
    # Replace unstable / non-finite cells by F = 0 so the solve stays harmless.
    if stable.all():
        Fs = F
    else:
        Fs = np.where(stable[..., None, None], np.broadcast_to(F, batch + (n, n)), 0.0)
    Gs = np.where(np.isfinite(G), G, 0.0)
    W = stein_solve(Fs, Gs @ np.swapaxes(Gs, -1, -2))
    HWH = np.einsum("...ij,...jk,...ik->...", H, W, H)
    value = np.sqrt(np.maximum(HWH, 0.0))
    value = np.where(np.isfinite(G).all(axis=(-2, -1)), value, np.nan)
    return _finish(value, rho, return_reason)


# --------------------------------------------------------------------------
# H-infinity
# --------------------------------------------------------------------------
_GOLD = (np.sqrt(5.0) - 1.0) / 2.0


def _sigma_max(F: Array, G: Array, H: Array, D: Array, *, w: Array) -> FloatArray:
    """sigma_max(H (e^{jw} I - F)^-1 G + D) for F (c,n,n) ... and w (c, k). -> (c, k);
    NaN where the response is not finite (a solve that overflowed or met a
    numerically singular e^{jw} I - F), so that hinf_norm is NaN there."""
    n = F.shape[-1]
    z = np.exp(1j * w)[..., None, None]
    M = z * np.eye(n) - F[:, None]
    with np.errstate(over="ignore", invalid="ignore"):
        R = _solve(M, np.broadcast_to(G[:, None], M.shape[:-1] + G.shape[-1:]))
        T = H[:, None] @ R + D[:, None]
    finite = np.isfinite(T).all(axis=(-2, -1))
    if finite.all():
        return np.linalg.svd(T, compute_uv=False)[..., 0]
    s = np.linalg.svd(np.where(finite[..., None, None], T, 0.0), compute_uv=False)[..., 0]
    out: FloatArray = np.where(finite, s, np.nan)
    return out


@overload
def hinf_norm(
    F: ArrayLike,
    G: ArrayLike,
    H: ArrayLike,
    D: ArrayLike | None = ...,
    *,
    grid: int = ...,
    peaks: int = ...,
    iters: int = ...,
    rho: ArrayLike | None = ...,
    return_reason: Literal[False] = ...,
) -> FloatArray: ...
@overload
def hinf_norm(
    F: ArrayLike,
    G: ArrayLike,
    H: ArrayLike,
    D: ArrayLike | None = ...,
    *,
    grid: int = ...,
    peaks: int = ...,
    iters: int = ...,
    rho: ArrayLike | None = ...,
    return_reason: Literal[True],
) -> tuple[FloatArray, Any]: ...
def hinf_norm(
    F: ArrayLike,
    G: ArrayLike,
    H: ArrayLike,
    D: ArrayLike | None = None,
    *,
    grid: int = 1024,
    peaks: int = 4,
    iters: int = 48,
    rho: ArrayLike | None = None,
    return_reason: bool = False,
) -> FloatArray | tuple[FloatArray, Any]:
    """sup_w sigma_max(H (e^jw I - F)^-1 G + D) on a refined grid; NaN unless F is
    :func:`schur_stable`.

    F (..., n, n), G (..., n, m), H (..., p, n), D (..., p, m) or None (zero)
    -> (...). Method: sigma_max on a uniform grid of ``grid`` frequencies over
    [0, pi] plus the angles of F's eigenvalues (so lightly damped resonances
    are not stepped over); then golden-section search (``iters`` steps, the
    bracket shrinks by 0.618^iters from two grid spacings, i.e. to ~1e-12 rad)
    on the brackets of the ``peaks`` largest local maxima of the grid. The
    result is the largest sigma_max evaluated (a lower bound that is accurate
    to far better than 1e-6 relative unless two peaks closer than a grid
    spacing are both missed). Real systems only (the response is conjugate
    symmetric, so [0, pi] suffices).
    """
    F, G, H, D, batch, n, m, p = _broadcast_sys(F, G, H, D)
    Nb = int(np.prod(batch, dtype=np.int64))
    if rho is None:
        rho = stability_radius(F)
    rho = np.broadcast_to(np.asarray(rho, dtype=float), batch)
    Ff = np.broadcast_to(F, batch + (n, n)).reshape(Nb, n, n)
    Gf = np.broadcast_to(G, batch + (n, m)).reshape(Nb, n, m)
    Hf = np.broadcast_to(H, batch + (p, n)).reshape(Nb, p, n)
    if D is None:
        Df = np.zeros((Nb, p, m))
    else:
        Df = np.broadcast_to(D, batch + (p, m)).reshape(Nb, p, m)
    ok = (
        schur_stable(rho.reshape(Nb))
        & np.isfinite(Gf).all((1, 2))
        & np.isfinite(Hf).all((1, 2))
        & np.isfinite(Df).all((1, 2))
    )
    out = np.full(Nb, np.nan)
    idx = np.flatnonzero(ok)
    if idx.size:
        k = grid + n
        per_cell = 16 * k * (n * n + n * m + p * m + n) * 2
        step = max(1, _CHUNK_BYTES // max(per_cell, 1))
        for s in range(0, idx.size, step):
            sel = idx[s : s + step]
            out[sel] = _hinf_chunk(
                Ff[sel], Gf[sel], Hf[sel], Df[sel], grid=grid, peaks=peaks, iters=iters
            )
    out = out.reshape(batch)
    return _finish(out, rho, return_reason)


def _hinf_chunk(
    F: Array, G: Array, H: Array, D: Array, *, grid: int, peaks: int, iters: int
) -> FloatArray:
    c, n = F.shape[0], F.shape[-1]
    base = np.linspace(0.0, np.pi, grid)
    poles = np.abs(np.angle(np.linalg.eigvals(F))) if n else np.zeros((c, 0))
    w = np.sort(np.concatenate([np.broadcast_to(base, (c, grid)), poles], axis=1), axis=1)
    f = _sigma_max(F, G, H, D, w=w)
    best = f.max(axis=1)
    # local maxima (ends included), the `peaks` largest per system
    left = np.concatenate([np.full((c, 1), -np.inf), f[:, :-1]], axis=1)
    right = np.concatenate([f[:, 1:], np.full((c, 1), -np.inf)], axis=1)
    score = np.where((f >= left) & (f >= right), f, -np.inf)
    kk = min(peaks, w.shape[1])
    cand = np.argsort(-score, axis=1)[:, :kk]  # (c, kk)
    valid = np.take_along_axis(score, cand, axis=1) > -np.inf
    last = w.shape[1] - 1
    a = np.take_along_axis(w, np.maximum(cand - 1, 0), axis=1)
    b = np.take_along_axis(w, np.minimum(cand + 1, last), axis=1)
    x1 = b - _GOLD * (b - a)
    x2 = a + _GOLD * (b - a)
    f1 = _sigma_max(F, G, H, D, w=x1)
    f2 = _sigma_max(F, G, H, D, w=x2)
    for _ in range(iters):
        go_left = f1 >= f2  # max in [a, x2]
        a = np.where(go_left, a, x1)
        b = np.where(go_left, x2, b)
        keep_x = np.where(go_left, x1, x2)
        keep_f = np.where(go_left, f1, f2)
        new_x = np.where(go_left, b - _GOLD * (b - a), a + _GOLD * (b - a))
        new_f = _sigma_max(F, G, H, D, w=new_x)
        x1 = np.where(go_left, new_x, keep_x)
        f1 = np.where(go_left, new_f, keep_f)
        x2 = np.where(go_left, keep_x, new_x)
        f2 = np.where(go_left, keep_f, new_f)
    refined = np.where(valid, np.maximum(f1, f2), -np.inf).max(axis=1)
    top: FloatArray = np.maximum(best, refined)
    return top
