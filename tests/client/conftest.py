"""The client and CLI tests run against real servers: the integration tests' ``stack``
fixture (uvicorn + a celery worker as real processes, embedded SQLite + filesystem
broker, and PostgreSQL + Redis when the SVROBS_TEST_* URLs are set)."""

import pytest

from tests.integration.conftest import stack  # noqa: F401 - the fixture, reused


@pytest.fixture
def http(stack):  # noqa: F811 - the fixture above
    """Plain httpx on the stack's API with its key: the oracle the tests compare with."""
    with stack.client() as c:
        yield c
