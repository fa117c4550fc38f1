"""The stage chain of one dataset: estimate -> bounds -> gain -> cost -> cost_bound -> sls.

One dataset is one (system, sigma_w, N) over a range of repetitions; every
stage is vectorised over the (rep, estimator/gamma) grid (R, E) and fills
record fields and per-cell notes (docs/science.md sections 2-8,
docs/spec.md#record-fields). The observer stages (gain, cost, cost_bound, sls) are in
:mod:`svrobs_core.observer_stages`.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from . import bounds as _bounds
from . import estimators as _est
from . import gains as _gains
from . import uncertainty as _unc
from .array_types import FloatArray, IntArray
from .bounds import BoundsResult
from .notes import Notes
from .observer_stages import design, observer_stages, sls_stage
from .planning import EstimatorAxis
from .rollouts import gram_data, sample_count
from .seeding import seed_key
from .spec import STAGES, ExperimentSpec
from .stage_cells import Cells, StageCells
from .uncertainty_stage import sound_bounds

# Above this cond(Z Z^T + g I) the solve is not trusted to ~1e-9 relative
# (tests/core/test_accuracy.py: 6e-12 at 1e18): the cell keeps its estimate
# but its certificates are null, with a note (a certificate rests on
# a successful computation).
ESTIMATE_COND_LIMIT = 1e20
CERTIFICATES = ("stable_certified", "thm1_holds_A", "thm1_holds_B", "certified")
# What ``reuse_gain`` carries to the next N: (L, A_hat, radius) of the chosen gain.
GainState = tuple[FloatArray, FloatArray, FloatArray]


# ---------------------------------------------------------------------------
# dataset driver
# ---------------------------------------------------------------------------
def run_dataset(
    spec: ExperimentSpec,
    *,
    si: int,
    wi: int,
    N: int,
    reps: Sequence[int],
    axis: EstimatorAxis,
    prev_gain: GainState | None = None,
) -> tuple[Any, ...]:
    """All stages for one (system, sigma_w, N) and a range of reps.

    -> (fields, notes, N0, gain state for ``reuse_gain`` or None)."""
    return run_dataset_variants(
        [spec], si=si, wi=wi, N=N, reps=reps, axis=axis, prev_gains=[prev_gain]
    )[0]


# The fields in which specs that share their data and estimates may differ
# (:func:`shares_data`): the bounds method and its options.
BOUNDS_KEYS = frozenset({"bounds_method", "S", "lambda0", "boot_reps", "boot_sigma_w"})


def shares_data(parent: ExperimentSpec, other: ExperimentSpec) -> bool:
    """True when ``other``'s data and estimates on each of its N are ``parent``'s:
    the same spec up to the bounds method and its options, with N a subset of
    the parent's (the whole N grid when ``reuse_gain`` couples them)."""
    a, b = parent.to_dict(), other.to_dict()
    for k in (a.keys() | b.keys()) - BOUNDS_KEYS - {"N"}:
        if a.get(k) != b.get(k):
            return False
    if parent.reuse_gain:
        return list(a["N"]) == list(b["N"])
    return set(b["N"]) <= set(a["N"])


