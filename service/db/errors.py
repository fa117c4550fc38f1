"""The domain errors of the DB package, mapped to HTTP responses by the API.

:class:`JobTooLarge` is a :class:`~svrobs_core.errors.SpecError` (422, naming the
field); :class:`QuotaExceeded` is a 429, :class:`IdempotencyConflict` a 409 and
:class:`AdminError` a bad ``svrobs admin`` request.
"""

from __future__ import annotations

from svrobs_core.errors import SpecError


class JobTooLarge(SpecError):
    """The spec is valid but over a job limit: SVROBS_MAX_JOB_CELLS, the estimated
    SVROBS_MAX_JOB_CPU_SECONDS or SVROBS_MAX_UNIT_MEMORY_MB (HTTP 422)."""


class QuotaExceeded(Exception):
    """The team already has SVROBS_MAX_QUEUED_JOBS_PER_TEAM active jobs (HTTP 429)."""


class IdempotencyConflict(Exception):
    """The Idempotency-Key was used before with a different spec (HTTP 409)."""

    def __init__(self, job):
        super().__init__(f"Idempotency-Key already used for job {job.id} with a different spec")
        self.job = job


class AdminError(ValueError):
    """A bad admin request (unknown team, duplicate name...)."""
