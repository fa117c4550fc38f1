"""Validation of an identified model on held-out rollouts, and the excitation
check of the training data (docs/measured.md#validation).

``validate(model, holdout) -> ValidationResult``: one-step prediction NRMSE
and fit %, open-loop simulation fit %, Ljung-Box whiteness of the residuals
and the input-residual cross-correlation test, per measured channel, pooled
over the held-out rollouts. ``excitation(data)``: the eigenvalues of the
regressors' mean Gram. ``validation_summary(spec, data)``: both, for each
estimator and gamma of a dataset spec, as JSON for the application layer.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import Any, cast

import numpy as np

from .. import estimators as _est
from ..array_types import FloatArray
from ..records import json_value
from ..spec import ExperimentSpec
from .data import MeasuredData, StateModel, regression

MAX_LAGS = 20
BAND_Z = 2.5758293035489004  # two-sided 99 % normal quantile: the autocorrelation band
NOT_EXCITED_RTOL = 1e-10  # lambda_min <= this lambda_max: a direction without data
WEAK_COND = 1e8  # above this condition number: weakly excited


def plain(value: object) -> Any:
    """dicts, lists and arrays -> JSON-able Python values (NaN/inf -> None)."""
    if isinstance(value, dict):
        return {k: plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [plain(v) for v in value]
    return json_value(value)


@dataclass(frozen=True)
class Model:
    """An identified model in its state coordinates: x+ = A x + B u (the ARX
    state when ``lags`` is (p, q)); ``estimator``, ``gamma``: how it was fitted."""

    A: FloatArray
    B: FloatArray
    lags: tuple[int, int] | None = None
    estimator: str = "ols"
    gamma: float | None = None


@dataclass
class Excitation:
    """Persistency of excitation of the regressors z = [x; u] of a dataset.

    eigenvalues (d,) of the mean Gram Z Z^T / N0, ascending (inf where one is beyond
    the float range); direction: the unit eigenvector of the smallest (over
    ``names``); cond: lambda_max / lambda_min (inf when lambda_min is 0), from the
    Gram of Z / max|Z|, so finite data of any magnitude has it; notes: what they
    mean."""

    names: tuple[str, ...]
    N0: int
    eigenvalues: FloatArray
    direction: FloatArray
    cond: float
    notes: list[str] = field(default_factory=list)

    @property
    def lambda_min(self) -> float:
        return float(self.eigenvalues[0])

    @property
    def lambda_max(self) -> float:
        return float(self.eigenvalues[-1])

    def to_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = plain(
            {
                "names": list(self.names),
                "N0": self.N0,
                "eigenvalues": self.eigenvalues,
                "lambda_min": self.lambda_min,
                "lambda_max": self.lambda_max,
                "cond": self.cond,
                "direction": self.direction,
                "notes": self.notes,
            }
        )
        return out


def excitation(data: MeasuredData, lags: tuple[int, int] | None = None) -> Excitation:
    """The excitation check of ``data``'s regressors (in the ARX state with ``lags``)."""
    sm = StateModel(ny=data.n, m=data.m, lags=lags)
    lifted = sm.lift(data)
    Z, _ = regression(lifted)
    return regressor_excitation(Z, tuple(lifted.state_names) + tuple(lifted.input_names))


