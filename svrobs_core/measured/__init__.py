"""Jobs on measured data: estimation, sound sets, certified observers and
validation on logged rollouts (docs/measured.md).

* :class:`MeasuredData`: the rollouts (X, U lists, ragged lengths, m = 0 allowed).
* :func:`run_measured_unit`: one work unit of a dataset job -> its records
  (a :class:`svrobs_core.UnitResult`); :func:`plan_measured_units` the units.
* :func:`check_against_data`: the spec's checks that need the dataset's shape.
* :func:`validate` / :func:`validation_summary`: held-out validation.
"""

from __future__ import annotations

from .data import MeasuredData, StateModel
from .runner import plan_measured_units, run_datasets, run_measured_unit
from .spec import SIGMA_W_ESTIMATED, DataLayout, DatasetOptions, check_against_data, data_layout
from .validation import (
    Excitation,
    Model,
    ValidationResult,
    excitation,
    fit_model,
    regressor_excitation,
    validate,
    validation_summary,
)

__all__ = [
    "SIGMA_W_ESTIMATED",
    "DataLayout",
    "DatasetOptions",
    "Excitation",
    "MeasuredData",
    "Model",
    "StateModel",
    "ValidationResult",
    "check_against_data",
    "data_layout",
    "excitation",
    "fit_model",
    "plan_measured_units",
    "regressor_excitation",
    "run_datasets",
    "run_measured_unit",
    "validate",
    "validation_summary",
]
