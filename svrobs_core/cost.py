"""Observer cost J of SPEC section 6: exact finite horizon, stationary, Monte Carlo.

Model (SPEC section 6). True system and observer on the estimates:

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

Monte Carlo: :func:`mc_cost` simulates one batch of cells with one noise
stream; :func:`mc_cost_shared` simulates a grid (repetitions x estimators /
gammas) where the cells of a repetition share that repetition's stream (the
experiment runner's case), drawing it once and simulating the plant once.
"""

from __future__ import annotations

import numpy as np

from .norms import REASON_UNSTABLE, spectral_radius, stability_reason, stein_solve

# Up to this state dimension the batched small products are done with the
# batch in the last axis; above it with stacked matmul (BLAS per matrix).
_SOA_MAX_N = 12


# --------------------------------------------------------------------------
# argument handling
# --------------------------------------------------------------------------
class _Cells:
    """Validated, broadcast arguments of one cost call."""

    def __init__(self, A, B, A_tilde, B_tilde, L, C, sigma_u, sigma_w, sigma_v):
        A = np.asarray(A, dtype=float)
        B = np.asarray(B, dtype=float)
        At = np.asarray(A_tilde, dtype=float)
        Bt = np.asarray(B_tilde, dtype=float)
        L = np.asarray(L, dtype=float)
        if B.ndim == 1:
            B = B[:, None]
        if Bt.ndim == 1:
            Bt = Bt[:, None]
        if A.ndim < 2 or A.shape[-1] != A.shape[-2]:
            raise ValueError(f"A must be (..., n, n), got {A.shape}")
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
            if arr.ndim < 2 or arr.shape[-2:] != shape:
                raise ValueError(f"{name} must be (..., {shape[0]}, {shape[1]}), got {arr.shape}")
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
    def F(self):
        return self.At - self.L @ self.C

    def dA(self):
        return self.A - self.At

    def dB(self):
        return self.B - self.Bt

    def Q_blocks(self):
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
class _SoA:
    """Matrices stored as (r, c, S, N): batch N in the last axis, S a stack axis."""

    def __init__(self, batch):
        self.batch = batch
        self.N = int(np.prod(batch, dtype=np.int64))

    def put(self, X):
        """(..., r, c) with batch broadcastable to self.batch -> (r, c, 1, N|1)."""
        X = np.asarray(X, dtype=float)
        r, c = X.shape[-2:]
        if int(np.prod(X.shape[:-2], dtype=np.int64)) == 1:
            return X.reshape(r, c, 1, 1)
        X = np.broadcast_to(X, self.batch + (r, c)).reshape(self.N, r, c)
        return np.ascontiguousarray(np.moveaxis(X, 0, -1))[:, :, None, :]

    @staticmethod
    def mm(a, b):
        return np.einsum("ik...,kj...->ij...", a, b)

    @staticmethod
    def t(a):
        return np.swapaxes(a, 0, 1)

    @staticmethod
    def stack(x, y):
        x, y = np.broadcast_arrays(x, y)
        return np.concatenate([x, y], axis=2)

    @staticmethod
    def part(x, i):
        return x[:, :, i : i + 1]

    @staticmethod
    def addto_w(new, t, Ma):
        new[:, :, 1] += t * Ma[:, :, 0]

    @staticmethod
    def trace(x):
        return np.trace(x, axis1=0, axis2=1)  # -> (S, N)

    def get(self, v):
        """(S=1, N|1) -> batch shape."""
        return np.broadcast_to(v[0], (self.N,)).reshape(self.batch)


class _AoS:
    """Matrices stored as (S, N, r, c); products by stacked matmul."""

    def __init__(self, batch):
        self.batch = batch
        self.N = int(np.prod(batch, dtype=np.int64))

    def put(self, X):
        X = np.asarray(X, dtype=float)
        r, c = X.shape[-2:]
        if int(np.prod(X.shape[:-2], dtype=np.int64)) == 1:
            return X.reshape(1, 1, r, c)
        return np.broadcast_to(X, self.batch + (r, c)).reshape(1, self.N, r, c)

    @staticmethod
    def mm(a, b):
        return a @ b

    @staticmethod
    def t(a):
        return np.swapaxes(a, -1, -2)

    @staticmethod
    def stack(x, y):
        x, y = np.broadcast_arrays(x, y)
        return np.concatenate([x, y], axis=0)

    @staticmethod
    def part(x, i):
        return x[i : i + 1]

    @staticmethod
    def addto_w(new, t, Ma):
        new[1] += t * Ma[0]

    @staticmethod
    def trace(x):
        return np.trace(x, axis1=-2, axis2=-1)  # -> (S, N)

    def get(self, v):
        return np.broadcast_to(v[0], (self.N,)).reshape(self.batch)


