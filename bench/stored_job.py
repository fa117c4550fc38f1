"""Compute a stored job's units in process and store them through the worker's
write path (``units.start_unit`` / ``units.complete_unit``)."""

from __future__ import annotations

from service.db import jobs, units
from service.db.session import session_scope
from svrobs_core.parsing import parse_spec
from svrobs_core.runner import run_unit_result


def run_stored_units(url: str, job_id: int, spec_dict: dict, *, worker: str, lease: int) -> None:
    """Run and store every unit of job ``job_id`` (spec ``spec_dict``), one session
    per step as a worker does."""
    spec = parse_spec(spec_dict)
    with session_scope(url) as s:
        ids = jobs.unit_ids_of_job(s, job_id)
    for uid in ids:
        with session_scope(url) as s:
            started = units.start_unit(s, uid, worker, lease, max_attempts=0)
        assert started is not None, f"unit {uid} of a fresh job could not be started"
        result = run_unit_result(spec, started[1])
        with session_scope(url) as s:
            units.complete_unit(s, uid, result)
