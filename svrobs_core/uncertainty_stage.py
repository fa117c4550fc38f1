"""The bounds stage for ``bounds_method`` "self-normalized" and "bootstrap" (docs/uncertainty.md).

Called by :mod:`svrobs_core.pipeline` for one dataset over the (rep,
estimator/gamma) grid (R, E): builds the box of :mod:`svrobs_core.uncertainty`
centred at the estimate, and turns it into the record's bound fields and the
quantities the observer stages use (eps_A, eps_B; R_A for the gain).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import estimators as _est
from . import uncertainty as _unc
from .bounds import BoundsResult, nullable

PAPER_ONLY_NOTE = "bounds: H_A, H_B, thm1_holds_A/B belong to the paper's method (null here)"


@dataclass
class SoundBounds:
    """The box of every cell, its record fields and the BoundsResult for later stages."""

    box: _unc.BoxResult
    fields: dict
    result: BoundsResult


def _ridge_axis(axis, N0: int, loss_scale: str):
    """lam and shrink per estimator cell: svr -> ridge lam; ols -> 0; shrunk-ols -> shrink."""
    E = len(axis.names)
    lam = np.zeros(E)
    shrink = np.zeros(E)
    for e, (name, g) in enumerate(zip(axis.names, axis.gammas)):
        if name == "svr":
            lam[e] = _est.ridge_parameters([g], N0, loss_scale)[0]
        elif name == "shrunk-ols":
            shrink[e] = g
    return lam, shrink


def _coverage(true, est, R) -> np.ndarray:
    """Fraction of entries with |true - est| <= R; NaN where the box is undefined."""
    inside = np.mean(np.abs(true - est) <= R, axis=(-2, -1))
    return np.where(np.isfinite(R).all(axis=(-2, -1)), inside, np.nan)


def sound_bounds(c, *, G, Z, F, N: int, N0: int) -> SoundBounds:
    """Box, record fields and BoundsResult of one dataset's cells (docs/uncertainty.md).

    ``c``: the pipeline's cell context (spec, system, sigma_w, keys, axis,
    A_hat, B_hat, notes); G the Gram matrices (R, d, d); Z, F the data (only
    needed for the bootstrap's residual noise estimate).
    """
    return bounds_from_box(c, sound_box(c, G=G, Z=Z, F=F, N=N, N0=N0))


def sound_box(c, *, G, Z, F, N: int, N0: int) -> _unc.BoxResult:
    """The box of the spec's ``bounds_method`` for one dataset's cells (:func:`sound_bounds`)."""
    spec, system = c.spec, c.system
    theta = np.concatenate([c.A_hat, c.B_hat], axis=-1)
    R, E = theta.shape[:2]
    if spec.bounds_method == "self-normalized":
        lam, shrink = _ridge_axis(c.axis, N0, spec.loss_scale)
        fac = _unc.gram_factor(G)
        box = _unc.self_normalized_box(
            _unc.GramFactor(lam=fac.lam[:, None], U=fac.U[:, None]),
            theta,
            sigma_w=c.sigma_w,
            delta=spec.delta,
            lam=lam,
            S=spec.S_bound,
            lambda0=spec.lambda0,
            shrink=shrink,
        )
    else:
        if spec.boot_sigma_w == "spec":
            sigma = c.sigma_w
        else:
            sigma, reason = _unc.noise_level(Z[:, None], F[:, None], theta)
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
        )
    return box


def bounds_from_box(c, box: _unc.BoxResult) -> SoundBounds:
    """Record fields and BoundsResult of the cells of ``c`` on ``box`` (:func:`sound_bounds`).

    Without a true system (``c.system.A`` None: measured data) the coverage
    fields are left out."""
    spec, system = c.spec, c.system
    R, E = c.A_hat.shape[:2]
    c.notes.add_reasons(box.reason, "bounds")
    c.notes.add_reasons(box.notes, "bounds")
    c.notes.add(True, PAPER_ONLY_NOTE)
    rho = _unc.rho_upper_bound(c.A_hat, box.R_A)
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
    return SoundBounds(box=box, fields=fields, result=result)
