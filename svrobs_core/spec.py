"""The experiment spec (docs/spec.md#spec-fields): parse, validate, normalise.

``parse_spec(dict) -> ExperimentSpec`` is the one entry point used by the
CLI, the REST API and the scheduler; every error is a :class:`SpecError`
naming the field.
"""

from __future__ import annotations

import json
import math
from collections.abc import Iterable
from dataclasses import MISSING, dataclass, field, fields
from typing import Any, cast

from .errors import SpecError, unknown_field
from .seeding import DEFAULT_RNG, RNGS
from .system_batch import resolve_systems
from .systems import MAX_DIM, SystemSpec
from .wishart_draws import DEFAULT_DRAWS, DRAWS

ESTIMATORS = ("ols", "svr", "shrunk-ols")
BOUNDS_METHODS = ("paper", "self-normalized", "bootstrap")
BOOT_SIGMA_SOURCES = ("estimate", "spec")
# Options of each non-paper bounds method (docs/uncertainty.md), with their defaults.
BOUNDS_OPTIONS: dict[str, dict[str, Any]] = {
    "self-normalized": {"S": None, "lambda0": 1.0},
    "bootstrap": {"boot_reps": 100, "boot_sigma_w": "estimate"},
}
STAGES = ("estimate", "bounds", "gain", "cost", "cost_bound", "sls")
# A stage needs the ones before it in this order (cost_bound needs cost's J).
STAGE_NEEDS = {
    "estimate": (),
    "bounds": ("estimate",),
    "gain": ("estimate", "bounds"),
    "cost": ("estimate", "bounds", "gain"),
    "cost_bound": ("estimate", "bounds", "gain", "cost"),
    "sls": ("estimate", "bounds"),
}

SPEC_KEYS = {
    "systems",
    "sigma_w",
    "N",
    "T0",
    "gamma",
    "estimators",
    "loss_scale",
    "data",
    "reps",
    "M",
    "delta",
    "stages",
    "mc_runs",
    "horizon",
    "mc_reps",
    "margin",
    "reuse_gain",
    "gamma_ref",
    "sls",
    "seed",
    "x0_std",
    "bounds_method",
    "S",
    "lambda0",
    "boot_reps",
    "boot_sigma_w",
    "rng",
    "draws",
}
# The fields of a job on measured data that a simulated job does not have
# (docs/measured.md#spec).
DATASET_KEYS = {"dataset", "holdout", "C", "sigma_v", "sigma_u", "state"}
DATASET_ONLY_MESSAGE = 'is only used with "dataset" (a job on measured data)'
MAX_GRID = 100_000  # any single list longer than this is surely a mistake
# Hard caps on the sizes one cell may ask for: beyond them a single
# cell needs more memory or time than any worker has; the cost model
# (svrobs_core.workload) limits the whole job below them.
MAX_STATE_DIM = MAX_DIM  # n, m, p: the Kalman step solves an (n^2 x n^2) system per cell
MAX_ROLLOUTS = 1_000_000  # N
MAX_SAMPLES = 10_000_000  # T0 * N: the samples of one repetition's data
MAX_MC_STEPS = 100_000_000  # horizon * mc_runs: the Monte Carlo steps of one cell
MAX_T_FIR = 1000  # sls.T_fir
MAX_T0 = 10_000
MAX_REPS = 1_000_000


