"""The bounds stage for ``bounds_method`` "self-normalized" and "bootstrap" (docs/uncertainty.md).

Called by :mod:`svrobs_core.pipeline` for one dataset over the (rep,
estimator/gamma) grid (R, E): builds the box of :mod:`svrobs_core.uncertainty`
centred at the estimate, and turns it into the record's bound fields and the
quantities the observer stages use (eps_A, eps_B; R_A for the gain). The
certificates (``stable_certified`` here, ``certified`` in the gain stage) use
the box's radii rounded up to cover every rounding error
(:func:`svrobs_core.uncertainty.certificate_radii`,
docs/uncertainty.md#certificates-on-the-boxes).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any, cast

import numpy as np

from . import estimators as _est
from . import uncertainty as _unc
from .array_types import Array, FloatArray
from .bounds import BoundsResult, nullable
from .data_factor import GramFactor
from .planning import EstimatorAxis

PAPER_ONLY_NOTE = "bounds: H_A, H_B, thm1_holds_A/B belong to the paper's method (null here)"
HEURISTIC_NOTE = (
    "bounds: the bootstrap box is a heuristic (no finite-sample guarantee;"
    " measured coverage below 1 - delta, docs/uncertainty.md (e))"
)
MARGIN_NOTE = (
    "bounds: certificates null: the rounding error of the estimate is not bounded"
    " (Z Z^T singular or too ill-conditioned)"
)


@dataclass
class SoundBounds:
    """The box the certificates use (the record's box with its radii rounded up
    by :func:`svrobs_core.uncertainty.certificate_radii`), the record fields
    (the box itself) and the BoundsResult for later stages."""

    box: _unc.BoxResult
    fields: dict[str, Any]
    result: BoundsResult


def ridge_axis(axis: EstimatorAxis, N0: int, loss_scale: str) -> tuple[FloatArray, FloatArray]:
    """lam and shrink per estimator cell: svr -> ridge lam; ols -> 0; shrunk-ols -> shrink."""
    E = len(axis.names)
    lam = np.zeros(E)
    shrink = np.zeros(E)
    for e, (name, g) in enumerate(zip(axis.names, axis.gammas)):
        if name == "svr":
            lam[e] = _est.ridge_parameters([cast(float, g)], N0, loss_scale)[0]
        elif name == "shrunk-ols":
            shrink[e] = g
    return lam, shrink


def _coverage(true: Array, est: Array, R: Array) -> FloatArray:
    """Fraction of entries with |true - est| <= R; NaN where the box is undefined."""
    inside = np.mean(np.abs(true - est) <= R, axis=(-2, -1))
    return np.where(np.isfinite(R).all(axis=(-2, -1)), inside, np.nan)


def sound_bounds(
    c: Any,
    *,
    G: Array | None,
    Z: Array | None,
    F: Array | None,
    N: int,
    N0: int,
    factor: GramFactor | None = None,
) -> SoundBounds:
    """Box, record fields and BoundsResult of one dataset's cells (docs/uncertainty.md).

    ``c``: the pipeline's cell context (spec, system, sigma_w, keys, axis,
    A_hat, B_hat, notes); Z, F the data (R, d, N0), (R, n, N0), factorised
    by :func:`sound_box`; G (the Gram matrices) only where there are no data.
    """
    return bounds_from_box(c, sound_box(c, G=G, Z=Z, F=F, N=N, N0=N0, factor=factor))


def sound_box(
    c: Any,
    *,
    G: Array | None,
    Z: Array | None,
    F: Array | None,
    N: int,
    N0: int,
    factor: GramFactor | None = None,
    sigma_err: Array | float = 0.0,
) -> _unc.BoxResult:
    """The box of the spec's ``bounds_method`` for one dataset's cells
    (:func:`sound_bounds`), with the radii its certificates use (``R_A_up``,
    ``R_B_up``, :func:`svrobs_core.uncertainty.certificate_radii`).
    ``sigma_err``: the relative error of ``c.sigma_w`` where it is computed (the
    bound of measured data), added to the radii's error estimate.

    The radii come from the data's own factor (:func:`svrobs_core.uncertainty.data_factor`);
    with ``Z`` None (a caller with only the Gram matrices G) from the formed
    G, whose error estimate is larger and whose certificate radii cannot
    include the estimate's rounding margin."""
    spec, system = c.spec, c.system
    theta = np.concatenate([c.A_hat, c.B_hat], axis=-1)
    lam, shrink = ridge_axis(c.axis, N0, spec.loss_scale)
    # (R, 1, ...): one factor per dataset, shared by its E cells
    if factor is None:  # ``factor``: data_factor(Z, F), when the caller has it already
        factor = (
            _unc.data_factor(Z, cast(Array, F))
            if Z is not None
            else _unc.gram_factor(cast(Array, G))
        )
    fac = factor.expand(1)
    if spec.bounds_method == "self-normalized":
        box = _unc.self_normalized_box(
            fac,
            theta,
            sigma_w=c.sigma_w,
            delta=spec.delta,
            lam=lam,
            S=spec.S_bound,
            lambda0=spec.lambda0,
            shrink=shrink,
            sigma_err=sigma_err,
        )
    else:
        if spec.boot_sigma_w == "spec":
            sigma = c.sigma_w
        else:
            assert Z is not None and F is not None  # the bootstrap's noise level needs the data
            sigma, reason = _unc.noise_level(Z[:, None], F[:, None], theta, N0=N0)
            if reason is not None:
                c.notes.add(True, f"bounds: {reason}")
        box = _unc.bootstrap_box(
            theta,
            estimators=list(zip(c.axis.names, c.axis.gammas)),
            sigma_w=sigma,
            sigma_u=system.sigma_u,
            N=N,
            T0=spec.T0,
            seed=spec.seed,
            keys=c.keys,
            delta=spec.delta,
            boot_reps=spec.boot_reps,
            data=spec.data,
            x0_std=spec.x0_std,
            loss_scale=spec.loss_scale,
            rng=spec.rng,
            draws=spec.draws,
        )
        c.notes.add(True, HEURISTIC_NOTE)
    R_A_up, R_B_up = _unc.certificate_radii(box, fac, theta, lam=lam, shrink=shrink)
    return replace(box, R_A_up=R_A_up, R_B_up=R_B_up)