def _layout(n, batch):
    return _SoA(batch) if n <= _SOA_MAX_N else _AoS(batch)


def _congruence(ops, P, M, need_xe=True):
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


def _join(ops, P_a, M_a, M_b, t_b, need_xe=True):
    """Stacked (Sigma, W) of the concatenation of segment a (power P_a, stacked
    M_a = (Sigma_a, W_a) blocks) followed by segment b (M_b, length t_b)."""
    C = _congruence(ops, P_a, M_b, need_xe)
    out = []
    for Ma, Cb in zip(M_a, C):
        if Cb is None:
            out.append(None)
            continue
        new = Ma + Cb  # fresh array (Sigma_a + .., W_a + ..)
        ops.addto_w(new, t_b, Ma)  # W_{a+b} gets the extra t_b * Sigma_a
        out.append(new)
    return tuple(out)


def _square(ops, P):
    Pa, Pr, Pf = P
    mm = ops.mm
    return mm(Pa, Pa), mm(Pr, Pa) + mm(Pf, Pr), mm(Pf, Pf)


# --------------------------------------------------------------------------
# exact finite-horizon cost
# --------------------------------------------------------------------------
def exact_cost(A, B, A_tilde, B_tilde, L, C, sigma_u, sigma_w, sigma_v, horizon=200):
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
    overhead is ~1 ms).
    """
    T = int(horizon)
    if T < 1 or T != horizon:
        raise ValueError(f"horizon must be a positive integer, got {horizon!r}")
    c = _Cells(A, B, A_tilde, B_tilde, L, C, sigma_u, sigma_w, sigma_v)
    ops = _layout(c.n, c.batch)
    Qxx, Qxe, Qee = c.Q_blocks()
    # one-step power Acal = [[A, 0], [-dA, F]]
    P = (ops.put(c.A), ops.put(-c.dA()), ops.put(c.F()))
    Q = (ops.put(Qxx), ops.put(Qxe), ops.put(Qee))
    # block of length 1: Sigma_1 = W_1 = Q   (stacked: index 0 Sigma, 1 W)
    blk = tuple(ops.stack(q, q) for q in Q)
    t_blk = 1
    acc = None
    t_acc = 0
    bits = bin(T)[2:][::-1]
    top = len(bits) - 1
    for j, bit in enumerate(bits):
        if bit == "1":
            if acc is None:
                acc, t_acc = blk, t_blk
            else:
                acc = _join(ops, P, blk, acc, t_acc, need_xe=(j < top))
                t_acc += t_blk
        if j < top:
            blk = _join(ops, P, blk, blk, t_blk)
            t_blk *= 2
            P = _square(ops, P)
    tr = ops.trace(ops.part(acc[2], 1))
    return ops.get(tr) / T


def optimal_cost(A, B, K, C, sigma_u, sigma_w, sigma_v, horizon=200):
    """J* of SPEC section 6: exact_cost with A~ = A, B~ = B, L = K. -> (...)

    (With the true model the error is the Kalman predictor error, decoupled
    from x; its stationary value is trace(P), P the DARE solution.)"""
    return exact_cost(A, B, A, B, K, C, sigma_u, sigma_w, sigma_v, horizon)


j_star = optimal_cost


# --------------------------------------------------------------------------
# stationary cost
# --------------------------------------------------------------------------
def stationary_cost(
    A, B, A_tilde, B_tilde, L, C, sigma_u, sigma_w, sigma_v, *, rho_F=None, return_reason=False
):
    """Stationary E||e||^2 by discrete Lyapunov; NaN where the augmented system
    is not Schur stable. -> (...)

    Blockwise: ``X = A X A^T + Qxx`` (true system, solved once), the cross
    block ``S = A S F^T + (-A X dA^T + Qxe)`` (Stein-Sylvester, batched) and
    the e block ``E = F E F^T + dA X dA^T - F S^T dA^T - dA S F^T + Qee``
    (batched); ``J = trace E``. The augmented matrix is block triangular, so
    it is Schur stable iff ``rho(A) < 1`` and ``rho(F) < 1``; otherwise the
    value is NaN with reason ``"unstable"`` (``"non-finite input"`` for NaN
    inputs). ``rho_F``: optional precomputed spectral radius of
    ``F = A~ - L C`` (saves the batched eigenvalue call). ``return_reason=True``
    gives ``(value, reason)``, reason an object array of None / str (a plain
    object for one cell).
    """
    c = _Cells(A, B, A_tilde, B_tilde, L, C, sigma_u, sigma_w, sigma_v)
    batch = c.batch
    tp = lambda M: np.swapaxes(M, -1, -2)
    F = c.F()
    rho_A = spectral_radius(c.A)  # A's own batch (usually one system)
    if rho_F is None:
        rho_F = spectral_radius(F)
    rho_F = np.asarray(rho_F, dtype=float)
    with np.errstate(invalid="ignore"):
        okA = rho_A < 1.0
        okF = rho_F < 1.0
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
    with np.errstate(invalid="ignore"):
        J = np.where(rho < 1.0, J, np.nan)
    if return_reason:
        return J, stability_reason(None, rho=rho)
    return J


# --------------------------------------------------------------------------
# Monte Carlo
# --------------------------------------------------------------------------
def mc_cost(A, B, A_tilde, B_tilde, L, C, sigma_u, sigma_w, sigma_v, horizon, rng, runs):
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
    T = int(horizon)
    runs = int(runs)
    if T < 1 or T != horizon:
        raise ValueError(f"horizon must be a positive integer, got {horizon!r}")
    if runs < 2:
        raise ValueError("runs must be at least 2 (for a standard error)")
    c = _Cells(A, B, A_tilde, B_tilde, L, C, sigma_u, sigma_w, sigma_v)
    n, m, p, batch = c.n, c.m, c.p, c.batch
    q = m + n + p
    tp = lambda M: np.swapaxes(M, -1, -2)
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
    per_run = acc / T
    mean = per_run.mean(axis=-1)
    se = per_run.std(axis=-1, ddof=1) / np.sqrt(runs)
    return mean, se


def mc_cost_shared(A, B, A_tilde, B_tilde, L, C, sigma_u, sigma_w, sigma_v, horizon, rngs, runs):
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
    T = int(horizon)
    runs = int(runs)
    if T < 1 or T != horizon:
        raise ValueError(f"horizon must be a positive integer, got {horizon!r}")
    if runs < 2:
        raise ValueError("runs must be at least 2 (for a standard error)")
    c = _Cells(A, B, A_tilde, B_tilde, L, C, sigma_u, sigma_w, sigma_v)
    if c.xbatch != () or c.C.ndim != 2 or c.su.ndim or c.sw.ndim or c.sv.ndim:
        raise ValueError("mc_cost_shared needs one true system (A, B, C) and scalar sigmas")
    n, m, p = c.n, c.m, c.p
    q = m + n + p
    shape = c.batch
    if len(shape) != 2:
        raise ValueError(f"A_tilde, B_tilde, L must be (R, E, ...), batch {shape}")
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
    Xz = np.zeros((R, W, h_max + 1, runs))  # [x_k; z_k] for the block's steps
    Ev = np.zeros((R, E, h_max + 1, n, runs))  # e_k
    acc = np.zeros((R, E, n, runs))
    k = 0
    while k < T:
        h = min(h_max, T - k)
        for r, g in enumerate(rngs):
            Xz[r, n:, :h, :] = g.standard_normal((h, runs, q)).transpose(2, 0, 1)
        for i in range(h):
            np.matmul(Mx, Xz[:, :, i, :], out=Xz[:, :n, i + 1, :])
        D = G @ Xz[:, None, :, :h, :].reshape(R, 1, W, h * runs)  # (R, E, n, h runs)
        D = D.reshape(R, E, n, h, runs)
        for i in range(h):
            np.matmul(F, Ev[:, :, i], out=Ev[:, :, i + 1])
            Ev[:, :, i + 1] += D[:, :, :, i]
        err = Ev[:, :, 1 : h + 1]
        acc += np.einsum("rehks,rehks->reks", err, err)
        Ev[:, :, 0] = Ev[:, :, h]
        Xz[:, :n, 0] = Xz[:, :n, h]
        k += h
    per_run = acc.sum(axis=2) / T  # (R, E, runs)
    mean = per_run.mean(axis=-1)
    se = per_run.std(axis=-1, ddof=1) / np.sqrt(runs)
    return mean, se


__all__ = [
    "REASON_UNSTABLE",
    "exact_cost",
    "j_star",
    "mc_cost",
    "mc_cost_shared",
    "optimal_cost",
    "stationary_cost",
]