def run_dataset_variants(
    specs: Sequence[ExperimentSpec],
    *,
    si: int,
    wi: int,
    N: int,
    reps: Sequence[int],
    axis: EstimatorAxis,
    prev_gains: Sequence[Any] | None = None,
    timings: dict[Any, float] | None = None,
) -> list[tuple[Any, ...]]:
    """:func:`run_dataset` for specs that share their data and estimates
    (:func:`shares_data` with ``specs[0]``): the rollouts are simulated, the
    Gram matrices factorised and the estimates computed once; then each spec's
    stages run on them (the sound boxes on one factor of the data,
    :func:`svrobs_core.uncertainty.data_factor`). -> one (fields, notes, N0, gain state) per spec; its
    records are the ones the spec gives on its own (the same arithmetic).
    ``timings``: a dict that gets each spec's CPU seconds added under its index
    (the shared part counts for the first), those of its Monte Carlo J under
    ``("mc", index)``."""
    clock = time.process_time()
    spec = specs[0]
    prev_gains = [None] * len(specs) if prev_gains is None else list(prev_gains)
    system = spec.systems[si]
    sigma_w = spec.sigma_w[wi]
    n = system.n
    keys = [seed_key(si, wi, N, r) for r in reps]
    # the sound boxes factorise the data themselves (svrobs_core.data_factor)
    need_data = any(e in ("ols", "shrunk-ols") for e in spec.estimators) or any(
        s.has("bounds") and s.bounds_method != "paper" for s in specs
    )
    G, P, Z, F = gram_data(
        system,
        sigma_w,
        N,
        spec.T0,
        seed=spec.seed,
        keys=keys,
        data=spec.data,
        x0_std=spec.x0_std,
        keep_data=need_data,
        rng=spec.rng,
        draws=spec.draws,
    )
    N0 = sample_count(N, spec.T0, spec.data)

    def rows_data(rows: IntArray) -> tuple[FloatArray, FloatArray]:
        # the regression data of these reps, for the ill-conditioned SVR cells
        if Z is not None and F is not None:
            return Z[rows], F[rows]
        _, _, Zr, Fr = gram_data(
            system,
            sigma_w,
            N,
            spec.T0,
            seed=spec.seed,
            keys=[keys[i] for i in rows],
            data=spec.data,
            x0_std=spec.x0_std,
            keep_data=True,
            rng=spec.rng,
            draws=spec.draws,
        )
        assert Zr is not None and Fr is not None  # keep_data=True returns the data
        return Zr, Fr

    try:
        theta, cond = _estimate(spec, G=G, P=P, Z=Z, F=F, N0=N0, data=rows_data)
    except Exception as exc:
        _tag(exc, "estimate", 0)
        raise
    A_hat, B_hat = theta[..., :n], theta[..., n:]
    R, E = theta.shape[:2]
    finite = np.isfinite(theta).all(axis=(-2, -1))
    unreliable = finite & ~(cond <= ESTIMATE_COND_LIMIT)
    estimate = {
        "A_hat": A_hat,
        "B_hat": B_hat,
        "rmse_A": _rmse(A_hat, system.A),
        "rmse_B": _rmse(B_hat, system.B),
    }
    results: list[tuple[Any, ...]] = []
    shared: dict[str, Any] = {}  # the data's factor, made by the first spec with a sound box
    if timings is not None:
        timings[0] = timings.get(0, 0.0) + time.process_time() - clock
    for s, prev_gain in zip(specs, prev_gains):
        clock = time.process_time()
        out: dict[str, np.ndarray] = dict(estimate)
        notes = Notes((R, E))
        notes.add(
            ~finite,
            "estimate: not finite (the simulated data leave the double range, or the"
            " regularised problem is numerically singular)",
        )
        notes.add(
            unreliable,
            f"estimate: data too ill-conditioned (cond(Z Z^T + g I) > {ESTIMATE_COND_LIMIT:g},"
            f" or the error its solve's refinement measures above {_est.REFINE_STEP_TRUST:g} of it):"
            " certificates withheld",
        )
        skipped = [st for st in STAGES if not s.has(st)]
        if skipped:
            notes.add(True, "stages not run: " + ", ".join(skipped))
        cells = StageCells(
            spec=s,
            system=system,
            sigma_w=sigma_w,
            keys=keys,
            axis=axis,
            A_hat=A_hat,
            B_hat=B_hat,
            out=out,
            notes=notes,
        )
        try:
            state = _run_stages(cells, N=N, N0=N0, prev_gain=prev_gain, data=(G, Z, F, shared))
        except Exception as exc:
            _tag(exc, cells.stage, len(results))
            raise
        if unreliable.any():
            for f in CERTIFICATES:
                if f in out:
                    withheld = np.array(out[f], dtype=object)
                    withheld[unreliable] = None
                    out[f] = withheld
        results.append((out, notes, N0, state))
        if timings is not None:
            i = len(results) - 1
            timings[i] = timings.get(i, 0.0) + time.process_time() - clock - cells.mc_seconds
            timings["mc", i] = timings.get(("mc", i), 0.0) + cells.mc_seconds
    return results


