"""Suite-wide: under pytest-xdist (``make test`` runs ``-n 2``) each worker gets a
Redis database number of its own, so that two real-process stacks never flush or
consume each other's queues. PostgreSQL needs nothing: every fixture creates a
private database or schema named after its process."""

from __future__ import annotations

import os
from urllib.parse import urlsplit, urlunsplit


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