def regressor_excitation(Z: FloatArray, names: tuple[str, ...]) -> Excitation:
    """The excitation check of the regressors ``Z`` (d, N0), channels ``names``."""
    N0 = Z.shape[1]
    # the Gram of Z / max|Z| (entries at most N0 / N0 = 1): no overflow nor underflow
    # for finite data of any magnitude; the eigenvalues are scaled back after
    scale = float(np.max(np.abs(Z))) if Z.size else 0.0
    Zs = Z / scale if scale > 0 else Z
    lam_s, V = np.linalg.eigh(Zs @ Zs.T / N0)
    lam_s = np.maximum(lam_s, 0.0)
    with np.errstate(over="ignore", under="ignore"):
        lam = lam_s * scale * scale if scale > 0 else lam_s
    # a positive eigenvalue that underflows to 0 or overflows: null, not 0 or inf
    out_of_range = (lam_s > 0) & ((lam == 0) | ~np.isfinite(lam))
    lam = np.where(out_of_range, np.nan, lam)
    cond = float(lam_s[-1] / lam_s[0]) if lam_s[0] > 0 else float("inf")
    ex = Excitation(names=names, N0=N0, eigenvalues=lam, direction=V[:, 0], cond=cond)
    top = int(np.argmax(np.abs(V[:, 0])))
    sizes, balanced = _balanced(Zs)
    if ex.cond > WEAK_COND and balanced <= WEAK_COND:
        ex.notes.append(
            f"badly scaled: the regressors' sizes differ by a factor of {sizes:.3g}; each "
            f"scaled to one size, the data excite every direction (condition number "
            f"{balanced:.3g}), but the sound sets and certificates are computed in the units "
            f"given and are null or wide along {names[top]}: rescale the channels for them"
        )
    elif not lam_s[0] > NOT_EXCITED_RTOL * lam_s[-1]:
        ex.notes.append(
            f"the data do not excite every direction: lambda_min/lambda_max = "
            f"{lam_s[0] / lam_s[-1] if lam_s[-1] > 0 else 0.0:.3g} (mostly along {names[top]}); the estimate along it is set "
            "by the regulariser or undefined, and the OLS sound set is null"
        )
    elif ex.cond > WEAK_COND:
        ex.notes.append(
            f"weakly excited: condition number {ex.cond:.3g} (smallest direction mostly along "
            f"{names[top]}): wide intervals along it"
        )
    if N0 < Z.shape[0]:
        ex.notes.append(f"fewer samples ({N0}) than regressors ({Z.shape[0]})")
    if out_of_range.any():
        ex.notes.append(
            f"eigenvalues beyond the double range (null): the regressors' largest magnitude "
            f"is {scale:.3g}, and its square is not a double; the condition number and the "
            "least excited direction are those of the data scaled to 1: rescale the channels"
        )
    return ex


def _balanced(Zs: FloatArray) -> tuple[float, float]:
    """(largest / smallest nonzero regressor norm, condition number of the Gram with
    every regressor scaled to norm 1): whether an ill-conditioned Gram is only the
    channels' units (inf where a regressor is all zero)."""
    norms = np.sqrt(np.sum(Zs * Zs, axis=1))
    if not (norms.size and norms.min() > 0):
        return float("inf"), float("inf")
    Ze = Zs / norms[:, None]
    lam = np.maximum(np.linalg.eigvalsh(Ze @ Ze.T), 0.0)
    cond = float(lam[-1] / lam[0]) if lam[0] > 0 else float("inf")
    return float(norms.max() / norms.min()), cond


@dataclass
class ValidationResult:
    """Validation statistics of one model on held-out rollouts (per channel j,
    input l): see docs/measured.md#validation for every definition."""

    channels: tuple[str, ...]
    inputs: tuple[str, ...]
    lags: int  # h of the whiteness and cross-correlation tests
    one_step_nrmse: FloatArray  # (ny,)
    one_step_fit: FloatArray  # (ny,) percent
    simulation_fit: FloatArray  # (rollouts, ny) percent
    simulation_fit_pooled: FloatArray  # (ny,)
    autocorrelation: FloatArray  # (ny, h): r_1 .. r_h
    band: float  # 99 % band of r_k under whiteness
    ljung_box_Q: FloatArray  # (ny,)
    ljung_box_p: FloatArray  # (ny,)
    cross_correlation: FloatArray  # (ny, m, h + 1): rho_0 .. rho_h
    cross_S: FloatArray  # (ny, m)
    cross_p: FloatArray  # (ny, m)
    predicted: list[FloatArray]  # one-step predictions per rollout (T_i, ny)
    simulated: list[FloatArray]  # open-loop simulations per rollout (T_i + 1, ny)
    notes: list[str] = field(default_factory=list)

    def to_dict(self) -> dict[str, Any]:
        """JSON-able (NaN/inf -> None)."""
        out: dict[str, Any] = plain({k: getattr(self, k) for k in self.__dataclass_fields__})
        return out


def _fit(y: FloatArray, yhat: FloatArray) -> FloatArray:
    """100 (1 - ||y - yhat|| / ||y - mean y||) per column (MATLAB's compare)."""
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        return 100.0 * (1.0 - _nrmse(y, yhat))


