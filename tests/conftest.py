"""Suite-wide: under pytest-xdist (``make test`` runs ``-n 3``) each worker gets a
Redis database number of its own, so that two real-process stacks never flush or
consume each other's queues. PostgreSQL needs nothing: every fixture creates a
private database or schema named after its process.

Property tests are derandomized and keep no example database, so a run's outcome
depends on the code alone, never on which examples a previous run happened to find.
Set ``HYPOTHESIS_PROFILE=explore`` to draw fresh examples while hunting for bugs.

The records computed in the test process are compared bit for bit with those of
worker processes, which pin BLAS's threads and kernel before numpy loads
(:mod:`svrobs_core.threads`): the test process pins them the same way, first."""

from __future__ import annotations

import os
import sys

from svrobs_core.threads import single_thread_env

if "numpy" not in sys.modules:  # a plugin that loaded numpy first fixed its BLAS already
    single_thread_env()
from urllib.parse import urlsplit, urlunsplit

from hypothesis import settings

settings.register_profile("repeatable", derandomize=True, database=None)
settings.register_profile("explore", derandomize=False)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "repeatable"))


def _worker_redis_url(url: str, worker: str) -> str:
    """``redis://host:port/5`` for worker ``gw1`` -> ``redis://host:port/6``."""
    parts = urlsplit(url)
    base = int(parts.path.strip("/") or 0)
    return urlunsplit(parts._replace(path=f"/{base + int(worker.removeprefix('gw'))}"))


_worker = os.environ.get("PYTEST_XDIST_WORKER")
if _worker and os.environ.get("SVROBS_TEST_BROKER_URL"):
    os.environ["SVROBS_TEST_BROKER_URL"] = _worker_redis_url(
        os.environ["SVROBS_TEST_BROKER_URL"], _worker
    )


# Modules that run longest, longest first (the durations of `make test
# PYTEST_ADDOPTS=--durations=120`). pytest-xdist's loadscope hands out whole modules in
# collection order, so starting these first and leaving the many short modules to
# fill in at the end keeps both workers busy to the last test (the order of the tests
# inside a module is kept).
_LONGEST_FIRST = (
    "tests/integration/test_readme_tour.py",
    "tests/deploy/test_image.py",
    "tests/multihost/",
    "tests/integration/test_trust.py",
    "tests/integration/test_serve.py",
    "tests/web/test_browser_a11y.py",
    "tests/integration/",
    "tests/web/test_browser",
    "tests/client/",
    "tests/core/test_invariants.py",
    "tests/core/test_property_specs.py",
    "tests/service/test_service_retention.py",
    "tests/service/test_service_api_reports.py",
    "tests/fuzz/",
    "tests/core/test_report.py",
    "tests/reliability/",
)


def _rank(nodeid: str) -> int:
    return next(
        (i for i, prefix in enumerate(_LONGEST_FIRST) if nodeid.startswith(prefix)),
        len(_LONGEST_FIRST),
    )


def pytest_collection_modifyitems(session, config, items):
    items.sort(key=lambda item: _rank(item.nodeid))  # stable: keeps each module's order