def bounds_from_box(c: Any, box: _unc.BoxResult) -> SoundBounds:
    """Record fields and BoundsResult of the cells of ``c`` on ``box`` (:func:`sound_bounds`).

    The certificates use ``box.R_A_up`` (``box.R_A`` where the box has none).
    Without a true system (``c.system.A`` None: measured data) the coverage
    fields are left out."""
    spec, system = c.spec, c.system
    R, E = c.A_hat.shape[:2]
    c.notes.add_reasons(box.reason, "bounds")
    c.notes.add_reasons(box.notes, "bounds")
    c.notes.add(True, PAPER_ONLY_NOTE)
    R_A_up = box.R_A if box.R_A_up is None else box.R_A_up
    R_B_up = box.R_B if box.R_B_up is None else box.R_B_up
    unbounded = box.ok & ~np.isfinite(R_A_up).all(axis=(-2, -1))
    c.notes.add(unbounded, MARGIN_NOTE)
    R_A_up = np.where(unbounded[..., None, None], np.nan, R_A_up)
    rho = _unc.rho_upper_bound(c.A_hat, R_A_up)
    with np.errstate(invalid="ignore"):  # null, not false, where rho or eps is undefined
        certified = nullable(rho < 1.0, np.isfinite(rho) & np.isfinite(box.eps_A))
    truth = system.A is not None
    cov_A = _coverage(system.A, c.A_hat, box.R_A) if truth else None
    cov_B = _coverage(system.B, c.B_hat, box.R_B) if truth else None
    fields = {
        "bounds_method": np.broadcast_to(np.array(spec.bounds_method, dtype=object), (R, E)),
        "r_A": box.r_A,
        "r_B": box.r_B if box.R_B.shape[-1] else np.full((R, E), np.nan),  # m = 0: no B
        "radii_A": box.R_A,
        "radii_B": box.R_B,
        "eps_A": box.eps_A,
        "eps_B": box.eps_B,
        "coverage_A": cov_A,
        "coverage_B": cov_B,
        "rho_upper_bound": rho,
        "stable_certified": certified,
    }
    result = BoundsResult(
        eps_A=box.eps_A,
        eps_B=box.eps_B,
        rho_upper_bound=rho,
        stable_certified=certified,
        coverage_A=cov_A,
        coverage_B=cov_B,
    )
    cert_box = replace(box, R_A=R_A_up, R_B=R_B_up)
    return SoundBounds(box=cert_box, fields=fields, result=result)