def _nrmse(y: FloatArray, yhat: FloatArray) -> FloatArray:
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        out: FloatArray = np.linalg.norm(y - yhat, axis=0) / np.linalg.norm(
            y - y.mean(axis=0), axis=0
        )
        return out


def _lagged(a: list[FloatArray], b: list[FloatArray], k: int) -> FloatArray:
    """sum over rollouts and t of a_t b_{t-k} (rows of a, b per rollout), per column pair
    (zeros when no rollout is longer than k). -> (a columns, b columns)"""
    zero = np.zeros((a[0].shape[1], b[0].shape[1]))
    out: FloatArray = sum(
        (x[k:].T @ y[: y.shape[0] - k] for x, y in zip(a, b) if x.shape[0] > k), zero
    )
    return out


def _pairs(eps: list[FloatArray], lags: range) -> FloatArray:
    """P_k: the (residual, lagged) pairs inside the rollouts at each lag k. -> (len(lags),)"""
    T = np.array([e.shape[0] for e in eps])
    return np.array([np.maximum(T - k, 0).sum() for k in lags], dtype=float)


NO_PAIRS = (
    "{test}: no pairs inside a held-out rollout at lag 1 (every held-out rollout has one"
    " transition): {stat} and its p-value null"
)


def _simulate(model: Model, X: list[FloatArray], U: list[FloatArray], ny: int) -> list[FloatArray]:
    """Open-loop simulation of every rollout from its first state with its inputs
    (rollouts padded to the longest): ``x_{k+1} = A x_k + B u_k`` as a prefix scan
    (:func:`_affine_scan`), about 2 log2(T) array passes instead of T steps."""
    R, T = len(X), max(u.shape[0] for u in U)
    n, m = model.A.shape[0], model.B.shape[1]
    u = np.zeros((R, T, m))
    for i, ui in enumerate(U):
        u[i, : ui.shape[0]] = ui
    x = np.empty((R, T + 1, n))
    x[:, 0] = np.stack([xi[0] for xi in X])
    with np.errstate(over="ignore", invalid="ignore"):
        x[:, 1:] = u @ model.B.T
        _affine_scan(model.A, x)
    return [x[i, : X[i].shape[0], :ny] for i in range(R)]


def _affine_scan(A: FloatArray, x: FloatArray) -> None:
    """In place: ``x[:, k] <- A x[:, k-1] + x[:, k]`` for k = 1, 2, ... (x (R, T+1, n)).

    Hillis-Steele: after the pass of offset s, ``x[:, k]`` holds the sum over
    j < 2s of ``A^j`` times the k-j-th input; each pass reads the values before it.
    If a power ``A^s`` it needs overflows (an unstable model over a long rollout,
    where ``inf * 0`` would make NaN of a state the recursion keeps finite), the
    recursion runs step by step instead."""
    steps = x.shape[1]
    powers = [A]
    while 2 ** len(powers) < steps:
        powers.append(powers[-1] @ powers[-1])
    if not all(np.isfinite(P).all() for P in powers):
        for k in range(1, steps):
            x[:, k] += x[:, k - 1] @ A.T
        return
    for i, P in enumerate(powers):
        s = 2**i
        x[:, s:] += x[:, :-s] @ P.T


def _constant(s: FloatArray, names: Sequence[str], test: str, stat: str) -> list[str]:
    """A note per channel whose residual sum of squares ``s`` is 0 (a residual that
    does not vary has no correlation): its ``stat`` and p-value are null."""
    return [
        f"{test}: the residual of {names[i]} is constant: {stat} and its p-value null"
        for i in np.flatnonzero(~(s > 0)).tolist()
    ]