def _tag(exc: BaseException, stage: str, index: int) -> None:
    """Name the stage (and which spec of :func:`run_dataset_variants`) on an exception
    passing through, without changing it (its type is what callers act on)."""
    if not hasattr(exc, "svrobs_stage"):
        setattr(exc, "svrobs_stage", (stage, index))  # noqa: B010 (an attribute of no exception type)
        exc.add_note(f"svrobs: raised in stage {stage!r}")


def failed_stage(exc: BaseException) -> tuple[str, int] | None:
    """(stage, index of the spec in :func:`run_dataset_variants`) an exception was raised in."""
    return getattr(exc, "svrobs_stage", None)


def _estimate(
    spec: ExperimentSpec,
    *,
    G: FloatArray,
    P: FloatArray,
    Z: FloatArray | None,
    F: FloatArray | None,
    N0: int,
    data: Callable[[IntArray], tuple[FloatArray, FloatArray]],
) -> tuple[FloatArray, FloatArray]:
    """Theta for every (rep, estimator/gamma): (R, E, n, d), and cond(Z Z^T + g I)
    of each cell (R, E); docs/science.md#2-estimators.

    SVR needs only the sufficient statistics G = Z Z^T, P = F Z^T, and the
    data of its ill-conditioned cells (``data(rows)``); OLS (and shrunk OLS)
    use the data themselves (iterative refinement, QR fallback).
    """
    parts: list[FloatArray] = []
    conds: list[FloatArray] = []
    ols: tuple[FloatArray, FloatArray] | None = None
    G_n = len(spec.gamma)
    for e in spec.estimators:
        if e == "svr":
            theta, cond = _est.svr_from_gram(
                G, P, N0, spec.gamma, loss_scale=spec.loss_scale, data=data, return_cond=True
            )
            parts.append(theta)
            conds.append(cond)
            continue
        if ols is None:  # ols, shrunk-ols: the data are kept for them
            assert Z is not None and F is not None
            ols = _est.fit_ols(Z, F, return_cond=True)
        theta_ols, cond_ols = ols
        if e == "ols":
            parts.append(theta_ols[:, None])
            conds.append(cond_ols[:, None])
        else:  # shrunk-ols
            parts.append(_est.shrunk_ols(theta_ols, spec.gamma))
            conds.append(np.repeat(cond_ols[:, None], G_n, axis=1))
    return np.concatenate(parts, axis=1), np.concatenate(conds, axis=1)


def _rmse(X: FloatArray, X_true: FloatArray) -> FloatArray:
    with np.errstate(over="ignore", invalid="ignore"):  # huge estimates: inf, noted with them
        rmse: FloatArray = np.sqrt(np.mean((X - X_true) ** 2, axis=(-2, -1)))
    return rmse


def _run_stages(
    c: Cells,
    *,
    N: int,
    N0: int,
    prev_gain: GainState | None,
    data: tuple[FloatArray, FloatArray | None, FloatArray | None, dict[str, Any]],
) -> GainState | None:
    """bounds, then the observer stages; -> the gain state for ``reuse_gain``.

    The gain is designed on the chosen method's box: the paper's (centre
    (1+gamma) A_tilde, scalar radius r_A) or, for the sound methods of
    docs/uncertainty.md, centre A_hat and the radius matrix R_A."""
    spec, out = c.spec, c.out
    if not spec.has("bounds"):
        return None
    c.stage = "bounds"
    if spec.bounds_method == "paper":
        b, gamma, radius = _paper_bounds(c, N=N, N0=N0)
    else:
        G, Z, F, shared = data
        if "factor" not in shared and Z is not None and F is not None:  # one factor for every box
            shared["factor"] = _unc.data_factor(Z, F)
        sound = sound_bounds(c, G=G, Z=Z, F=F, N=N, N0=N0, factor=shared.get("factor"))
        out.update(sound.fields)
        b, gamma, radius = sound.result, np.zeros(len(c.axis.names)), sound.box.R_A
    state = _gain_stages(c, b, gamma, radius, prev_gain) if spec.has("gain") else None
    if spec.has("sls"):
        c.stage = "sls"
        sls_stage(c, b)
    return state


