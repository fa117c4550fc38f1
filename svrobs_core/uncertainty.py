"""Sound uncertainty sets for Theta = [A B] (docs/uncertainty.md).

* :func:`self_normalized_box`: the confidence ellipsoid of Abbasi-Yadkori,
  Pal, Szepesvari (2011, Thms 1-2) per row of Theta, union bound over the n
  rows, projected on the entries (radius matrices R_A, R_B) and on the
  spectral norms of the A and B blocks (eps_A, eps_B).
* :func:`bootstrap_box`: the parametric bootstrap of Dean, Mania, Matni,
  Recht, Tu (2020, Algorithm 2), re-simulating with the rollout code of
  :mod:`svrobs_core.rollouts` and re-estimating with :mod:`svrobs_core.estimators`.
* :func:`rho_upper_bound`: the stability certificate on a box (the observer
  gain's, g(L) with a radius matrix, is :func:`svrobs_core.gains.certificate`).

Everything is batched over leading dims (...), e.g. (rep, estimator/gamma).
Undefined results are NaN with a reason (python-control style), never an
exception from deep inside.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, cast

import numpy as np
from numpy.typing import ArrayLike

from . import estimators as _est
from .array_types import Array, BoolArray, FloatArray
from .data_factor import (
    U_ROUND,
    GramFactor,
    VParts,
    data_factor,
    estimate_margin,
    gram_factor,
    v_parts,
)
from .linalg import perron_upper_bound, up
from .rollouts import resampled_grams, sample_count
from .wishart_draws import DEFAULT_DRAWS

__all__ = [
    "BOOT_STREAM",
    "BoxResult",
    "GramFactor",
    "bootstrap_box",
    "certificate_radii",
    "data_factor",
    "gram_factor",
    "noise_level",
    "rho_upper_bound",
    "self_normalized_box",
]

BOOT_STREAM = (2,)  # resample b of a cell's key uses the stream key + (2, b)
RADIUS_RTOL = 1e-6  # radii whose estimated relative error exceeds this are null
BOOT_CHUNK_BYTES = 16 * 2**20  # working set of one chunk of resampled datasets
REASON_SINGULAR = "Z Z^T is singular (OLS self-normalized bound undefined)"
REASON_NONFINITE = "non-finite estimate or noise level"
REASON_OVERFLOW = (
    "the radius overflows: lambda (lambda0 for OLS, else the ridge's gamma) is too "
    "small beside Z Z^T for log det(I + G/lambda)"
)


def _one_digit(x: ArrayLike) -> FloatArray:
    """x rounded to one significant digit (the numbers of :func:`reason_inaccurate`)."""
    x = np.asarray(x, dtype=float)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        e = np.floor(np.log10(np.where(x > 0, x, 1.0)))
        out = np.round(x / 10.0**e) * 10.0**e
    digit: FloatArray = np.where(np.isfinite(out), out, x)
    return digit


def reason_inaccurate(cond: float, err: float) -> str:
    """Why a radius is null: its estimated error (1 significant digit, so that the
    cells of a dataset share a few texts)."""
    return (
        f"radii and certificates null: relative error of the radii could exceed"
        f" {RADIUS_RTOL:g} (estimate {err:.0e}, cond(Z Z^T + g I) = {cond:.0e})"
    )


@dataclass
class BoxResult:
    """An uncertainty set centred at the estimate Theta_hat, batch shape (...).

    R_A (..., n, n), R_B (..., n, m): per-entry radii, |Theta_hat_ij - Theta_ij| <= R_ij;
    eps_A, eps_B (...): bounds on ||A - A_hat||, ||B - B_hat|| (spectral);
    beta (...): the V-norm radius of every row (self-normalized only);
    sigma_w (...): the noise level used; reason (...) object: why a cell is
    NaN (None where defined); notes (...) object: caveats of a defined cell;
    rel_err, cond (...): the estimated relative error of the radii and
    cond(Z Z^T + g I), parts: the :class:`~svrobs_core.data_factor.VParts`
    they come from (self-normalized only); R_A_up, R_B_up: the radii the
    certificates use (:func:`certificate_radii`), when computed.
    """

    R_A: Array
    R_B: Array
    eps_A: Array
    eps_B: Array
    reason: Array
    notes: Array
    sigma_w: Array
    beta: Array | None = None
    rel_err: Array | None = None
    cond: Array | None = None
    parts: VParts | None = None
    R_A_up: Array | None = None
    R_B_up: Array | None = None

    @property
    def ok(self) -> BoolArray:
        ok: BoolArray = np.vectorize(lambda r: r is None, otypes=[bool])(self.reason)
        return ok

    @property
    def r_A(self) -> FloatArray:
        """The largest entry of R_A (the record's scalar r_A)."""
        r: FloatArray = np.max(self.R_A, axis=(-2, -1))
        return r

    @property
    def r_B(self) -> FloatArray:
        r: FloatArray = np.max(self.R_B, axis=(-2, -1))
        return r


def _spectral_norm(X: Array) -> FloatArray:
    """||X||_2 over the last two axes; NaN where X has a non-finite entry."""
    ok = cast(BoolArray, np.isfinite(X).all(axis=(-2, -1)))
    norm = np.linalg.norm(np.where(ok[..., None, None], X, 0.0), ord=2, axis=(-2, -1))
    return np.where(ok, norm, np.nan)


def _objects(shape: tuple[int, ...], mask: ArrayLike, text: str) -> Array:
    out = np.full(shape, None, dtype=object)
    out[np.broadcast_to(mask, shape)] = text
    return out


def self_normalized_box(
    gram: ArrayLike | GramFactor,
    theta_hat: ArrayLike,
    *,
    sigma_w: ArrayLike,
    delta: float,
    lam: ArrayLike,
    S: float | FloatArray,
    lambda0: float = 1.0,
    shrink: ArrayLike = 0.0,
    sigma_err: ArrayLike = 0.0,
) -> BoxResult:
    """Self-normalized box (docs/uncertainty.md, (b)-(d)).

    gram: Gram matrices Z Z^T (..., d, d) or their :class:`GramFactor`;
    theta_hat (..., n, d) the estimate (the centre); lam (...) the ridge
    parameter of the estimator (gamma, or gamma N0 for the mean loss;
    lam = 0 means OLS, which uses V0 = lambda0 I); S bounds ||theta_i||
    (ridge only); shrink (...) is gamma for shrunk-ols (Theta_OLS / (1+gamma),
    with lam = 0), else 0. All batch shapes broadcast.

    Ridge: beta = sigma_w sqrt(log det(I + G/lam) + 2 log(n/delta)) + sqrt(lam) S, V = G + lam I.
    OLS: beta = sigma_w sqrt((1 + lambda0/lambda_min(G)) (log det(I + G/lambda0)
    + 2 log(n/delta))), V = G. R_ij = beta sqrt((V^-1)_jj) (+ shrink |Theta_hat_ij|);
    eps_A = sqrt(n) beta sqrt(lambda_max((V^-1)_AA)) (+ shrink ||A_hat||), B alike.

    Accuracy (docs/uncertainty.md#numerical-accuracy-of-the-radii): ``rel_err``
    estimates the relative error of the radii from the factor's backward
    error, plus ``sigma_err`` (...), the relative error of ``sigma_w`` when it is
    itself computed (the bound of measured data, docs/measured.md#sigma-w-estimate;
    every radius scales with sigma_w at most linearly); where it exceeds
    RADIUS_RTOL the cell is null with a reason that gives cond(V). OLS is singular (null) when Z is numerically rank
    deficient (lambda_min(G) <= (d u)^2 lambda_max(G) from the data, d u
    lambda_max(G) from a formed G).
    """
    fac = gram if isinstance(gram, GramFactor) else gram_factor(gram)
    theta = np.asarray(theta_hat, dtype=float)
    n, d = theta.shape[-2:]
    lam = np.asarray(lam, dtype=float)
    sw = np.asarray(sigma_w, dtype=float)
    shrink = np.asarray(shrink, dtype=float)
    batch = np.broadcast_shapes(
        fac.lam.shape[:-1], theta.shape[:-2], lam.shape, sw.shape, shrink.shape
    )
    lam = np.broadcast_to(lam, batch)
    ols = lam == 0
    log_n_delta = 2.0 * np.log(n / float(delta))
    rank_tol = d * U_ROUND if fac.formed else (d * U_ROUND) ** 2
    parts = v_parts(fac, lam, lambda0=lambda0, n=n)
    err = np.broadcast_to(parts.err + np.asarray(sigma_err, dtype=float), batch)
    cond = np.broadcast_to(parts.cond, batch)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        lam_min, lam_max = parts.lam_min, parts.lam_max
        singular = ols & ~(lam_min > rank_tol * lam_max)
        logdet = parts.logdet
        beta_ridge = sw * np.sqrt(logdet + log_n_delta) + np.sqrt(lam) * S
        beta_ols = sw * np.sqrt((1.0 + lambda0 / lam_min) * (logdet + log_n_delta))
        beta = np.where(ols, beta_ols, beta_ridge)
        diag = np.where(singular[..., None], np.nan, parts.diag)  # diag(V^-1)
    bad = singular | ~np.isfinite(beta) | ~np.isfinite(theta).all(axis=(-2, -1))
    bad = bad | ~np.isfinite(parts.lmax_A)
    inaccurate = ~bad & ~(err <= RADIUS_RTOL)
    bad = bad | inaccurate
    lmax_A = np.where(bad, 0.0, parts.lmax_A)
    lmax_B = np.where(bad, 0.0, parts.lmax_B)
    root_n = np.sqrt(n)
    beta = np.where(bad, 0.0, beta)  # NaN again below; keeps the arithmetic quiet
    with np.errstate(invalid="ignore"):  # 0 * inf of a null cell: NaN, as below
        R = beta[..., None, None] * np.sqrt(np.maximum(diag, 0.0))[..., None, :]
    R = np.broadcast_to(R, batch + (n, d))
    eps_A = root_n * beta * np.sqrt(np.maximum(lmax_A, 0.0))
    eps_B = root_n * beta * np.sqrt(np.maximum(lmax_B, 0.0))
    th = np.broadcast_to(theta, batch + (n, d))
    if np.any(shrink != 0):
        with np.errstate(over="ignore", invalid="ignore"):  # non-finite cells: NaN below
            R = R + shrink[..., None, None] * np.abs(th)
            safe_th = np.where(np.isfinite(th), th, 0.0)
            eps_A = eps_A + shrink * np.linalg.norm(safe_th[..., :n], ord=2, axis=(-2, -1))
            if d > n:
                eps_B = eps_B + shrink * np.linalg.norm(safe_th[..., n:], ord=2, axis=(-2, -1))
    nan = bad[..., None, None]
    R = np.where(nan, np.nan, R)
    eps_A, eps_B, beta = (np.where(bad, np.nan, x) for x in (eps_A, eps_B, beta))
    reason = _objects(batch, singular, REASON_SINGULAR)
    inputs = np.isfinite(theta).all(axis=(-2, -1)) & np.isfinite(sw)  # else the box's own
    other = bad & ~singular & ~inaccurate
    reason[other & ~inputs] = REASON_NONFINITE
    reason[other & inputs] = REASON_OVERFLOW
    if inaccurate.any():  # one text per (cond, err) to one significant digit
        pairs = np.stack([_one_digit(cond[inaccurate]), _one_digit(err[inaccurate])], axis=-1)
        uniq, inverse = np.unique(pairs, axis=0, return_inverse=True)
        texts = np.empty(len(uniq), dtype=object)
        texts[:] = [reason_inaccurate(c, e) for c, e in uniq.tolist()]
        reason[inaccurate] = texts[inverse.reshape(-1)]
    with np.errstate(invalid="ignore", over="ignore"):  # a norm beyond the doubles: > S
        over = ~ols & (np.linalg.norm(th, axis=-1).max(axis=-1) > S)
    notes = _objects(batch, over & ~bad, f"some row of Theta_hat has norm > S = {S:g}")
    return BoxResult(
        R_A=R[..., :n],
        R_B=R[..., n:],
        eps_A=eps_A,
        eps_B=eps_B,
        reason=reason,
        notes=notes,
        sigma_w=np.broadcast_to(sw, batch).astype(float),
        beta=beta,
        rel_err=np.where(bad & ~inaccurate, np.nan, err),
        cond=cond,
        parts=parts,
    )


def certificate_radii(
    box: BoxResult,
    fac: GramFactor,
    theta_hat: ArrayLike,
    *,
    lam: ArrayLike,
    shrink: ArrayLike = 0.0,
) -> tuple[FloatArray, FloatArray]:
    """Radius matrices that the certificates use: (R_A_up, R_B_up), never below the
    exact radii of the box around the exact estimate. -> (..., n, n), (..., n, m)

    R_up = up((R (1 + e) + (1 + shrink) (m_i sqrt((V^-1)_jj) (1 + e) + 4 u |Theta_hat_ij|))
    (1 + 8 u)) with e = ``box.rel_err`` (0 for a box without one, the bootstrap),
    m_i the estimate's rounding margin (:func:`svrobs_core.data_factor.estimate_margin`)
    and V = Z Z^T + lam I of the cell's estimator: the radius's own rounding, the
    distance of the computed estimate from the exact estimator on the exact
    data, and the final rounding (docs/uncertainty.md#certificates-on-the-boxes).
    NaN where the box is NaN or its error estimate exceeds RADIUS_RTOL, inf where
    the margin is unbounded (a singular V). From a formed Gram matrix
    (:func:`gram_factor`, no data) the margin is not bounded, so the radii are NaN
    (no certificate rests on them): every pipeline passes the data.
    """
    theta = np.asarray(theta_hat, dtype=float)
    n, d = theta.shape[-2:]
    R = np.concatenate([box.R_A, box.R_B], axis=-1)
    lam = np.asarray(lam, dtype=float)
    shrink = np.asarray(shrink, dtype=float)
    parts = box.parts if box.parts is not None else v_parts(fac, lam, n=n)
    err = parts.err
    if box.rel_err is not None:
        err = np.fmax(err, box.rel_err)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        if fac.formed:  # no data: the estimate's rounding is not bounded
            margin = np.full(parts.diag.shape[:-1] + (n,), np.nan)
        else:
            margin = estimate_margin(fac, theta, lam=lam, shrink=shrink, parts=parts)
        e = (1.0 + err)[..., None, None]
        diag = np.sqrt(np.maximum(parts.diag, 0.0))[..., None, :]
        floor = margin[..., :, None] * diag * e
        floor = (1.0 + shrink)[..., None, None] * (floor + 4 * U_ROUND * np.abs(theta))
        R_up = up((R * e + floor) * (1.0 + 8 * U_ROUND))
    R_up = np.where((err <= RADIUS_RTOL)[..., None, None], R_up, np.nan)
    return R_up[..., :n], R_up[..., n:]


def rho_upper_bound(A_hat: ArrayLike, R_A: ArrayLike) -> FloatArray:
    """An upper bound of rho(|A_hat| + R_A) >= rho(A) for every A in the box, never
    below the exact value: |A_hat| + R_A rounded up, then the Collatz-Wielandt
    bound of :func:`svrobs_core.linalg.perron_upper_bound`; inf where non-finite. -> (...)"""
    with np.errstate(invalid="ignore", over="ignore"):
        M = up(np.abs(np.asarray(A_hat, dtype=float)) + np.asarray(R_A, dtype=float))
    return perron_upper_bound(M)


# ---------------------------------------------------------------------------
# parametric bootstrap (Dean et al. 2020, Algorithm 2)
# ---------------------------------------------------------------------------
def noise_level(
    Z: ArrayLike, F: ArrayLike, theta_hat: ArrayLike, *, N0: int | None = None
) -> tuple[FloatArray, str | None]:
    """sigma_hat_w^2 = ||F - Theta_hat Z||_F^2 / (n (N0 - d)); -> (sigma_hat (...), reason).

    Z (..., d, c), F (..., n, c), theta_hat (..., n, d), batch dims broadcast; N0 the
    sample count (default c; more with Wishart draws, docs/science.md#15-wishart-draws).
    NaN with a reason when N0 <= d.
    """
    Z = np.asarray(Z, dtype=float)
    F = np.asarray(F, dtype=float)
    theta = np.asarray(theta_hat, dtype=float)
    n, d = theta.shape[-2:]
    N0 = Z.shape[-1] if N0 is None else N0
    with np.errstate(over="ignore", invalid="ignore"):  # huge data: inf/NaN, noted downstream
        rss = np.sum((F - theta @ Z) ** 2, axis=(-2, -1))
    if N0 <= d:
        return np.full(rss.shape, np.nan), f"sigma_w estimate needs N0 > d = {d}"
    return np.sqrt(rss / (n * (N0 - d))), None


def _refit(name: str, gamma: Any, Z: Array, F: Array, G: Array, N0: int, loss_scale: str) -> Array:
    """Re-estimate with the cell's own estimator from the data (docs/science.md#2-estimators);
    N0 the datasets' sample count (Z may hold fewer columns with the same Gram). -> (h, n, d)"""
    if name == "ols":
        return _est.fit_ols(Z, F)
    if name == "svr":
        with np.errstate(over="ignore", invalid="ignore"):  # huge data: inf/NaN, noted downstream
            P = np.matmul(F, np.swapaxes(Z, -1, -2))
        return _est.svr_from_gram(
            G, P, N0, [gamma], loss_scale=loss_scale, data=lambda rows: (Z[rows], F[rows])
        )[:, 0]
    if name == "shrunk-ols":
        return _est.shrunk_ols(_est.fit_ols(Z, F), [gamma])[:, 0]
    raise ValueError(f"unknown estimator {name!r}")


def _deviations(
    name: str,
    gamma: Any,
    centre: Array,
    s: Array,
    G: Array,
    W: Array,
    Z: Array,
    F: Array,
    N0: int,
    loss_scale: str,
) -> Array:
    """Theta_b - Theta for one estimator column of a chunk of resampled datasets
    of N0 samples each.

    The data were simulated from ``centre`` Theta (h, n, d) with noise level s
    (h,), so ``F Z^T = Theta G + s W`` and the estimator's deviation is, for the
    ridge parameter g (0 for OLS), ``(s W - g Theta) (G + g I)^-1`` (shrunk OLS:
    the OLS one shrunk, ``(s W G^-1 - gamma Theta) / (1 + gamma)``): solved with
    the eigendecomposition of G, without the cancellation of ``Theta_b - Theta``.
    Datasets with cond(G + g I) above the estimator's limit (or non-finite)
    are re-estimated from their data (:func:`_refit`) instead."""
    d = G.shape[-1]
    g = _est.ridge_parameters([gamma], N0, loss_scale)[0] if name == "svr" else 0.0
    limit = _est.SVR_COND_LIMIT if name == "svr" else _est.REFINE_COND_LIMIT
    ok = cast(BoolArray, np.isfinite(G).all(axis=(-2, -1)) & np.isfinite(W).all(axis=(-2, -1)))
    lam, V = np.linalg.eigh(np.where(ok[:, None, None], G, np.eye(d)))
    lam = np.maximum(lam, 0.0)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        fine = ok & ((lam[:, -1] + g) <= limit * (lam[:, 0] + g)) & (lam[:, 0] + g > 0)
        rhs = s[:, None, None] * W - g * centre
        dev: Array = np.matmul(np.matmul(rhs, V) / (lam + g)[:, None, :], np.swapaxes(V, -1, -2))
    if name == "shrunk-ols":
        dev = (dev - gamma * centre) / (1.0 + gamma)
    if not fine.all():
        rows = np.flatnonzero(~fine)
        dev[rows] = _refit(name, gamma, Z[rows], F[rows], G[rows], N0, loss_scale) - centre[rows]
    return dev


def bootstrap_box(
    theta_hat: ArrayLike,
    *,
    estimators: Sequence[tuple[str, float | None]],
    sigma_w: ArrayLike,
    sigma_u: float,
    N: int,
    T0: int,
    seed: int,
    keys: Sequence[tuple[int, ...]],
    delta: float,
    boot_reps: int = 100,
    data: str = "all",
    x0_std: float = 0.0,
    loss_scale: str = "sum",
    joint: bool = True,
    rng: str = "pcg64",
    draws: str = DEFAULT_DRAWS,
) -> BoxResult:
    """Parametric bootstrap box
    (docs/uncertainty.md#e-the-parametric-bootstrap-dean-mania-matni-recht-tu-2020-alg-2).

    theta_hat (R, E, n, d): the estimate of each (repetition, estimator) cell;
    estimators: the E (name, gamma) pairs; sigma_w (R, E) (or broadcasting):
    the noise level to re-simulate with; keys: the R seed keys. Resample b of
    repetition r draws from the stream keys[r] + (2, b) in the data order of
    docs/science.md#14-randomness-and-reproducibility, shared by the E cells of
    the repetition. eps_A, eps_B: (1 - delta) quantiles of ||A_b - A_hat||, ||B_b - B_hat||. Radii: with
    ``joint`` the studentised max-statistic box R = c s (s the RMS of
    Theta_b - Theta_hat per entry, c the (1 - delta) quantile of
    max_ij |Theta_b - Theta_hat|_ij / s_ij), else the (1 - delta) quantile
    of |Theta_b - Theta_hat| per entry. numpy's default (linear) quantiles.
    ``draws``: each resample's N rollouts, or (``"wishart"``) their noise's
    scatter matrix drawn at once (docs/uncertainty.md#how-the-resamples-are-drawn).

    Batched: all R x boot_reps resampled datasets go through one chunked
    simulation of every cell's system (:func:`svrobs_core.rollouts.resampled_grams`)
    and one re-estimation per estimator column and chunk (:func:`_deviations`);
    a cell's numbers do not depend on the chunking (docs/performance.md#bootstrap).
    """
    theta = np.asarray(theta_hat, dtype=float)
    R, E, n, d = theta.shape
    if len(estimators) != E or len(keys) != R:
        raise ValueError("estimators and keys must match theta_hat's (R, E) axes")
    Bn = int(boot_reps)
    sw = np.broadcast_to(np.asarray(sigma_w, dtype=float), (R, E))
    good = np.isfinite(theta).all(axis=(-2, -1)) & np.isfinite(sw) & (sw >= 0)
    th = np.where(good[..., None, None], theta, 0.0)
    s_ok = np.where(good, sw, 0.0)
    systems = np.concatenate([th, s_ok[..., None, None] * np.eye(n)], axis=-1)  # (R, E, n, d+n)
    D = R * Bn
    N0 = sample_count(int(N), T0, data)
    owner = np.arange(D) // Bn
    bkeys = [tuple(keys[r]) + BOOT_STREAM + (b,) for r in range(R) for b in range(Bn)]
    dev_b = np.empty((D, E, n, d))
    for idx, G, W, Z, F in resampled_grams(
        seed,
        bkeys,
        systems,
        owner,
        sigma_u=sigma_u,
        N=N,
        T0=T0,
        data=data,
        x0_std=x0_std,
        rng=rng,
        draws=draws,
        chunk_bytes=BOOT_CHUNK_BYTES,
    ):
        r = owner[idx]
        for ei, (name, gamma) in enumerate(estimators):
            dev_b[idx, ei] = _deviations(
                name,
                gamma,
                th[r, ei],
                s_ok[r, ei],
                G[:, ei],
                W[:, ei],
                Z[:, ei],
                F[:, ei],
                N0,
                loss_scale,
            )
    dev = dev_b.reshape(R, Bn, E, n, d).transpose(0, 2, 1, 3, 4)
    level = 1.0 - float(delta)
    # resamples beyond the double range give inf / NaN radii: not finite, so no certificate
    with np.errstate(over="ignore", divide="ignore", invalid="ignore"):
        eps_A = np.quantile(_spectral_norm(dev[..., :n]), level, axis=-1)
        eps_B = np.quantile(_spectral_norm(dev[..., n:]), level, axis=-1)
        a = np.abs(dev)
        if joint:
            scale = np.sqrt(np.mean(dev**2, axis=2))  # (R, E, n, d)
            t = np.where(a > 0, a / scale[:, :, None], 0.0).max(axis=(-2, -1))
            Rad = np.quantile(t, level, axis=-1)[..., None, None] * scale
        else:
            Rad = np.quantile(a, level, axis=2)
    bad = ~good
    Rad = np.where(bad[..., None, None], np.nan, Rad)
    eps_A, eps_B = np.where(bad, np.nan, eps_A), np.where(bad, np.nan, eps_B)
    return BoxResult(
        R_A=Rad[..., :n],
        R_B=Rad[..., n:],
        eps_A=eps_A,
        eps_B=eps_B,
        reason=_objects((R, E), bad, REASON_NONFINITE),
        notes=np.full((R, E), None, dtype=object),
        sigma_w=np.asarray(sw, dtype=float).copy(),
    )
