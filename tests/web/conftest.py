"""Fixtures of the web UI tests, reused by import: the service tests' migrated database
and TestClient (tests/service/conftest.py) for the unit tests, and the real-process
stack (tests/integration/conftest.py) for the browser tests."""

from tests.integration.conftest import stack  # noqa: F401
from tests.service.conftest import (  # noqa: F401
    build_client,
    client,
    client_pub,
    connection,
    db_url,
    engine,
    make_account,
    publisher,
    session,
    session_factory,
    settings,
)
