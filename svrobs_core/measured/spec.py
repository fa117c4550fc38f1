"""The spec of a job on measured data (docs/measured.md#spec).

``parse_dataset_spec`` is what :func:`svrobs_core.parse_spec` runs for a spec
with ``"dataset"``: the checks that need no data. ``check_against_data`` runs
the checks that need the dataset's shape (the application layer calls it at
submit; the runner calls it again). Every error is a :class:`SpecError`
naming the field.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import dataclass, fields
from typing import Any

import numpy as np

from ..array_types import IntArray
from ..errors import SpecError, unknown_field
from ..spec import (
    MAX_STATE_DIM,
    SPEC_KEYS,
    ExperimentSpec,
    _bounds_options,
    _float,
    _int,
    _n_grid,
    _object,
    shared_options,
)
from ..systems import SIGMA_V0_COND_LIMIT, _matrix, _positive_number

SPEC_FIELDS = (
    "dataset",
    "N",
    "holdout",
    "sigma_w",
    "C",
    "sigma_v",
    "sigma_u",
    "state",
    "gamma",
    "estimators",
    "loss_scale",
    "reps",
    "M",
    "delta",
    "stages",
    "horizon",
    "margin",
    "gamma_ref",
    "sls",
    "seed",
    "bounds_method",
    "S",
    "lambda0",
)
BOUNDS_METHOD = "self-normalized"  # the one sound on measured data
_NOT_ON_DATA = {  # why the other bounds methods are refused on a dataset
    "paper": "the paper's bounds need the simulation design (x0 = 0, Gaussian inputs of a "
    "known sigma_u, equal T0)",
    "bootstrap": "the bootstrap re-simulates the simulation design from the estimate, "
    "not the measured inputs: on logged rollouts there is no such design to resample",
}
# The record key sigma_w of a job whose noise level is estimated: a key, not a level.
SIGMA_W_ESTIMATED = -1.0


@dataclass(frozen=True, kw_only=True)
class DatasetOptions:
    """What a dataset job adds to :class:`ExperimentSpec` (its ``measured`` field).

    ``sigma_w`` None means "estimate"; ``C`` None means the default (I_n, or for
    the ARX state the rows that pick y_k); ``sigma_u`` None means the RMS of the
    training pool's inputs; ``lags`` (p, q) for the ARX state, None for the full state.
    """

    dataset: int
    holdout: int = 0
    sigma_w: float | None = None
    C: tuple[tuple[float, ...], ...] | None = None
    sigma_v: float = 0.1
    sigma_u: float | None = None
    lags: tuple[int, int] | None = None

    @property
    def system_name(self) -> str:
        """The records' ``system`` key."""
        return f"dataset-{self.dataset}"

    @property
    def record_sigma_w(self) -> float:
        """The records' ``sigma_w`` key: the given level, or :data:`SIGMA_W_ESTIMATED`."""
        return SIGMA_W_ESTIMATED if self.sigma_w is None else self.sigma_w

    def state_dim(self, n: int, m: int) -> int:
        """The model's state dimension for data with n measured channels and m inputs."""
        if self.lags is None:
            return n
        p, q = self.lags
        return p * n + q * m

    def C_matrix(self, n: int, m: int) -> np.ndarray:
        """The observer's C for data with n measured channels and m inputs."""
        if self.C is not None:
            return np.array(self.C, dtype=float)
        return np.eye(n, self.state_dim(n, m))

    def spec_dict(self, spec: ExperimentSpec) -> dict[str, Any]:
        """The normalised JSON of the dataset spec (``parse_spec`` reads it back)."""
        out = {
            "dataset": self.dataset,
            "N": list(spec.N),
            "holdout": self.holdout,
            "sigma_w": "estimate" if self.sigma_w is None else self.sigma_w,
            "C": None if self.C is None else [list(r) for r in self.C],
            "sigma_v": self.sigma_v,
            "sigma_u": self.sigma_u,
            "state": None if self.lags is None else {"lags": dict(zip("yu", self.lags))},
            "gamma": list(spec.gamma),
            "estimators": list(spec.estimators),
            "loss_scale": spec.loss_scale,
            "reps": spec.reps,
            "M": spec.M,
            "delta": spec.delta,
            "stages": list(spec.stages),
            "horizon": spec.horizon,
            "margin": spec.margin,
            "gamma_ref": spec.gamma_ref,
            "sls": {"T_fir": spec.sls_T_fir, "C_bound": spec.sls_C_bound},
            "seed": spec.seed,
            "bounds_method": spec.bounds_method,
            "S": spec.S,
            "lambda0": spec.lambda0,
        }
        return {k: out[k] for k in SPEC_FIELDS}


_DEFAULTS = {f.name: f.default for f in fields(DatasetOptions)}  # written once, there


def _sigma_w(value: object) -> float | None:
    if value == "estimate":
        return None
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise SpecError(
            "sigma_w", f'must be a number or "estimate", got {json.dumps(value, default=str)}'
        )
    return _float(value, "sigma_w", nonneg=True)


def _lags(value: object) -> tuple[int, int] | None:
    """``{"lags": {"y": p, "u": q}}`` -> (p, q); None (or absent) -> the full state."""
    if value is None:
        return None
    if not isinstance(value, dict) or set(value) != {"lags"}:
        raise SpecError("state", 'must be {"lags": {"y": p, "u": q}} (or absent: the full state)')
    lags = _object(value["lags"], "state.lags", ("y", "u"))
    if "y" not in lags:
        raise SpecError("state.lags.y", "is required")
    p = _int(lags["y"], "state.lags.y", lo=1, hi=MAX_STATE_DIM)
    q = _int(lags.get("u", 0), "state.lags.u", lo=0, hi=MAX_STATE_DIM)
    return p, q


