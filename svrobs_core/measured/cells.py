"""The stage chain on a batch of measured datasets (docs/measured.md#records).

``run_cells`` takes the regression data of R datasets with the same sample
count, stacked (Z (R, d, N0), F (R, n_rows, N0)), and fills the record fields
over the (dataset, estimator/gamma) grid (R, E), vectorised over it, with the
stage functions a simulated job uses (estimation, the self-normalized box,
the gain design, the Kalman gain, the costs, Theorem 3, SLS) called with the
estimate where a simulated job passes its true system. Fields that need the
true system are left out (null in the records) with the note ``NO_TRUTH``.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import TypeAlias

import numpy as np

from .. import bounds as _bounds
from .. import cost_bound as _cb
from .. import cost_check as _check
from .. import kalman as _kalman
from .. import uncertainty as _unc
from ..array_types import Array, BoolArray, FloatArray
from ..bounds import BoundsResult
from ..data_factor import GramFactor, data_factor, estimate_margin
from ..estimators import REFINE_STEP_TRUST, fit_ols
from ..norms import stability_radius
from ..notes import Notes
from ..observer_stages import checked_j_star, design
from ..pipeline import CERTIFICATES, ESTIMATE_COND_LIMIT, _estimate
from ..planning import EstimatorAxis
from ..spec import STAGES, ExperimentSpec
from ..stage_cells import StageCells  # the context the stage functions read
from ..uncertainty_stage import bounds_from_box, ridge_axis, sound_box
from .data import StateModel
from .noise import REASON_RANGE, noise_level, residual_error, residual_sum

NO_TRUTH = "measured data: no true system"
# below this magnitude a number's square underflows (about 1.5e-154)
_SQRT_TINY = float(np.sqrt(np.finfo(float).tiny))
# The fields each stage fills on a simulated job that need the true system.
TRUTH_FIELDS = {
    "estimate": ("rmse_A", "rmse_B"),
    "bounds": ("coverage_A", "coverage_B"),
    "gain": ("rho_true",),
    "cost": ("J_exact", "J_stationary", "J_mc", "J_mc_se", "cost_ratio"),
    "cost_bound": ("delta_J",),
}
PLUG_IN = (
    "measured data: K and J_star are the estimated system's; J_bound and J_opt use its"
    " norms and K in place of the true system's (no guarantee)"
)


@dataclass(frozen=True)
class Observer:
    """What stands where a simulated job has its true system: C and the noise
    levels of the observer model, and no A, B."""

    C: FloatArray
    sigma_u: float
    sigma_v: float
    A: None = None
    B: None = None


# A batch of measured datasets' context: no true system; sigma_w None until the
# noise level is known, then the box's and the observer model's (a number or (R, 1)).
MeasuredCells: TypeAlias = StageCells[Observer, float | FloatArray | None]


def run_cells(
    spec: ExperimentSpec,
    *,
    Z: FloatArray,
    F: FloatArray,
    model: StateModel,
    N: int,
    keys: list[tuple[int, int, int, int]],
    axis: EstimatorAxis,
    observer: Observer,
) -> tuple[dict[str, Array | None], Notes]:
    """All stages for R datasets of one N with the same N0 -> (fields, notes)."""
    R, _, N0 = Z.shape
    Zt = np.swapaxes(Z, -1, -2)
    with np.errstate(over="ignore"):  # data beyond the range: noted below
        G, P = Z @ Zt, F @ Zt
    rows, cond = _estimate(spec, G=G, P=P, Z=Z, F=F, N0=N0, data=lambda r: (Z[r], F[r]))
    # data whose squares leave the range: Z Z^T is infinite or subnormal (digits lost)
    scale = _out_of_range(Z, G)
    rows = np.where(scale[:, None, None, None], np.nan, rows)
    theta = model.full(rows)
    n = model.n
    notes = Notes(theta.shape[:2])
    c: MeasuredCells = StageCells(
        spec=spec,
        system=observer,
        sigma_w=None,
        keys=keys,
        axis=axis,
        A_hat=theta[..., :n],
        B_hat=theta[..., n:],
        out={"A_hat": theta[..., :n], "B_hat": theta[..., n:]},
        notes=notes,
    )
    ran = [st for st in STAGES if spec.has(st)]
    truth = [f for st in ran for f in TRUTH_FIELDS.get(st, ())]
    notes.add(True, f"{NO_TRUTH} (null: {', '.join(truth)})")
    withheld = ~(cond <= ESTIMATE_COND_LIMIT) | ~np.isfinite(theta).all(axis=(-2, -1))
    notes.add(withheld & scale[:, None], f"estimate: certificates withheld: {REASON_RANGE}")
    notes.add(
        withheld & ~scale[:, None],
        f"estimate: not finite, or cond(Z Z^T + g I) > {ESTIMATE_COND_LIMIT:g} or the error"
        f" its solve's refinement measures above {REFINE_STEP_TRUST:g} of it (the data do not"
        " excite every direction well enough): certificates withheld",
    )
    if len(ran) < len(STAGES):
        notes.add(True, "stages not run: " + ", ".join(st for st in STAGES if st not in ran))
    # the data's factor: the noise bound's and the box's (docs/measured.md#sound-set)
    fac = data_factor(Z, _full_targets(model, Z, F))
    theta_ols = rows[:, axis.names.index("ols")] if "ols" in axis.names else fit_ols(Z, F)
    sigma_box, sigma_model, sigma_err = _noise(
        c, fac, Z=Z, F=F, theta_ols=theta_ols, model=model, N0=N0
    )
    if spec.has("bounds"):
        _bounds_and_observer(
            c,
            sigma_box,
            sigma_model,
            model=model,
            Z=Z,
            N=N,
            N0=N0,
            fac=fac,
            sigma_err=sigma_err,
            scale=scale,
            theta_ols=model.full(theta_ols),
        )
    for f in CERTIFICATES:
        if f in c.out and withheld.any():
            # None: an object scalar, which numpy's stubs do not admit in where()
            c.out[f] = np.where(withheld, None, np.asarray(c.out[f], dtype=object))  # type: ignore[call-overload]
    return c.out, notes


def _out_of_range(Z: FloatArray, G: FloatArray) -> BoolArray:
    """(R,) True where the data's squares leave the double range: Z Z^T overflows, or a
    regressor's largest magnitude is nonzero but its square underflows (OLS is
    scale-equivariant: such data are well posed once rescaled)."""
    top = np.abs(Z).max(axis=-1)  # (R, d)
    tiny = (top > 0) & (top < _SQRT_TINY)
    out: BoolArray = ~np.isfinite(G).all(axis=(-2, -1)) | tiny.any(axis=-1)
    return out


def _noise(
    c: MeasuredCells,
    fac: GramFactor,
    *,
    Z: FloatArray,
    F: FloatArray,
    theta_ols: FloatArray,
    model: StateModel,
    N0: int,
) -> tuple[float | FloatArray, float | FloatArray, float | FloatArray]:
    """(sigma of the box, sigma of the observer model, the relative error of the
    box's sigma), each (R, 1) or a number; the notes say what was estimated
    (docs/measured.md#sigma-w-estimate). ``fac``: the data's factor (full targets);
    ``theta_ols`` (R, n_rows, d) the OLS estimate of the estimated rows."""
    spec, notes = c.spec, c.notes
    n_rows = F.shape[1]
    rss = residual_sum(Z, F, theta_ols)
    # the OLS estimate's distance from the exact fit, in the norm of Z Z^T
    margin = estimate_margin(fac, model.full(theta_ols), lam=0.0)[:, :n_rows]
    err, q, lam0 = residual_error(Z, F, theta_ols, margin, rss), spec.delta / 4, spec.lambda0
    lvl = noise_level(fac, rss, n=n_rows, N0=N0, delta1=q, delta2=q, lambda0=lam0, resid_err=err)
    given = spec.measured.sigma_w
    if given is not None:
        with np.errstate(invalid="ignore"):
            below = lvl.sigma_low > given
        texts = np.array(
            [
                f"noise: the data contradict the given sigma_w = {given:g}: its lower confidence"
                f" bound is {s:.4g} (1 - delta/4); the set assumes the noise level is at most"
                " the given one"
                if a
                else None
                for s, a in zip(lvl.sigma_low.tolist(), below.tolist())
            ],
            dtype=object,
        )
        notes.add_reasons(texts[:, None], None)
        return given, given, 0.0
    texts = np.array(
        [
            f"noise: sigma_w estimated: sigma_hat_w = {s:.4g} (residual, for K and the costs),"
            f" sigma_bar_w = {b:.4g} (upper bound at 1 - delta/2, for the set)"
            for s, b in zip(lvl.sigma_hat.tolist(), lvl.sigma_bar.tolist())
        ],
        dtype=object,
    )
    finite = np.isfinite(lvl.sigma_bar)
    # None: an object scalar, which numpy's stubs do not admit in where()
    notes.add_reasons(np.where(finite, texts, None)[:, None], None)  # type: ignore[call-overload]
    notes.add_reasons(lvl.reason[:, None], "noise")
    return lvl.sigma_bar[:, None], lvl.sigma_hat[:, None], lvl.rel_err[:, None]


def _bounds_and_observer(
    c: MeasuredCells,
    sigma_box: float | FloatArray,
    sigma_model: float | FloatArray,
    *,
    model: StateModel,
    Z: FloatArray,
    N: int,
    N0: int,
    fac: GramFactor,
    sigma_err: float | FloatArray,
    scale: BoolArray,
    theta_ols: FloatArray,
) -> None:
    """The box from the data's own factor ``fac`` (of the full targets), with the
    estimate's rounding margin and the error of an estimated sigma (``sigma_err``)
    in its certificate radii (docs/uncertainty.md#certificates-on-the-boxes;
    the known rows of the ARX state with radius 0, docs/measured.md#arx), null
    for the ridge cells where the OLS box refutes ``S`` (``theta_ols`` (R, n, d),
    docs/measured.md#sound-set), its certificates, then the observer stages on
    the estimate."""
    spec, out, notes, C = c.spec, c.out, c.notes, c.system.C
    estimate = spec.measured.sigma_w is None
    boxed = replace(c, spec=replace(spec, delta=spec.delta / 2) if estimate else spec)
    boxed.sigma_w = sigma_box
    box = sound_box(boxed, G=None, Z=Z, F=None, N=N, N0=N0, factor=fac, sigma_err=sigma_err)
    # a null box of data out of the range says so, not what the overflow looked like
    nulled = scale[:, None] & (box.reason != None)  # noqa: E711 - elementwise on objects
    box = replace(box, reason=np.where(nulled, REASON_RANGE, box.reason))
    if model.lags is not None:
        known = ~model.estimated[:, None]
        assert box.R_A_up is not None and box.R_B_up is not None  # sound_box sets them
        box = replace(
            box,
            R_A=np.where(known, 0.0, box.R_A),
            R_B=np.where(known, 0.0, box.R_B),
            R_A_up=np.where(known, 0.0, box.R_A_up),
            R_B_up=np.where(known, 0.0, box.R_B_up),
        )
    if spec.bounds_method == "self-normalized":
        box = _ridge_premise(c, box, fac, theta_ols, model=model, N0=N0, spec=boxed.spec)
    sound = bounds_from_box(c, box)
    out.update(sound.fields)
    b = sound.result
    R_cert = sound.box.R_A  # the certificate radii R_up (NaN where not bounded)
    c.sigma_w = sigma_model
    unmeasured = ~(C != 0).any(axis=0)  # state columns that no row of C reads
    if unmeasured.any():
        with np.errstate(invalid="ignore"):
            floor = (np.abs(c.A_hat) + R_cert)[..., unmeasured].sum(axis=-1).max(axis=-1)
        notes.add(
            floor >= 1.0,
            "gain: no L is certified: in the columns C does not measure, a row of"
            " |A_hat| + R_A sums to >= 1 already (docs/measured.md#arx)",
        )
    kal = _kalman.kalman_predictor(c.A_hat, C, sigma_model, c.system.sigma_v)
    if not kal.ok.all():
        notes.add_reasons(kal.reasons(), "K")
    K = kal.K
    L = None
    if spec.has("gain"):
        L = _gain(c, R_cert, K)
    norms = None
    if spec.has("cost") or spec.has("sls"):
        notes.add(True, PLUG_IN)
        norms = _estimate_norms(c.A_hat, c.B_hat, C, K)
    if spec.has("cost"):
        noise = dict(sigma_u=c.system.sigma_u, sigma_w=sigma_model, sigma_v=c.system.sigma_v)
        J, bad = checked_j_star(c.A_hat, c.B_hat, K, C, horizon=spec.horizon, **noise)
        notes.add(bad, f"J_star: {_check.REASON_ROUNDING}")
        out["J_star"] = np.where(bad, np.nan, J)
    if spec.has("cost_bound"):
        assert L is not None and norms is not None  # cost_bound needs gain and cost
        t3 = _cb.theorem3_bound(
            c.A_hat,
            L,
            C,
            K,
            eps_A=b.eps_A,
            eps_B=b.eps_B,
            sigma_u=c.system.sigma_u,
            sigma_v=c.system.sigma_v,
            norms=norms,
            rho_F=stability_radius(c.A_hat - L @ C),
        )
        notes.add_reasons(t3.reason, "J_bound")
        out["J_bound"] = t3.J_b
    if spec.has("sls"):
        assert norms is not None  # computed for the sls stage above
        _sls(c, b, K, norms)


def _ridge_premise(
    c: MeasuredCells,
    box: _unc.BoxResult,
    fac: GramFactor,
    theta_ols: FloatArray,
    *,
    model: StateModel,
    N0: int,
    spec: ExperimentSpec,
) -> _unc.BoxResult:
    """``box`` with its ridge (SVR) cells null where the data refute ``S``.

    The ridge box needs ``||theta_i|| <= S`` for every row; the ridge estimate's own
    norm cannot show a violation, as the ridge shrinks it. The OLS box of the same
    data (same sigma_w and delta, no S) contains every true row with the box's
    probability; where even its smallest norm, ``||max(|theta_ols_ij| - R_ij, 0)||``
    over an estimated row, exceeds S, the true row's does; where even its largest,
    ``||theta_ols_ij| + R_ij||``, is within S for every row, S holds. Where S is the
    default (``sqrt(2) M``, not given) and the data neither refute nor confirm it, the
    ridge box says that it assumes it (docs/measured.md#sound-set)."""
    lam, _ = ridge_axis(c.axis, N0, spec.loss_scale)
    if not (lam > 0).any():
        return box
    sigma = np.asarray(box.sigma_w, dtype=float)[:, 0]  # (R, E): one sigma per dataset
    ols = _unc.self_normalized_box(
        fac,
        theta_ols,
        sigma_w=sigma,
        delta=spec.delta,
        lam=0.0,
        S=spec.S_bound,
        lambda0=spec.lambda0,
    )
    R = np.concatenate([ols.R_A, ols.R_B], axis=-1)[:, model.estimated]
    size = np.abs(theta_ols[:, model.estimated])
    with np.errstate(invalid="ignore", over="ignore"):  # a null OLS box: NaN, no refutation
        floor = np.linalg.norm(np.maximum(size - R, 0.0), axis=-1).max(axis=-1)
        ceiling = np.linalg.norm(size + R, axis=-1).max(axis=-1)
        refuted = (floor > spec.S_bound)[:, None] & (lam > 0) & box.ok
        confirmed = (ceiling <= spec.S_bound)[:, None]
    if spec.S is None:
        c.notes.add(
            (lam > 0) & box.ok & ~refuted & ~confirmed,
            f"bounds: the SVR box assumes every row of [A B] has norm <= S = {spec.S_bound:g}"
            " (the default, sqrt(2) M), which the data do not confirm: set S",
        )
    if not refuted.any():
        return box
    texts = np.array(
        [
            f"S = {spec.S_bound:g} is refuted by the data: a row of the OLS box has norm"
            f" >= {f:.4g} (set S to bound the rows of [A B]; the ridge box needs it)"
            for f in floor.tolist()
        ],
        dtype=object,
    )
    reason = np.where(refuted, texts[:, None], box.reason)
    null = refuted[..., None, None]
    return replace(
        box,
        reason=reason,
        R_A=np.where(null, np.nan, box.R_A),
        R_B=np.where(null, np.nan, box.R_B),
        eps_A=np.where(refuted, np.nan, box.eps_A),
        eps_B=np.where(refuted, np.nan, box.eps_B),
        beta=None if box.beta is None else np.where(refuted, np.nan, box.beta),
        R_A_up=None if box.R_A_up is None else np.where(null, np.nan, box.R_A_up),
        R_B_up=None if box.R_B_up is None else np.where(null, np.nan, box.R_B_up),
    )


def _full_targets(model: StateModel, Z: FloatArray, F: FloatArray) -> FloatArray:
    """The targets of every row of the state (R, n, N0): F for the estimated rows
    (the first ny), and for the known rows of the ARX state the regressor each
    copies (a shift or the input), so that the factor of [Z^T F^T] matches the
    full [A B]."""
    if model.lags is None:
        return F
    known = np.concatenate(model.known_rows(), axis=1)[~model.estimated]
    return np.concatenate([F, Z[:, np.argmax(known, axis=1)]], axis=1)


def _gain(c: MeasuredCells, R_A: Array, K: FloatArray) -> Array:
    """The certified gain on the box (centre A_hat, from the Kalman gain of A_hat)."""
    out, notes = c.out, c.notes
    designed, k_hat_reasons = design(c, np.zeros(len(c.axis.names)), R_A, matrix=True)
    if k_hat_reasons is not None:
        notes.add_reasons(k_hat_reasons, "K_hat")
    g = designed.g_L
    notes.add(~np.isfinite(g), "certified: undefined (no finite gain L or radius)")
    assert designed.feasible is not None  # design_gain sets it
    with np.errstate(invalid="ignore"):
        notes.add(
            ~designed.feasible & np.isfinite(g), "gain: margin not reachable, L minimises g(L)"
        )
    out.update(
        L=designed.L,
        g_L=g,
        certified=_bounds.nullable(designed.certified, np.isfinite(g)),
        K=K,
    )
    return designed.L


def _estimate_norms(
    A_hat: FloatArray, B_hat: FloatArray, C: FloatArray, K: FloatArray
) -> _cb.TrueSystemNorms:
    """The norms Theorem 3 and SLS take from the true system, of the estimate
    (per cell); with m = 0 the input term's norm is 0 (there is no input)."""
    if B_hat.shape[-1]:
        return _cb.true_system_norms(A_hat, B_hat, C, K)
    norms = _cb.true_system_norms(A_hat, np.zeros(A_hat.shape[:-1] + (1,)), C, K)
    h = np.asarray(norms.hinf_PhiA_B)
    return replace(norms, hinf_PhiA_B=np.where(np.isfinite(h), 0.0, h))


def _sls(c: MeasuredCells, b: BoundsResult, K: FloatArray, norms: _cb.TrueSystemNorms) -> None:
    """J_opt by SLS on the estimate (cvxpy + Clarabel, one program per cell) and
    the paper's bound on it, with the estimate's K and norms
    (docs/science.md#8-sls-sub-optimal-observer-j_opt)."""
    from .. import sls as _sls

    spec, sys_ = c.spec, c.system
    R, E = c.shape
    eps1 = _sls.eps_max(b.eps_A, b.eps_B)
    F = np.broadcast_to(
        _sls.sls_F(
            eps1, norms.hinf_PhiA_B, norms.hinf_PhiA_K, sigma_u=sys_.sigma_u, sigma_v=sys_.sigma_v
        ),
        (R, E),
    )
    if spec.sls_C_bound is None:
        with np.errstate(invalid="ignore"):
            C_bound = np.broadcast_to(_sls.default_C_bound(K, norms.h2_closed), (R, E))
    else:
        C_bound = np.full((R, E), spec.sls_C_bound)
    run = np.isfinite(F) & np.isfinite(C_bound) & np.isfinite(K).all(axis=(-2, -1))
    c.notes.add(~run, "J_opt: not run (F or C_bound undefined: a norm of the estimate is infinite)")
    J_opt = np.full((R, E), np.nan)
    status = np.full((R, E), "not_run", dtype=object)
    for ri, ei in zip(*np.nonzero(run)):  # a convex program per cell
        res = _sls.sls_observer(
            c.A_hat[ri, ei],
            sys_.C,
            K[ri, ei],
            F[ri, ei],
            C_bound=C_bound[ri, ei],
            T_fir=spec.sls_T_fir,
        )
        J_opt[ri, ei], status[ri, ei] = res.J_opt, res.status
    bound, reason = _sls.jopt_upper_bound_from_norms(
        b.eps_A, eps1, C_bound, norms, sigma_u=sys_.sigma_u, sigma_v=sys_.sigma_v
    )
    c.notes.add_reasons(reason, None)
    c.out.update(J_opt=J_opt, sls_status=status, J_opt_bound=bound)
