"""A work unit's computation, for the worker (``worker.tasks``): a simulated job's by
the core alone (``svrobs_core.runner.run_unit_result``), a dataset job's on its
stored arrays (``svrobs_core.measured.run_measured_unit``); after a dataset job's
unit, its validation is stored if it is not yet (:mod:`svrobs_lab.validation`)."""

from __future__ import annotations

import logging
from typing import cast

from svrobs_core.measured import MeasuredData, run_measured_unit
from svrobs_core.parsing import parse_spec
from svrobs_core.runner import run_unit_result
from svrobs_core.unit_result import UnitResult

from .datasets.loaded import measured_data
from .validation import store_after_unit

log = logging.getLogger(__name__)


def compute_unit(scope, spec_dict: dict, payload: dict) -> tuple[UnitResult, MeasuredData | None]:
    """(the unit's records, the dataset it ran on or None); ``scope`` is
    :func:`service.db.session.session_scope` (a dataset's arrays are read with it)."""
    spec = parse_spec(spec_dict)
    if spec.measured is None:
        return run_unit_result(spec, payload), None
    with scope(write=False) as s:
        data = measured_data(s, cast(int, spec.dataset), cache=True)  # a dataset job's id
    return run_measured_unit(spec, payload, data), data


def after_unit(scope, unit_id: int, spec_dict: dict, data: MeasuredData | None) -> None:
    """What follows a stored unit: a dataset job's validation, stored once. Best
    effort: ``GET /jobs/{id}/validation`` computes what this did not store."""
    if data is None:
        return
    try:
        store_after_unit(scope, unit_id, spec_dict, data)
    except Exception as exc:  # noqa: BLE001 - the unit's records are stored already
        log.warning("unit %s: storing its job's validation failed: %s", unit_id, exc)
