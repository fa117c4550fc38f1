"""Private PostgreSQL and Redis servers, and a stack on them, for the fault tests.

The fault tests stop, kill and restart servers, so they never touch the
machine's own PostgreSQL or Redis: a session-scoped :class:`PrivateRedis`
(``redis-server`` on a spare loopback port, no persistence) and
:class:`PrivatePostgres` (``initdb`` into a temporary folder, the postmaster run
in the foreground on a spare loopback port, stopped with ``pg_ctl stop -m
fast``) are started once. Running as root, PostgreSQL runs as the ``postgres``
OS user (initdb refuses root) in a folder it owns.

``fstack`` is the integration tests' :class:`~integration.stack.Stack` pointed
at those servers (one schema of its own), with the API running. Every server
and process is started in its own process group with a parent-death signal,
and finalizers kill the groups: no orphans, even if a test fails half way.
Every wait is bounded in time.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import httpx
import pytest

from tests.integration.servers import PG_BINDIR, REDIS_SERVER, PrivatePostgres, PrivateRedis
from tests.integration.stack import Stack

FAULT_ENV = {
    # the fault tests measure recovery, not the abuse limits: keep those out of the way
    "SVROBS_RATE_LIMIT_PER_MINUTE": "1000000",
    "SVROBS_MAX_QUEUED_JOBS_PER_TEAM": "10000",
}


class Servers:
    def __init__(self, pg: PrivatePostgres, redis: PrivateRedis):
        self.pg = pg
        self.redis = redis

    def ensure_up(self) -> None:
        """A previous test may have failed with a server stopped: start it again."""
        if not self.redis.running():
            self.redis.start()
        if not self.pg.running():
            self.pg.start()


# --------------------------------------------------------------------------- stack
class FaultStack(Stack):
    """The integration Stack on the private servers, plus DB access for the checks."""

    def __init__(self, root: Path, servers: Servers):
        super().__init__(
            "pg", root, pg_url=servers.pg.url, redis_url=servers.redis.url, extra_env=FAULT_ENV
        )
        self.servers = servers
        self._engine = None

    @property
    def db_url(self) -> str:
        return self.env["SVROBS_DATABASE_URL"]

    def engine(self):
        if self._engine is None:
            import sqlalchemy as sa

            self._engine = sa.create_engine(
                self.db_url, pool_pre_ping=True, connect_args={"connect_timeout": 3}
            )
        return self._engine

    def sql(self, query: str, **params) -> list:
        import sqlalchemy as sa

        with self.engine().begin() as c:
            res = c.execute(sa.text(query), params)
            return list(res.all()) if res.returns_rows else []

    def dispose(self) -> None:
        if self._engine is not None:
            self._engine.dispose()

    def teardown(self) -> None:
        # the servers (and the schema with them) go away at the end of the session
        from svrobs_cli.processes import stop_all

        stop_all(list(self.children.values()), grace=10)
        self.children.clear()
        if self._engine is not None:
            self._engine.dispose()

    def api_alive(self) -> bool:
        child = self.children.get("api")
        if child is None or child.poll() is not None:
            return False
        try:
            return httpx.get(self.base_url + "/readyz", timeout=5).status_code == 200
        except httpx.HTTPError:
            return False


@pytest.fixture(scope="session")
def servers(tmp_path_factory):
    if PG_BINDIR is None or REDIS_SERVER is None:
        pytest.skip("the fault tests need PostgreSQL's initdb/pg_ctl/postgres and redis-server")
    if os.geteuid() == 0:
        import pwd

        try:
            pwd.getpwnam("postgres")
        except KeyError:
            pytest.skip("running as root without a `postgres` OS user for initdb")
    redis = PrivateRedis(tmp_path_factory.mktemp("redis"))
    pg = None
    try:
        redis.start()
        pg = PrivatePostgres()
        pg.init()
        pg.start()
        yield Servers(pg, redis)
    finally:
        redis.stop()
        if pg is not None:
            pg.close()


@pytest.fixture(scope="module")
def fstack(servers, tmp_path_factory):
    """A migrated stack (schema of its own, team key) with the API running."""
    servers.ensure_up()
    st = FaultStack(tmp_path_factory.mktemp("fstack"), servers)
    try:
        st.setup()
        st.start_api()
        yield st
    finally:
        st.teardown()


def _stop_all_but_api(st: FaultStack) -> None:
    from svrobs_cli.processes import stop_all

    names = [n for n in st.children if n != "api"]
    stop_all([st.children.pop(n) for n in names], grace=5)  # in parallel


@pytest.fixture
def stack_up(fstack):
    """Before each test: both servers and the API up (restarted if an earlier test
    failed half way), and no worker or beat left from that test."""
    fstack.servers.ensure_up()
    _stop_all_but_api(fstack)
    if not fstack.api_alive():
        fstack.stop("api", grace=2)
        fstack.start_api()
    yield fstack
    _stop_all_but_api(fstack)


# --------------------------------------------------------------------------- report
RESULTS: dict = {}  # the tests' measured figures, printed at the end of the session


def pytest_terminal_summary(terminalreporter):
    if not RESULTS:
        return
    terminalreporter.section("fault tests: measured")
    for name, value in RESULTS.items():
        terminalreporter.write_line(f"{name}: {json.dumps(value, default=str)}")
    path = os.environ.get("SVROBS_FAULTS_REPORT")
    if path:
        Path(path).parent.mkdir(parents=True, exist_ok=True)
        Path(path).write_text(json.dumps(RESULTS, indent=2, default=str) + "\n")
        terminalreporter.write_line(f"(written to {path})")
