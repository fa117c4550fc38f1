"""The one error hierarchy of the lab: :class:`LabError` and its kinds.

Each error has a ``kind`` (what went wrong, for the front ends' one mapping:
``service.api.errors`` to an HTTP status, ``service.web.errors`` to a page), an
optional ``field`` (the request field it is about) and a plain ``message``. The
module imports nothing of the service, so the store (``service.db``) raises these
too (docs/architecture.md#layers). A bad spec is the core's
:class:`~svrobs_core.errors.SpecError`, treated as :class:`Invalid` by both
mappings.
"""

from __future__ import annotations

from svrobs_core.errors import SpecError

NAMED_SCHEDULES = 10  # how many schedule names a DatasetScheduled message gives


class LabError(Exception):
    """A request the lab refuses: ``kind``, optional ``field``, plain ``message``."""

    kind = "error"

    def __init__(self, message: str, *, field: str | None = None):
        Exception.__init__(self, message)
        self.message = message
        self.field = field


class NotFound(LabError):
    """No such object for this caller (another team's is indistinguishable from none)."""

    kind = "not_found"


class Conflict(LabError):
    """The request contradicts the object's state."""

    kind = "conflict"


class JobActive(Conflict):
    """The job is queued or running; it can be deleted once cancelled or finished."""

    def __init__(self, job_id: int, status: str):
        super().__init__(f"job {job_id} is {status}: cancel it before deleting it")
        self.job_id = job_id
        self.status = status


class DatasetInUse(Conflict):
    """Jobs run on the dataset: it can be deleted once they are (their ids named)."""

    def __init__(self, dataset_id: int, job_ids: list[int], total: int):
        named = ", ".join(map(str, job_ids))
        more = f" and {total - len(job_ids)} more" if total > len(job_ids) else ""
        jobs = "job" if total == 1 else "jobs"
        super().__init__(f"dataset {dataset_id} is used by {jobs} {named}{more}: delete them first")
        self.dataset_id, self.job_ids, self.total = dataset_id, job_ids, total


class DatasetScheduled(Conflict):
    """Schedules' templates run on the dataset: it can be deleted once they do not
    (their names given)."""

    def __init__(self, dataset_id: int, names: list[str]):
        shown = ", ".join(repr(n) for n in names[:NAMED_SCHEDULES])
        more = f" and {len(names) - NAMED_SCHEDULES} more" if len(names) > NAMED_SCHEDULES else ""
        which = "schedule" if len(names) == 1 else "schedules"
        super().__init__(
            f"dataset {dataset_id} is named by {which} {shown}{more}: change or delete them first"
        )
        self.dataset_id, self.names = dataset_id, names


class IdempotencyConflict(Conflict):
    """The Idempotency-Key was used before with a different spec, name or tags
    (``differs``: which of them)."""

    def __init__(self, job, differs: str = "spec"):
        super().__init__(
            f"Idempotency-Key already used for job {job.id} with a different {differs}",
            field="Idempotency-Key",
        )
        self.job = job
        self.differs = differs


class Invalid(LabError, ValueError):
    """A bad value in the request, naming its ``field``."""

    kind = "invalid"


class JobTooLarge(SpecError, Invalid):
    """The spec is valid but over a job limit: SVROBS_MAX_JOB_CELLS, the estimated
    SVROBS_MAX_JOB_CPU_SECONDS or SVROBS_MAX_UNIT_MEMORY_MB. A
    :class:`~svrobs_core.errors.SpecError` (``str`` is ``"field: message"``)."""

    field: str  # always a spec field (SpecError's), never None

    def __init__(self, field: str, message: str):
        SpecError.__init__(self, field, message)


class DatasetNotFound(SpecError, Invalid):
    """A spec names a dataset the caller's team does not have (another team's is the
    same as none): invalid, naming the spec field that refers to it. A
    :class:`~svrobs_core.errors.SpecError` (``str`` is ``"field: message"``)."""

    field: str  # always a spec field (SpecError's), never None

    def __init__(self, dataset_id, field: str = "dataset"):
        SpecError.__init__(self, field, f"no dataset {dataset_id} in your team")
        self.dataset_id = dataset_id


class BadDatasetFile(SpecError, Invalid):
    """An uploaded file cannot be read as a dataset (or a system); the message names
    the row, column or variable. Invalid, naming the field ``file``."""

    field: str  # always a spec field (SpecError's), never None

    def __init__(self, message: str, field: str = "file"):
        SpecError.__init__(self, field, message)


class AdminError(Invalid):
    """A bad admin request (unknown team, duplicate name...)."""


class Gone(LabError):
    """What the request needs was dropped (retention pruned the job's cell rows)."""

    kind = "gone"


class NeedsCellRows(Gone):
    """The grouping needs cell rows that retention dropped (``job_ids``)."""

    def __init__(self, job_ids: list[int], by: list[str], group_fields: tuple[str, ...]):
        self.job_ids = job_ids
        super().__init__(
            f"job(s) {', '.join(map(str, job_ids))} were pruned by the team's retention "
            f"policy: grouping by {', '.join(b for b in by if b not in group_fields)} needs "
            f"their cell rows; group by {', '.join(group_fields)} (from the stored summaries)",
            field="by",
        )


class Forbidden(LabError):
    """The caller may not do this."""

    kind = "forbidden"


class QuotaExceeded(LabError):
    """Over a per-team limit: SVROBS_MAX_QUEUED_JOBS_PER_TEAM active jobs."""

    kind = "quota"


class RateLimited(QuotaExceeded):
    """Over the key's SVROBS_RATE_LIMIT_PER_MINUTE; ``retry_after`` seconds."""

    def __init__(self, message: str, retry_after: int):
        super().__init__(message)
        self.retry_after = retry_after


class PayloadTooLarge(LabError):
    """A request body over SVROBS_MAX_BODY_BYTES."""

    kind = "too_large"


__all__ = [
    "AdminError",
    "BadDatasetFile",
    "Conflict",
    "DatasetInUse",
    "DatasetScheduled",
    "DatasetNotFound",
    "Forbidden",
    "Gone",
    "IdempotencyConflict",
    "Invalid",
    "JobActive",
    "JobTooLarge",
    "LabError",
    "NeedsCellRows",
    "NotFound",
    "PayloadTooLarge",
    "QuotaExceeded",
    "RateLimited",
]
