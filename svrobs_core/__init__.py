"""svrobs_core: the science of SPEC.md as pure, vectorised functions (no I/O).

from svrobs_core import parse_spec, run_spec
spec = parse_spec({"systems": ["paper-stable"], "sigma_w": [1.0], "N": [50]})
records = [r for batch in run_spec(spec) for r in batch]
"""

from .errors import SpecError
from .experiments import plan_units, run_spec, run_unit
from .records import RECORD_FIELDS, summarize
from .spec import ExperimentSpec, parse_spec
from .systems import PRESETS, SystemSpec, resolve_system

__version__ = "0.1.0"

__all__ = [
    "PRESETS",
    "RECORD_FIELDS",
    "ExperimentSpec",
    "SpecError",
    "SystemSpec",
    "__version__",
    "parse_spec",
    "plan_units",
    "resolve_system",
    "run_spec",
    "run_unit",
    "summarize",
]