def parse_dataset_spec(obj: dict[str, Any]) -> ExperimentSpec:
    """Validate a dataset spec (docs/measured.md#spec): the checks that need no data."""
    for key in obj:
        if key in SPEC_FIELDS:
            continue
        if key == "systems":
            raise SpecError("dataset", "give either systems or dataset, not both")
        if key in SPEC_KEYS:
            raise SpecError(key, "is not used with a dataset (it describes a simulation)")
        raise SpecError(key, unknown_field(key, SPEC_FIELDS))
    if "N" not in obj:
        raise SpecError("N", "is required")
    dataset = _int(obj["dataset"], "dataset", lo=1, hi=2**63 - 1)
    method = obj.get("bounds_method", BOUNDS_METHOD)
    if method != BOUNDS_METHOD:
        why = _NOT_ON_DATA.get(method, "it is not a bounds method")
        raise SpecError(
            "bounds_method",
            f'must be "{BOUNDS_METHOD}" for a dataset, got {json.dumps(method, default=str)}: '
            f"{why} (docs/measured.md#spec)",
        )
    C = obj.get("C")
    if C is not None:
        C = tuple(tuple(r) for r in _matrix(C, "C").tolist())
    sigma_u = obj.get("sigma_u")
    if sigma_u is not None:
        sigma_u = _positive_number(sigma_u, "sigma_u", allow_zero=False)
    options = DatasetOptions(
        dataset=dataset,
        holdout=_int(obj.get("holdout", _DEFAULTS["holdout"]), "holdout", lo=0, hi=2**31 - 1),
        sigma_w=_sigma_w(obj.get("sigma_w", "estimate")),
        C=C,
        sigma_v=_positive_number(
            obj.get("sigma_v", _DEFAULTS["sigma_v"]), "sigma_v", allow_zero=True
        ),
        sigma_u=sigma_u,
        lags=_lags(obj.get("state")),
    )
    return ExperimentSpec(
        systems=(),
        sigma_w=(),
        N=_n_grid(obj["N"]),
        **shared_options(obj),
        **_bounds_options({**obj, "bounds_method": BOUNDS_METHOD}),
        measured=options,
    )


@dataclass(frozen=True)
class DataLayout:
    """The shapes a dataset job's records have on a dataset of this shape.

    n: the model's state dimension (p ny + q m for ARX), m inputs, p outputs
    (rows of C); ``matrix_shapes``: (rows, cols) of every matrix record field."""

    system: str
    sigma_w: float
    n: int
    m: int
    p: int
    C: np.ndarray

    @property
    def matrix_shapes(self) -> dict[str, tuple[int, int]]:
        n, m, p = self.n, self.m, self.p
        return {
            "A_hat": (n, n),
            "B_hat": (n, m),
            "radii_A": (n, n),
            "radii_B": (n, m),
            "L": (n, p),
            "K": (n, p),
        }


def check_against_data(
    spec: ExperimentSpec,
    n: int,
    m: int,
    rollouts: int,
    *,
    lengths: Sequence[int] | IntArray | None = None,
) -> DataLayout:
    """The checks of a dataset spec that need the dataset's shape -> its DataLayout.

    n: measured channels per sample (states; outputs y for the ARX state), m
    inputs, rollouts: how many; ``lengths``: optional transitions per rollout
    (T_i), checked against the ARX lags. Raises SpecError naming the field.
    """
    opts = spec.measured
    if opts is None:
        raise SpecError("dataset", "the spec is not a dataset spec (it has systems)")
    if rollouts < 1:
        raise SpecError("dataset", "has no rollouts")
    if opts.holdout >= rollouts:
        raise SpecError(
            "holdout",
            f"must be below the dataset's {rollouts} rollouts (training needs at least one)",
        )
    pool = rollouts - opts.holdout
    top = max(spec.N)
    if top > pool:
        raise SpecError(
            "N",
            f"N = {top} rollouts, but the dataset has {pool} for training "
            f"({rollouts} rollouts, holdout {opts.holdout})",
        )
    if opts.lags is not None:
        p, q = opts.lags
        if m == 0 and q > 0:
            raise SpecError("state.lags.u", f"must be 0: the dataset has no inputs, got {q}")
        if lengths is not None:
            k0 = max(p - 1, q)
            short = [i for i, t in enumerate(lengths) if t <= k0]
            if short:
                i = short[0]
                raise SpecError(
                    "state.lags",
                    f"rollout {i} has {lengths[i] + 1} samples; these lags need at least {k0 + 2}",
                )
    dim = opts.state_dim(n, m)
    if dim > MAX_STATE_DIM:
        field = "dataset" if opts.lags is None else "state.lags"
        raise SpecError(field, f"the state has {dim} entries, at most {MAX_STATE_DIM}")
    layout = data_layout(spec, n, m)
    C = layout.C
    if C.shape[1] != dim:
        raise SpecError("C", f"must have {dim} columns (the state dimension), got {C.shape[1]}")
    if opts.sigma_v == 0.0 and not (C.shape[0] == dim and np.linalg.cond(C) <= SIGMA_V0_COND_LIMIT):
        raise SpecError(
            "sigma_v", "sigma_v = 0 needs a square invertible C (the Kalman gain is A C^-1)"
        )
    return layout


def data_layout(spec: ExperimentSpec, n: int, m: int) -> DataLayout:
    """The DataLayout of a dataset spec on data with n measured channels and m
    inputs, without the checks of :func:`check_against_data` (for reading the
    records of a job that passed them)."""
    opts = spec.measured
    C = opts.C_matrix(n, m)
    return DataLayout(
        system=opts.system_name,
        sigma_w=opts.record_sigma_w,
        n=opts.state_dim(n, m),
        m=m,
        p=C.shape[0],
        C=C,
    )