@dataclass(frozen=True, kw_only=True)
class ExperimentSpec:
    """A validated spec (docs/spec.md#spec-fields). ``to_dict()`` gives the normalised JSON."""

    systems: tuple[SystemSpec, ...]
    sigma_w: tuple[float, ...]
    N: tuple[int, ...]
    T0: int = 11
    gamma: tuple[float, ...] = (0.05,)
    estimators: tuple[str, ...] = ("ols", "svr")
    loss_scale: str = "sum"
    data: str = "all"
    reps: int = 45
    M: float = 1.1
    delta: float = 0.01
    stages: tuple[str, ...] = ("estimate", "bounds")
    mc_runs: int = 1000
    horizon: int = 200
    mc_reps: int | None = None
    margin: float = 0.01
    reuse_gain: bool = False
    gamma_ref: float = 0.1
    sls_T_fir: int = 30
    sls_C_bound: float | None = None
    seed: int = 0
    x0_std: float = 0.0
    bounds_method: str = "paper"
    # self-normalized: bound on ||theta_i|| (None: sqrt(2) M), and V0 = lambda0 I of OLS
    S: float | None = BOUNDS_OPTIONS["self-normalized"]["S"]
    lambda0: float = BOUNDS_OPTIONS["self-normalized"]["lambda0"]
    boot_reps: int = BOUNDS_OPTIONS["bootstrap"]["boot_reps"]
    # bootstrap noise level: the residuals' estimate or the spec's
    boot_sigma_w: str = BOUNDS_OPTIONS["bootstrap"]["boot_sigma_w"]
    rng: str = DEFAULT_RNG  # bit generator of every draw (docs/performance.md#generators)
    # a dataset's N rollouts, or their noise's Wishart scatter (docs/science.md#15-wishart-draws)
    draws: str = DEFAULT_DRAWS
    raw_systems: tuple[Any, ...] = field(default=(), compare=False)
    # A job on measured data: its options (svrobs_core.measured.spec.DatasetOptions);
    # then systems and sigma_w are empty (docs/measured.md#spec).
    measured: Any = None

    @property
    def dataset(self) -> int | None:
        """The dataset id of a job on measured data, else None."""
        return None if self.measured is None else self.measured.dataset

    def has(self, stage: str) -> bool:
        return stage in self.stages

    @property
    def cells_per_rep(self) -> int:
        """Records per (system, sigma_w, N, rep): one per (estimator, gamma)."""
        return sum(1 if e == "ols" else len(self.gamma) for e in self.estimators)

    @property
    def grid_systems(self) -> tuple[str, ...]:
        """The records' ``system`` keys: the systems' names, or a dataset job's one
        (``dataset-ID``)."""
        if self.measured is not None:
            return (self.measured.system_name,)
        return tuple(s.name for s in self.systems)

    @property
    def grid_sigma_w(self) -> tuple[float, ...]:
        """The records' ``sigma_w`` keys: the spec's levels, or a dataset job's one
        (its given level, or -1 for "estimate": docs/measured.md#records)."""
        if self.measured is not None:
            return (self.measured.record_sigma_w,)
        return tuple(self.sigma_w)

    @property
    def n_cells(self) -> int:
        pairs = len(self.grid_systems) * len(self.grid_sigma_w)
        return pairs * len(self.N) * self.reps * self.cells_per_rep

    def to_dict(self) -> dict[str, Any]:
        if self.measured is not None:
            out: dict[str, Any] = self.measured.spec_dict(self)
            return out
        return {
            "systems": [s if isinstance(s, str) else s for s in self.raw_systems],
            "sigma_w": list(self.sigma_w),
            "N": list(self.N),
            "T0": self.T0,
            "gamma": list(self.gamma),
            "estimators": list(self.estimators),
            "loss_scale": self.loss_scale,
            "data": self.data,
            "reps": self.reps,
            "M": self.M,
            "delta": self.delta,
            "stages": list(self.stages),
            "mc_runs": self.mc_runs,
            "horizon": self.horizon,
            "mc_reps": self.mc_reps,
            "margin": self.margin,
            "reuse_gain": self.reuse_gain,
            "gamma_ref": self.gamma_ref,
            "sls": {"T_fir": self.sls_T_fir, "C_bound": self.sls_C_bound},
            "seed": self.seed,
            "x0_std": self.x0_std,
            **self._bounds_dict(),
            # only a non-default generator: the normalised JSON of older specs is unchanged
            **({} if self.rng == DEFAULT_RNG else {"rng": self.rng}),
            **({} if self.draws == DEFAULT_DRAWS else {"draws": self.draws}),
        }

    def _bounds_dict(self) -> dict[str, Any]:
        """The bounds options, only for a non-paper method (so that the normalised
        JSON of every spec written before ``bounds_method`` existed is unchanged)."""
        if self.bounds_method == "paper":
            return {}
        opts = BOUNDS_OPTIONS[self.bounds_method]
        return {"bounds_method": self.bounds_method, **{k: getattr(self, k) for k in opts}}

    @property
    def S_bound(self) -> float:
        """S of the self-normalized method: the spec's, else sqrt(2) M
        (docs/uncertainty.md#b-the-self-normalized-confidence-ellipsoid)."""
        return math.sqrt(2.0) * self.M if self.S is None else self.S


