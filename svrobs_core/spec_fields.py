"""The spec's fields as a table (what a form shows: kind, one-line help, unit, bounds,
default), and every error of a spec at once.

:data:`SPEC_FIELDS` declares each key of :func:`svrobs_core.parsing.parse_spec`; the
defaults are :data:`svrobs_core.spec.DEFAULTS` (those of ExperimentSpec and
``BOUNDS_OPTIONS``, written once, there, and read by the parser), and the bounds are those the parser
enforces (``tests/core/test_spec_fields.py`` probes the parser at each bound).
:func:`spec_errors` collects the errors of every field: the parser stops at the
first, so each field is checked alone on a spec that is otherwise valid, and the
whole spec is checked last for the rules between fields (T0·N, the stages' needs,
mc_runs·horizon, options of another bounds method). See docs/spec.md#spec-fields.
:data:`DATASET_FIELDS` declares the keys only a job on measured data has, and
:func:`for_datasets` says which fields such a job takes (docs/measured.md#spec).
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from typing import Any

from .errors import SpecError, unknown_field
from .measured.spec import BOUNDS_METHOD as DATASET_BOUNDS_METHOD
from .measured.spec import SPEC_FIELDS as DATASET_SPEC_KEYS
from .measured.spec import DatasetOptions
from .parsing import parse_spec
from .seeding import RNGS
from .spec import (
    BOOT_SIGMA_SOURCES,
    BOUNDS_METHODS,
    BOUNDS_OPTIONS,
    DATASET_KEYS,
    DATASET_ONLY_MESSAGE,
    DEFAULTS,
    ESTIMATORS,
    MAX_REPS,
    MAX_ROLLOUTS,
    MAX_T0,
    MAX_T_FIR,
    SPEC_KEYS,
    STAGES,
)
from .systems import PRESETS
from .wishart_draws import DRAWS

REQUIRED = object()  # the default of a field the spec must give


@dataclass(frozen=True)
class SpecField:
    """One spec key. ``kind``: ``systems``, ``numbers`` (a list of numbers), ``grid``
    (N: a list of integers or start/stop/step), ``int``, ``number``, ``choice``,
    ``choices`` (a subset, in order), ``bool``; ``optional``: null (empty) allowed.
    ``lo``/``hi`` bound the value (``lo_open``: > instead of ≥, ``hi_open``: <);
    ``only_with``: the bounds_method the option belongs to. A field of
    :data:`DATASET_FIELDS` has ``dataset_only`` (kinds ``dataset``: a dataset's id,
    ``level``: a number or ``"estimate"``, ``json``: a JSON value) and ``key``, the
    name a form gives it where it differs from the spec key's (σ_w is a list in a
    simulated job, one level in a dataset job)."""

    name: str
    kind: str
    help: str
    unit: str = ""
    lo: float | None = None
    hi: float | None = None
    lo_open: bool = False
    hi_open: bool = False
    choices: tuple[Any, ...] = ()
    optional: bool = False
    only_with: str | None = None
    group: str = "grid"
    dataset_only: bool = False
    key: str = ""

    @property
    def form_key(self) -> str:
        """The field's name in a form (the spec key unless ``key`` says otherwise)."""
        return self.key or self.name

    @property
    def default(self) -> Any:
        """The parser's default (lists as lists), or REQUIRED."""
        if self.dataset_only:
            return _DATASET_DEFAULTS[self.name]
        if self.name in ("systems", "sigma_w", "N"):
            return REQUIRED
        if self.only_with:
            return BOUNDS_OPTIONS[self.only_with][self.name]
        attr = {"sls.T_fir": "sls_T_fir", "sls.C_bound": "sls_C_bound"}.get(self.name, self.name)
        value = DEFAULTS[attr]
        return list(value) if isinstance(value, tuple) else value

    def bounds_text(self) -> str:
        """The bounds in words: ``1 … 1000000``, ``> 0``, ``0 ≤ x < 1``."""
        if self.lo is None and self.hi is None:
            return ""
        lo = "" if self.lo is None else f"{_num(self.lo)} {'<' if self.lo_open else '≤'} "
        hi = "" if self.hi is None else f" {'<' if self.hi_open else '≤'} {_num(self.hi)}"
        if self.lo is not None and self.hi is None:
            return f"{'>' if self.lo_open else '≥'} {_num(self.lo)}"
        assert self.hi is not None  # both bounds None returned above
        if self.lo is None:
            return f"{'<' if self.hi_open else '≤'} {_num(self.hi)}"
        if self.kind in ("int", "grid") and not (self.lo_open or self.hi_open):
            return f"{_num(self.lo)} … {_num(self.hi)}"
        return f"{lo}x{hi}"


