"""svrobs_client: a Python client of the svrobs REST API (httpx; pandas optional).

    from svrobs_client import Client

    with Client("http://127.0.0.1:8000", "svr_...") as c:
        job = c.submit(spec, name="tour", tags=["demo"])   # waits, with a progress bar
        df = c.results(job, estimator="svr", N=[50, 100])  # a DataFrame; matrices as arrays
        c.summary(job)                                     # mean/std/count per group
        c.report(job, "report/")                           # report.html + figures/
        ds = c.upload_dataset("runs.csv", name="plant runs")  # measured rollouts
        c.model(job, "system=plant,N=50,estimator=svr,gamma=0.05,rep=0")  # StateSpace

Errors are :class:`SvrobsError` subclasses carrying ``status``, ``field`` and
``message`` (see :mod:`svrobs_client.errors`).
"""

from .client import RESULT_FILTERS, SEED_POLICIES, Client
from .config import DEFAULT_URL, config_path, resolve
from .datasets import Model
from .errors import (
    AuthError,
    BadRequest,
    ConfigError,
    Conflict,
    ConnectionFailed,
    MethodNotAllowed,
    NotFound,
    RateLimited,
    ServerError,
    SvrobsError,
    TooLarge,
    Unavailable,
    ValidationError,
    WaitTimeout,
)
from .frames import MATRIX_FIELDS
from .models import (
    TERMINAL,
    Dataset,
    DatasetPage,
    Job,
    JobPage,
    Progress,
    Report,
    Schedule,
    ScheduleRun,
    Share,
)
from .params import NUMERIC_FIELDS, RANGE_FIELDS

__all__ = [
    "AuthError",
    "BadRequest",
    "Client",
    "ConfigError",
    "Conflict",
    "ConnectionFailed",
    "DEFAULT_URL",
    "Dataset",
    "DatasetPage",
    "Job",
    "JobPage",
    "MATRIX_FIELDS",
    "MethodNotAllowed",
    "Model",
    "NUMERIC_FIELDS",
    "NotFound",
    "Progress",
    "RANGE_FIELDS",
    "RESULT_FILTERS",
    "RateLimited",
    "Report",
    "Schedule",
    "ScheduleRun",
    "SEED_POLICIES",
    "ServerError",
    "Share",
    "SvrobsError",
    "TERMINAL",
    "TooLarge",
    "Unavailable",
    "ValidationError",
    "WaitTimeout",
    "config_path",
    "resolve",
]