# The default of every spec key, written once (the fields of ExperimentSpec above, the
# bounds options in BOUNDS_OPTIONS); a tuple as the list a JSON spec gives.
DEFAULTS: dict[str, Any] = {
    f.name: list(f.default) if isinstance(f.default, tuple) else f.default
    for f in fields(ExperimentSpec)
    if f.default is not MISSING
}


def _int(value: object, name: str, *, lo: int, hi: int | None = None) -> int:
    """A JSON integer: booleans, floats (3.0 too) and strings are refused."""
    if isinstance(value, bool) or not isinstance(value, int):
        raise SpecError(name, f"must be an integer, got {json.dumps(value, default=str)}")
    if value < lo:
        raise SpecError(name, f"must be >= {lo}")
    if hi is not None and value > hi:
        raise SpecError(name, f"must be <= {hi}")
    return value


def _float(value: object, name: str, *, positive: bool = False, nonneg: bool = False) -> float:
    """A JSON number: booleans and numeric strings ("0.5") are refused."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise SpecError(name, f"must be a number, got {json.dumps(value, default=str)}")
    try:
        v = float(value)
    except OverflowError:  # an integer beyond the double range
        v = math.inf
    if not math.isfinite(v):
        raise SpecError(name, "must be finite (no NaN or inf)")
    if positive and v <= 0:
        raise SpecError(name, "must be > 0")
    if nonneg and v < 0:
        raise SpecError(name, "must be >= 0")
    return v


def _list(value: object, name: str) -> list[Any]:
    if not isinstance(value, list) or not value:
        raise SpecError(name, "must be a non-empty list")
    if len(value) > MAX_GRID:
        raise SpecError(name, f"has more than {MAX_GRID} entries")
    return value


def _choice(value: Any, name: str, options: Iterable[str]) -> str:
    if value not in options:
        raise SpecError(name, f"must be one of {list(options)}, got {value!r}")
    return cast(str, value)


def _n_grid(value: object) -> tuple[int, ...]:
    if isinstance(value, dict):
        unknown = set(value) - {"start", "stop", "step"}
        if unknown:
            raise SpecError(f"N.{sorted(unknown)[0]}", "unknown field")
        for key in ("start", "stop"):
            if key not in value:
                raise SpecError(f"N.{key}", "is required")
        start = _int(value["start"], "N.start", lo=1, hi=MAX_ROLLOUTS)
        stop = _int(value["stop"], "N.stop", lo=start, hi=MAX_ROLLOUTS)
        step = _int(value.get("step", 1), "N.step", lo=1)
        if (stop - start) // step + 1 > MAX_GRID:
            raise SpecError("N", f"has more than {MAX_GRID} entries")
        return tuple(range(start, stop + 1, step))
    items = _list(value, "N")
    out = tuple(_int(v, f"N[{i}]", lo=1, hi=MAX_ROLLOUTS) for i, v in enumerate(items))
    return _unique(out, "N")


def _object(value: object, name: str, keys: tuple[str, ...]) -> dict[str, Any]:
    """A JSON object whose fields are among ``keys`` (an unknown one is named)."""
    if not isinstance(value, dict):
        raise SpecError(name, f"must be an object {{{', '.join(keys)}}}")
    unknown = set(value) - set(keys)
    if unknown:
        raise SpecError(f"{name}.{sorted(unknown)[0]}", "unknown field")
    return value


def _unique(values: tuple[Any, ...], name: str) -> tuple[Any, ...]:
    if len(set(values)) != len(values):
        raise SpecError(name, "has duplicate entries")
    return values


def parse_simulation_spec(obj: dict[str, Any]) -> ExperimentSpec:
    """Validate a spec of a simulated job (a dict from JSON) and fill the defaults.

    :func:`svrobs_core.parsing.parse_spec` takes either kind of job."""
    if not isinstance(obj, dict):
        raise SpecError("spec", "must be a JSON object")
    unknown = set(obj) - SPEC_KEYS
    if unknown:
        key = sorted(unknown)[0]
        message = unknown_field(key, SPEC_KEYS | DATASET_KEYS)
        raise SpecError(key, DATASET_ONLY_MESSAGE if key in DATASET_KEYS else message)
    for key in ("systems", "sigma_w", "N"):
        if key not in obj:
            raise SpecError(key, "is required")

    raw_systems = _list(obj["systems"], "systems")
    systems = resolve_systems(raw_systems, "systems")  # as resolve_system each, in order
    _unique(tuple(s.name for s in systems), "systems")
    sigma_w = tuple(
        _float(v, f"sigma_w[{i}]", nonneg=True)
        for i, v in enumerate(_list(obj["sigma_w"], "sigma_w"))
    )
    _unique(sigma_w, "sigma_w")
    N = _n_grid(obj["N"])
    T0 = _int(obj.get("T0", DEFAULTS["T0"]), "T0", lo=2, hi=MAX_T0)
    if T0 * max(N) > MAX_SAMPLES:
        i = "N" if isinstance(obj["N"], dict) else f"N[{list(obj['N']).index(max(N))}]"
        raise SpecError(i, f"T0 * N = {T0 * max(N)} samples per repetition is over {MAX_SAMPLES}")

    shared = shared_options(obj)
    mc_reps = obj.get("mc_reps")
    reuse = obj.get("reuse_gain", DEFAULTS["reuse_gain"])
    if not isinstance(reuse, bool):
        raise SpecError("reuse_gain", "must be true or false")
    mc_runs = _int(obj.get("mc_runs", DEFAULTS["mc_runs"]), "mc_runs", lo=2, hi=1_000_000)
    if "cost" in shared["stages"] and mc_runs * shared["horizon"] > MAX_MC_STEPS:
        raise SpecError(
            "mc_runs",
            f"mc_runs * horizon = {mc_runs * shared['horizon']} is over {MAX_MC_STEPS} per cell",
        )
    bounds = _bounds_options(obj)

    return ExperimentSpec(
        systems=systems,
        sigma_w=sigma_w,
        N=N,
        T0=T0,
        data=_choice(obj.get("data", DEFAULTS["data"]), "data", ("all", "final")),
        mc_runs=mc_runs,
        mc_reps=None if mc_reps is None else _int(mc_reps, "mc_reps", lo=0, hi=MAX_REPS),
        reuse_gain=reuse,
        x0_std=_float(obj.get("x0_std", DEFAULTS["x0_std"]), "x0_std", nonneg=True),
        **shared,
        **bounds,
        rng=_choice(obj.get("rng", DEFAULTS["rng"]), "rng", tuple(RNGS)),
        draws=_choice(obj.get("draws", DEFAULTS["draws"]), "draws", DRAWS),
        raw_systems=tuple(raw_systems),
    )


def shared_options(obj: dict[str, Any]) -> dict[str, Any]:
    """The options a simulated and a dataset job share (estimators, gamma, stages,
    sls, delta, margin, seed, horizon, loss_scale, reps, M, gamma_ref), checked
    and with their defaults: ExperimentSpec keyword arguments."""
    estimators = tuple(
        _choice(e, f"estimators[{i}]", ESTIMATORS)
        for i, e in enumerate(_list(obj.get("estimators", DEFAULTS["estimators"]), "estimators"))
    )
    _unique(estimators, "estimators")
    gamma = tuple(
        _float(g, f"gamma[{i}]", positive=True)
        for i, g in enumerate(_list(obj.get("gamma", DEFAULTS["gamma"]), "gamma"))
    )
    _unique(gamma, "gamma")

    stages = tuple(
        _choice(s, f"stages[{i}]", STAGES)
        for i, s in enumerate(_list(obj.get("stages", DEFAULTS["stages"]), "stages"))
    )
    _unique(stages, "stages")
    for s in stages:
        for need in STAGE_NEEDS[s]:
            if need not in stages:
                raise SpecError("stages", f"stage {s!r} needs stage {need!r}")
    stages = tuple(s for s in STAGES if s in stages)

    sls = _object(obj.get("sls") or {}, "sls", ("T_fir", "C_bound"))
    c_bound = sls.get("C_bound")

    delta = _float(obj.get("delta", DEFAULTS["delta"]), "delta", positive=True)
    if delta >= 1:
        raise SpecError("delta", "must be < 1")
    margin = _float(obj.get("margin", DEFAULTS["margin"]), "margin", nonneg=True)
    if margin >= 1:
        raise SpecError("margin", "must be < 1")
    return {
        "estimators": estimators,
        "gamma": gamma,
        "stages": stages,
        "delta": delta,
        "margin": margin,
        "seed": _int(obj.get("seed", DEFAULTS["seed"]), "seed", lo=0, hi=2**63 - 1),
        "horizon": _int(obj.get("horizon", DEFAULTS["horizon"]), "horizon", lo=1, hi=100_000),
        "loss_scale": _choice(
            obj.get("loss_scale", DEFAULTS["loss_scale"]), "loss_scale", ("sum", "mean")
        ),
        "reps": _int(obj.get("reps", DEFAULTS["reps"]), "reps", lo=1, hi=MAX_REPS),
        "M": _float(obj.get("M", DEFAULTS["M"]), "M", positive=True),
        "gamma_ref": _float(
            obj.get("gamma_ref", DEFAULTS["gamma_ref"]), "gamma_ref", positive=True
        ),
        "sls_T_fir": _int(sls.get("T_fir", DEFAULTS["sls_T_fir"]), "sls.T_fir", lo=2, hi=MAX_T_FIR),
        "sls_C_bound": None if c_bound is None else _float(c_bound, "sls.C_bound", positive=True),
    }


def _bounds_options(obj: dict[str, Any]) -> dict[str, Any]:
    """bounds_method and the options of that method (docs/uncertainty.md); an option
    of another method is an error naming it."""
    method = _choice(
        obj.get("bounds_method", DEFAULTS["bounds_method"]), "bounds_method", BOUNDS_METHODS
    )
    own = BOUNDS_OPTIONS.get(method, {})
    for opts in BOUNDS_OPTIONS.values():
        for key in opts:
            if key in obj and key not in own:
                users = [m for m, o in BOUNDS_OPTIONS.items() if key in o]
                raise SpecError(key, f"is only used with bounds_method {users[0]!r}")
    out: dict[str, Any] = {"bounds_method": method}
    if method == "self-normalized":
        S = obj.get("S")
        out["S"] = None if S is None else _float(S, "S", positive=True)
        out["lambda0"] = _float(obj.get("lambda0", DEFAULTS["lambda0"]), "lambda0", positive=True)
    elif method == "bootstrap":
        out["boot_reps"] = _int(
            obj.get("boot_reps", DEFAULTS["boot_reps"]), "boot_reps", lo=2, hi=100_000
        )
        out["boot_sigma_w"] = _choice(
            obj.get("boot_sigma_w", DEFAULTS["boot_sigma_w"]), "boot_sigma_w", BOOT_SIGMA_SOURCES
        )
    return out
