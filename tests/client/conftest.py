"""The client and CLI tests run against real servers: the integration tests' ``stack``
fixture (uvicorn + a celery worker as real processes, embedded SQLite + filesystem
broker, and PostgreSQL + Redis when the SVROBS_TEST_* URLs are set)."""

from tests.integration.conftest import stack  # noqa: F401 - the fixture, reused