def _num(v: float) -> str:
    return f"{int(v):,}" if float(v).is_integer() else f"{v:g}"


SPEC_FIELDS: tuple[SpecField, ...] = (
    SpecField(
        "systems",
        "systems",
        "Systems to identify: presets, or system objects (JSON view)",
        choices=tuple(sorted(PRESETS)),
    ),
    SpecField(
        "sigma_w",
        "numbers",
        "Process-noise standard deviations σ_w (a grid axis)",
        "state units",
        lo=0,
    ),
    SpecField(
        "N", "grid", "Numbers of rollouts N (a grid axis)", "rollouts", lo=1, hi=MAX_ROLLOUTS
    ),
    SpecField(
        "gamma",
        "numbers",
        "Regularisation values γ of svr and shrunk-ols (a grid axis)",
        "dimensionless",
        lo=0,
        lo_open=True,
    ),
    SpecField("estimators", "choices", "Estimators to run", choices=ESTIMATORS, group="estimate"),
    SpecField(
        "reps",
        "int",
        "Repetitions per grid point",
        "repetitions",
        lo=1,
        hi=MAX_REPS,
        group="estimate",
    ),
    SpecField(
        "T0",
        "int",
        "Rollout length T0 (T0 · max N ≤ 10,000,000)",
        "steps",
        lo=2,
        hi=MAX_T0,
        group="estimate",
    ),
    SpecField(
        "data",
        "choice",
        "all: N0 = (T0 − 1)·N regression samples; final: N0 = N",
        choices=("all", "final"),
        group="estimate",
    ),
    SpecField(
        "loss_scale",
        "choice",
        "sum: the ridge parameter is γ; mean: it is γ·N0",
        choices=("sum", "mean"),
        group="estimate",
    ),
    SpecField(
        "x0_std",
        "number",
        "Standard deviation of the initial state (0: x0 = 0)",
        "state units",
        lo=0,
        group="estimate",
    ),
    SpecField("seed", "int", "Seed of every random stream", lo=0, hi=2**63 - 1, group="estimate"),
    SpecField(
        "rng", "choice", "Bit generator of every random draw", choices=tuple(RNGS), group="estimate"
    ),
    SpecField(
        "draws",
        "choice",
        "A dataset's noise: its N rollouts, or their Wishart scatter matrix at once",
        choices=DRAWS,
        group="estimate",
    ),
    SpecField(
        "stages",
        "choices",
        "Stages to run (each needs the ones before it)",
        choices=STAGES,
        group="stages",
    ),
    SpecField(
        "bounds_method",
        "choice",
        "How the uncertainty radii are computed",
        choices=BOUNDS_METHODS,
        group="bounds",
    ),
    SpecField(
        "M", "number", "Assumption 1's bound M", "dimensionless", lo=0, lo_open=True, group="bounds"
    ),
    SpecField(
        "delta",
        "number",
        "The bounds hold with probability 1 − δ",
        lo=0,
        hi=1,
        lo_open=True,
        hi_open=True,
        group="bounds",
    ),
    SpecField(
        "S",
        "number",
        "Bound on ‖θ_i‖ (empty: √2·M)",
        lo=0,
        lo_open=True,
        optional=True,
        only_with="self-normalized",
        group="bounds",
    ),
    SpecField(
        "lambda0",
        "number",
        "Prior of OLS: V0 = λ0·I",
        lo=0,
        lo_open=True,
        only_with="self-normalized",
        group="bounds",
    ),
    SpecField(
        "boot_reps",
        "int",
        "Resampled datasets per cell",
        "datasets",
        lo=2,
        hi=100_000,
        only_with="bootstrap",
        group="bounds",
    ),
    SpecField(
        "boot_sigma_w",
        "choice",
        "Noise of the resamples: the residuals' or the cell's",
        choices=BOOT_SIGMA_SOURCES,
        only_with="bootstrap",
        group="bounds",
    ),
    SpecField(
        "margin",
        "number",
        "Design margin of the gain: g(L) ≤ 1 − margin",
        lo=0,
        hi=1,
        hi_open=True,
        group="gain",
    ),
    SpecField(
        "reuse_gain", "bool", "Keep the previous N's gain while it is certified", group="gain"
    ),
    SpecField(
        "mc_runs",
        "int",
        "Monte Carlo runs per cell (mc_runs · horizon ≤ 10⁸)",
        "runs",
        lo=2,
        hi=1_000_000,
        group="cost",
    ),
    SpecField(
        "horizon",
        "int",
        "Horizon T of the exact and Monte Carlo cost",
        "steps",
        lo=1,
        hi=100_000,
        group="cost",
    ),
    SpecField(
        "mc_reps",
        "int",
        "Monte Carlo cost only for rep < mc_reps (empty: every rep)",
        "repetitions",
        lo=0,
        hi=MAX_REPS,
        optional=True,
        group="cost",
    ),
    SpecField(
        "gamma_ref",
        "number",
        "Reference γ of the cost ratio",
        "dimensionless",
        lo=0,
        lo_open=True,
        group="cost",
    ),
    SpecField(
        "sls.T_fir",
        "int",
        "FIR length of the SLS program",
        "steps",
        lo=2,
        hi=MAX_T_FIR,
        group="sls",
    ),
    SpecField(
        "sls.C_bound",
        "number",
        "Bound on ‖Φ_w‖_H2 (empty: from the true system)",
        lo=0,
        lo_open=True,
        optional=True,
        group="sls",
    ),
)
FIELDS_BY_NAME = {f.name: f for f in SPEC_FIELDS}
_DATASET_DEFAULTS = {
    "dataset": REQUIRED,
    "sigma_w": "estimate",
    **{f.name: f.default for f in fields(DatasetOptions) if f.name not in ("dataset", "sigma_w")},
}
_DATASET_DEFAULTS["state"] = _DATASET_DEFAULTS.pop("lags")
# the keys of a job on measured data that a simulated job does not have, or has
# otherwise (sigma_w: one level, not a grid axis); docs/measured.md#spec
DATASET_FIELDS: tuple[SpecField, ...] = (
    SpecField(
        "dataset",
        "dataset",
        "The team's dataset the job runs on (its rollouts instead of simulated systems)",
        dataset_only=True,
    ),
    SpecField(
        "sigma_w",
        "level",
        "Process-noise σ_w: a level you vouch for, or estimate (an upper confidence bound "
        "from the data)",
        "state units",
        lo=0,
        dataset_only=True,
        key="dataset_sigma_w",
    ),
    SpecField(
        "holdout",
        "int",
        "Rollouts set aside for validation (the dataset's last ones)",
        "rollouts",
        lo=0,
        hi=2**31 - 1,
        dataset_only=True,
    ),
    SpecField(
        "state",
        "json",
        'Input-output data: the ARX state {"lags": {"y": p, "u": q}} (empty: the measured state)',
        optional=True,
        group="estimate",
        dataset_only=True,
    ),
    SpecField(
        "C",
        "json",
        "Output matrix of the observer model, p × n, as JSON (empty: I, or the rows that "
        "pick y_k of the ARX state)",
        optional=True,
        group="gain",
        dataset_only=True,
    ),
    SpecField(
        "sigma_v",
        "number",
        "Measurement-noise standard deviation of the observer model",
        lo=0,
        group="gain",
        dataset_only=True,
    ),
    SpecField(
        "sigma_u",
        "number",
        "Input standard deviation of the cost model (empty: the RMS of the training inputs)",
        lo=0,
        lo_open=True,
        optional=True,
        group="cost",
        dataset_only=True,
    ),
)


