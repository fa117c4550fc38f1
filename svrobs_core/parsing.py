"""The one entry point for a spec of either kind of job.

A spec with ``"systems"`` is a simulated job (:func:`svrobs_core.spec.parse_simulation_spec`,
docs/spec.md); one with ``"dataset"`` instead is a job on measured data
(:func:`svrobs_core.measured.spec.parse_dataset_spec`, docs/measured.md#spec). This
module sits above both, so that neither spec module imports the other.
"""

from __future__ import annotations

from .errors import SpecError
from .measured.spec import parse_dataset_spec
from .spec import ExperimentSpec, parse_simulation_spec


def parse_spec(obj: object) -> ExperimentSpec:
    """Validate a spec (a dict from JSON) and fill the defaults; errors name the field."""
    if not isinstance(obj, dict):
        raise SpecError("spec", "must be a JSON object")
    if "dataset" in obj:
        return parse_dataset_spec(obj)
    return parse_simulation_spec(obj)
