"""svrobs_core: the science of docs/science.md as pure, vectorised functions (no I/O).

from svrobs_core import parse_spec, run_spec
spec = parse_spec({"systems": ["paper-stable"], "sigma_w": [1.0], "N": [50]})
records = [r for batch in run_spec(spec) for r in batch]

The names below are imported on first use, so that ``svrobs_core.threads``
can be imported (and the BLAS thread variables set) before numpy is.

Modules, by stage of a run: spec, systems -> planning (work units) ->
runner (units -> records) -> pipeline (the stage chain: estimators, bounds,
kalman, gains, cost, cost_mc, cost_bound, sls) -> unit_result, notes,
records; parallel and threads for execution; errors for the typed errors.
Jobs on measured rollouts: measured (docs/measured.md).
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

__version__ = "0.1.0"

_EXPORTS = {
    "DimensionError": "errors",
    "SpecError": "errors",
    "check_matrix": "errors",
    "MeasuredData": "measured",
    "check_against_data": "measured",
    "run_measured_unit": "measured",
    "open_pool": "parallel",
    "plan_units": "planning",
    "RECORD_FIELDS": "records",
    "summarize": "records",
    "run_spec": "runner",
    "run_unit": "runner",
    "run_unit_result": "runner",
    "ExperimentSpec": "spec",
    "parse_spec": "parsing",
    "PRESETS": "systems",
    "SystemSpec": "systems",
    "resolve_system": "systems",
    "UnitResult": "unit_result",
}

__all__ = [
    "DimensionError",
    "ExperimentSpec",
    "MeasuredData",
    "PRESETS",
    "RECORD_FIELDS",
    "SpecError",
    "SystemSpec",
    "UnitResult",
    "__version__",
    "check_against_data",
    "check_matrix",
    "open_pool",
    "parse_spec",
    "plan_units",
    "resolve_system",
    "run_measured_unit",
    "run_spec",
    "run_unit",
    "run_unit_result",
    "summarize",
]

if TYPE_CHECKING:  # the same names, for linters and type checkers
    from .errors import DimensionError, SpecError, check_matrix
    from .measured import MeasuredData, check_against_data, run_measured_unit
    from .parallel import open_pool
    from .parsing import parse_spec
    from .planning import plan_units
    from .records import RECORD_FIELDS, summarize
    from .runner import run_spec, run_unit, run_unit_result
    from .spec import ExperimentSpec
    from .systems import PRESETS, SystemSpec, resolve_system
    from .unit_result import UnitResult


def __getattr__(name: str) -> Any:
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(importlib.import_module(f".{module}", __name__), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted([*globals(), *_EXPORTS])