def for_datasets(f: SpecField) -> bool:
    """Whether a job on measured data takes the field (its bounds method is always
    DATASET_BOUNDS_METHOD, so only that method's options)."""
    if f.dataset_only:
        return True
    if f.name == "sigma_w" or f.name.split(".", 1)[0] not in DATASET_SPEC_KEYS:
        return False
    return f.only_with in (None, DATASET_BOUNDS_METHOD)


REQUIRED_KEYS = ("systems", "sigma_w", "N")
_OPTION_OF = {key: method for method, opts in BOUNDS_OPTIONS.items() for key in opts}
_BASE = {"systems": ["paper-stable"], "sigma_w": [1.0], "N": [10]}
_DATASET_BASE = {"dataset": 1, "N": [1]}


def _top(path: str) -> str:
    """The spec key an error path belongs to: ``systems[0].A`` -> ``systems``."""
    return path.split("[", 1)[0].split(".", 1)[0]


def spec_errors(obj: object) -> dict[str, str]:
    """Every error of the spec ``obj`` as ``{field path: message}`` (empty when
    ``parse_spec(obj)`` accepts it; otherwise it holds the parser's own error). A spec
    on measured data (``dataset``, docs/measured.md#spec) is checked by its own parser,
    field by field in the same way (the checks against the dataset's shape come at
    submit)."""
    if not isinstance(obj, dict):
        return {"spec": "must be a JSON object"}
    errors: dict[str, str] = {}
    if "dataset" in obj:  # a job on measured data: each field alone, then the whole
        for key in obj:
            try:
                parse_spec({**_DATASET_BASE, key: obj[key]})
            except SpecError as exc:
                errors.setdefault(exc.field or key, exc.message)
        if "N" not in obj:
            errors["N"] = "is required"
        return _whole(obj, errors)
    for key in sorted(set(obj) - SPEC_KEYS):
        message = unknown_field(key, SPEC_KEYS | DATASET_KEYS)
        errors[key] = DATASET_ONLY_MESSAGE if key in DATASET_KEYS else message
    for key in REQUIRED_KEYS:
        if key not in obj:
            errors[key] = "is required"
    for key in SPEC_KEYS & set(obj):
        probe = {**_BASE, key: obj[key]}
        if key in _OPTION_OF:
            probe["bounds_method"] = _OPTION_OF[key]
        if key == "N":  # T0 · N is checked on N (the parser names the N entry)
            t0 = obj.get("T0", DEFAULTS["T0"])
            valid = isinstance(t0, int) and not isinstance(t0, bool) and 2 <= t0 <= MAX_T0
            probe["T0"] = t0 if valid else 2
        try:
            parse_spec(probe)
        except SpecError as exc:
            errors.setdefault(exc.field or key, exc.message)
    return _whole(obj, errors)


def _whole(obj: dict[str, Any], errors: dict[str, str]) -> dict[str, str]:
    """``errors`` and the whole spec's error, unless it is one of them again."""
    try:
        parse_spec(obj)
    except SpecError as exc:  # a rule between fields, or the first error found again
        field = exc.field or "spec"
        if not any(_top(p) == _top(field) for p in errors):
            errors[field] = exc.message
    return errors