def _gain_stages(
    c: Cells,
    b: BoundsResult,
    gamma: FloatArray,
    radius: FloatArray,
    prev_gain: GainState | None,
) -> GainState:
    """gain (with the reuse policy), cost, cost_bound; -> the gain state for ``reuse_gain``."""
    spec, system, notes = c.spec, c.system, c.notes
    c.stage = "gain"
    matrix = spec.bounds_method != "paper"
    designed, k_hat_reasons = design(c, gamma, radius, matrix=matrix)
    if k_hat_reasons is not None:
        notes.add_reasons(k_hat_reasons, "K_hat")
    shape = c.shape
    radius = np.broadcast_to(radius, shape + (radius.shape[-2:] if matrix else ()))
    state = (designed.L, c.A_hat, radius)
    # reuse_gain: keep the previous L while certified (docs/science.md#44-reuse_gain)
    if prev_gain is not None:
        L_prev, A_prev, r_prev = prev_gain
        radii = np.stack([r_prev, radius])
        reuse = _gains.reuse_gains(
            np.stack([L_prev, designed.L]),
            np.stack([A_prev, c.A_hat]),
            gamma,
            r_A=radii,  # read only without R_A
            C=system.C,
            R_A=radii if matrix else None,
        )
        designed = _gains.GainResult(
            L=reuse.L[1], g_L=reuse.g_L[1], certified=reuse.certified[1], feasible=None
        )
        notes.add(reuse.reused[1], "gain: reused from the previous N")
        state = (reuse.L[1], c.A_hat, radius)
    observer_stages(c, b, designed)
    return state


def _paper_bounds(c: Cells, *, N: int, N0: int) -> tuple[BoundsResult, FloatArray, FloatArray]:
    """The paper's bounds (docs/science.md#3-error-bounds-theorem-1-lemma-2-corollary-1) ->
    (BoundsResult, gamma of the centre, r_A per estimator)."""
    spec, system, out, notes = c.spec, c.system, c.out, c.notes
    gamma = c.axis.gamma_array
    rad = _bounds.radii(
        n=system.n,
        m=system.m,
        N=N,
        N0=N0,
        T0=spec.T0,
        sigma_u=system.sigma_u,
        sigma_w=c.sigma_w,
        gamma=gamma,
        M=spec.M,
        delta=spec.delta,
    )
    b = _bounds.evaluate_bounds(c.A_hat, c.B_hat, gamma, rad, A_true=system.A, B_true=system.B)
    notes.add_reasons(rad.reason_A, None)
    notes.add_reasons(rad.reason_B, None)
    shape = c.shape
    n, m = system.n, system.m
    out.update(
        {
            "bounds_method": np.broadcast_to(np.array("paper", dtype=object), shape),
            "radii_A": np.broadcast_to(rad.r_A[:, None, None], shape + (n, n)),
            "radii_B": np.broadcast_to(rad.r_B[:, None, None], shape + (n, m)),
            "H_A": np.broadcast_to(rad.H_A, shape),
            "H_B": np.broadcast_to(rad.H_B, shape),
            "r_A": np.broadcast_to(rad.r_A, shape),
            "r_B": np.broadcast_to(rad.r_B, shape),
            "eps_A": b.eps_A,
            "eps_B": b.eps_B,
            "coverage_A": b.coverage_A,
            "coverage_B": b.coverage_B,
            "thm1_holds_A": b.thm1_holds_A,
            "thm1_holds_B": b.thm1_holds_B,
            "rho_upper_bound": b.rho_upper_bound,
            "stable_certified": b.stable_certified,
        }
    )
    return b, gamma, rad.r_A
