"""svrobs_core: the science of SPEC.md as pure, vectorised functions (no I/O).

from svrobs_core import parse_spec, run_spec
spec = parse_spec({"systems": ["paper-stable"], "sigma_w": [1.0], "N": [50]})
records = [r for batch in run_spec(spec) for r in batch]
"""

from .errors import DimensionError, SpecError, check_matrix
from .parallel import open_pool
from .planning import plan_units
from .records import RECORD_FIELDS, summarize
from .runner import run_spec, run_unit, run_unit_result
from .spec import ExperimentSpec, parse_spec
from .systems import PRESETS, SystemSpec, resolve_system
from .unit_result import UnitResult

__version__ = "0.1.0"

__all__ = [
    "PRESETS",
    "RECORD_FIELDS",
    "DimensionError",
    "ExperimentSpec",
    "SpecError",
    "SystemSpec",
    "UnitResult",
    "__version__",
    "check_matrix",
    "open_pool",
    "parse_spec",
    "plan_units",
    "resolve_system",
    "run_spec",
    "run_unit",
    "run_unit_result",
    "summarize",
]