def _whiteness(
    eps: list[FloatArray], names: Sequence[str]
) -> tuple[int, FloatArray, FloatArray, int, list[str]]:
    """Ljung-Box per channel on residuals pooled within rollouts -> (h, r (ny, h), Q, n,
    notes); r_k and Q are NaN where lag k has no pairs inside a rollout, or the
    channel's residual is constant."""
    E = np.concatenate(eps)
    n_res = E.shape[0]
    h = min(MAX_LAGS, max(1, max(e.shape[0] for e in eps) // 4))
    mu = E.mean(axis=0)
    ec = [e - mu for e in eps]
    s0 = np.sum((E - mu) ** 2, axis=0)
    P = _pairs(eps, range(1, h + 1))
    none = P == 0
    with np.errstate(divide="ignore", invalid="ignore"):
        r = np.stack([np.diag(_lagged(ec, ec, k)) for k in range(1, h + 1)], axis=1) / s0[:, None]
        r[:, none] = np.nan
        Q = n_res * (n_res + 2) * np.sum(r * r / P, axis=1)
    if none.any():
        return h, r, Q, n_res, [NO_PAIRS.format(test="whiteness", stat="Q")]
    return h, r, Q, n_res, _constant(s0, names, "whiteness", "Q")


def _cross(
    eps: list[FloatArray],
    U: list[FloatArray],
    h: int,
    names: Sequence[str],
    channels: Sequence[str],
) -> tuple[FloatArray, FloatArray, list[str]]:
    """Residual-input cross-correlations rho (ny, m, h + 1) and the statistic
    S = s^T R_u^-1 s per (channel, input), s_k = n rho_k / sqrt(P_k) (P_k pairs at
    lag k inside the rollouts), R_u the input's autocorrelation Toeplitz matrix;
    -> (rho, S, notes); rho_k is NaN, and S null, where lag k has no pairs."""
    E, Uall = np.concatenate(eps), np.concatenate(U)
    ny, m = E.shape[1], Uall.shape[1]
    ec = [e - E.mean(axis=0) for e in eps]
    uc = [u - Uall.mean(axis=0) for u in U]
    s_e = np.sum(np.concatenate(ec) ** 2, axis=0)
    s_u = np.sum(np.concatenate(uc) ** 2, axis=0)
    rho = np.zeros((ny, m, h + 1))
    S = np.full((ny, m), np.nan)
    notes: list[str] = []
    if not m:
        return rho, S, notes
    with np.errstate(divide="ignore", invalid="ignore"):
        rho = np.stack([_lagged(ec, uc, k) for k in range(h + 1)], axis=-1)
        rho = rho / np.sqrt(s_e[:, None, None] * s_u[None, :, None])
        ru = np.stack([np.diag(_lagged(uc, uc, k)) for k in range(h + 1)], axis=1) / s_u[:, None]
    lag = np.abs(np.subtract.outer(np.arange(h + 1), np.arange(h + 1)))
    n_res = E.shape[0]
    pairs = _pairs(eps, range(h + 1))
    if (pairs == 0).any():
        rho[..., pairs == 0] = np.nan
        return rho, S, [NO_PAIRS.format(test="cross-correlation", stat="S")]
    std = rho * (n_res / np.sqrt(pairs))  # Var ~ 1 per lag for a white input (P_k pairs)
    for j in range(m):  # one (h + 1) x (h + 1) solve per input
        Ru = ru[j][lag]
        if np.isfinite(Ru).all() and np.linalg.cond(Ru) < 1e12:
            S[:, j] = np.sum(std[:, j] * np.linalg.solve(Ru, std[:, j].T).T, axis=1)
        else:
            notes.append(f"cross-correlation: input {names[j]} is not excited (null)")
    return rho, S, notes + _constant(s_e, channels, "cross-correlation", "S")


def validate(model: Model, holdout: MeasuredData) -> ValidationResult:
    """The validation statistics of ``model`` on the rollouts ``holdout``."""
    from scipy.stats import chi2  # lazily: scipy.stats takes 1.5 s to import

    data = StateModel(ny=holdout.n, m=holdout.m, lags=model.lags).lift(holdout)
    ny = holdout.n
    predicted = [(x[:-1] @ model.A.T + u @ model.B.T)[:, :ny] for x, u in zip(data.X, data.U)]
    eps = [x[1:, :ny] - p for x, p in zip(data.X, predicted)]
    Y = np.concatenate([x[1:, :ny] for x in data.X])
    one_step = _nrmse(Y, np.concatenate(predicted))
    simulated = _simulate(model, data.X, data.U, ny)
    sim_fit = np.stack([_fit(x[1:, :ny], s[1:]) for x, s in zip(data.X, simulated)])
    notes: list[str] = []
    if not np.isfinite(one_step).all():
        notes.append("one-step prediction: left the double range or a constant channel (null)")
    if not np.isfinite(sim_fit).all():
        notes.append("open-loop simulation: left the double range or a constant channel (null)")
    channels = holdout.state_names
    h, r, Q, n_res, white_notes = _whiteness(eps, channels)
    rho, S, cross_notes = _cross(eps, data.U, h, data.input_names, channels)
    return ValidationResult(
        channels=tuple(holdout.state_names),
        inputs=tuple(holdout.input_names),
        lags=h,
        one_step_nrmse=one_step,
        one_step_fit=100.0 * (1.0 - one_step),
        simulation_fit=sim_fit,
        simulation_fit_pooled=_fit(Y, np.concatenate([s[1:] for s in simulated])),
        autocorrelation=r,
        band=BAND_Z / np.sqrt(n_res),
        ljung_box_Q=Q,
        ljung_box_p=chi2.sf(Q, h),
        cross_correlation=rho,
        cross_S=S,
        cross_p=chi2.sf(S, h + 1),
        predicted=predicted,
        simulated=simulated,
        notes=notes + white_notes + cross_notes,
    )


def fit_model(
    spec: ExperimentSpec,
    data: MeasuredData,
    *,
    estimator: str,
    gamma: float | None = None,
    N: int | None = None,
) -> Model:
    """The model of one (estimator, gamma) of a dataset spec, fitted on the first N
    rollouts of the training pool (default: the spec's largest N), as its cells' rep 0."""
    opts = spec.measured
    train, _ = data.split(opts.holdout)
    N = max(spec.N) if N is None else N
    sm = StateModel(ny=data.n, m=data.m, lags=opts.lags)
    Z, F = regression(sm.lift(train.take(range(N))))
    F = F[sm.estimated]
    if estimator == "ols":
        rows = _est.fit_ols(Z, F)
    elif estimator == "svr":  # svr and shrunk-ols: the axis gives them a gamma
        rows = _est.fit_svr(Z, F, [cast(float, gamma)], loss_scale=spec.loss_scale)[0]
    elif estimator == "shrunk-ols":
        rows = _est.shrunk_ols(_est.fit_ols(Z, F), [cast(float, gamma)])[0]
    else:
        raise ValueError(f"unknown estimator {estimator!r}")
    theta = sm.full(rows)
    n = sm.n
    return Model(A=theta[:, :n], B=theta[:, n:], lags=opts.lags, estimator=estimator, gamma=gamma)


def validation_summary(
    spec: ExperimentSpec,
    data: MeasuredData,
    *,
    series_rollouts: int | None = None,
    series_steps: int | None = None,
) -> dict[str, Any]:
    """JSON for a dataset job: the excitation of the training rollouts used at the
    largest N, and each (estimator, gamma)'s model and its validation on the
    held-out rollouts (None without held-out rollouts). The per-step series
    (``predicted``, ``simulated``) are kept for the first ``series_rollouts``
    held-out rollouts and their first ``series_steps`` steps (all when None); the
    statistics are over every held-out step."""
    from ..planning import estimator_axis

    def cut(v: ValidationResult) -> ValidationResult:
        r, t = series_rollouts, series_steps
        return replace(
            v,
            predicted=[p[:t] for p in v.predicted[:r]],
            simulated=[x[: None if t is None else t + 1] for x in v.simulated[:r]],
        )

    opts = spec.measured
    train, held = data.split(opts.holdout)
    N = max(spec.N)
    axis = estimator_axis(spec)
    models: list[dict[str, Any]] = []
    for name, gamma in zip(axis.names, axis.gammas):
        model = fit_model(spec, data, estimator=name, gamma=gamma, N=N)
        models.append(
            {
                "estimator": name,
                "gamma": gamma,
                "A_hat": plain(model.A),
                "B_hat": plain(model.B),
                "validation": None if held is None else cut(validate(model, held)).to_dict(),
            }
        )
    return {
        "N": N,
        "holdout": opts.holdout,
        "excitation": excitation(train.take(range(N)), opts.lags).to_dict(),
        "models": models,
        "notes": [] if held is not None else ["no held-out rollouts (holdout = 0)"],
    }
