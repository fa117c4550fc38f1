"""Fixtures for the service tests: a migrated database (SQLite always, PostgreSQL when
SVROBS_TEST_DATABASE_URL is set), one outer transaction per test rolled back at the end
(sessions join it with SAVEPOINTs), and a TestClient whose publisher is recorded."""

from __future__ import annotations

import os
import uuid

import pytest
from fastapi.testclient import TestClient
from sqlalchemy import create_engine, text
from sqlalchemy.engine import make_url
from sqlalchemy.exc import DBAPIError
from sqlalchemy.orm import Session

from service.db import accounts
from service.db.migrate import upgrade
from service.db.session import create_db_engine
from service.http.deps import get_broker_check
from tests.service.svc_helpers import Account, RecordingPublisher, make_settings, no_broker_check

PG_ENV = "SVROBS_TEST_DATABASE_URL"


def _pg_private_db(base_url: str):
    """A fresh database on the test server (so concurrent suites never collide)."""
    url = make_url(base_url)
    name = f"svrobs_svc_{os.getpid()}_{uuid.uuid4().hex[:6]}"
    admin_engine = create_engine(url, isolation_level="AUTOCOMMIT")
    try:
        with admin_engine.connect() as c:
            c.execute(text(f'CREATE DATABASE "{name}"'))
    except DBAPIError:
        admin_engine.dispose()
        return base_url, None  # no CREATEDB right: use the given database as is
    return url.set(database=name).render_as_string(hide_password=False), (admin_engine, name)


BACKENDS = ["sqlite", "postgresql"]


@pytest.fixture(scope="session", params=BACKENDS)
def db_url(request, tmp_path_factory):
    if request.param == "sqlite":
        url = f"sqlite:///{tmp_path_factory.mktemp('db') / 'svrobs.db'}"
        upgrade(url)
        yield url
        return
    base = os.environ.get(PG_ENV)
    if not base:
        pytest.skip(f"{PG_ENV} not set")
    url, cleanup = _pg_private_db(base)
    upgrade(url)
    yield url
    if cleanup is not None:
        from service.db.session import dispose_all

        dispose_all()
        admin_engine, name = cleanup
        with admin_engine.connect() as c:
            c.execute(text(f'DROP DATABASE IF EXISTS "{name}" WITH (FORCE)'))
        admin_engine.dispose()


@pytest.fixture(scope="session")
def engine(db_url):
    eng = create_db_engine(db_url)
    yield eng
    eng.dispose()


@pytest.fixture
def connection(engine):
    conn = engine.connect()
    trans = conn.begin()
    yield conn
    trans.rollback()
    conn.close()


@pytest.fixture
def session_factory(connection):
    def factory(write: bool = True) -> Session:
        return Session(
            bind=connection, join_transaction_mode="create_savepoint", expire_on_commit=False
        )

    return factory


@pytest.fixture
def session(session_factory):
    s = session_factory()
    yield s
    s.close()


@pytest.fixture
def make_account(session):
    def make(team_name: str | None = None, *, is_admin: bool = False, **key_kw) -> Account:
        name = team_name or f"team-{uuid.uuid4().hex[:8]}"
        team = accounts.create_team(session, name)
        user = accounts.create_user(
            session, team.id, f"{uuid.uuid4().hex[:8]}@{name}.org", is_admin=is_admin
        )
        key_row, key = accounts.create_key(session, user.id, **key_kw)
        session.commit()
        return Account(team, user, key_row, key)

    return make


@pytest.fixture
def settings(db_url):
    return make_settings(db_url)


@pytest.fixture
def build_client(session_factory, db_url):
    """build_client(**settings_overrides) -> (TestClient, publisher)."""
    from service.app import create_app

    def build(**kw):
        app = create_app(make_settings(db_url, **kw))
        app.state.session_factory = session_factory
        publisher = RecordingPublisher()
        app.state.publisher = publisher
        app.dependency_overrides[get_broker_check] = lambda: no_broker_check
        client = TestClient(app, raise_server_exceptions=False)
        return client, publisher

    return build


@pytest.fixture
def client_pub(build_client):
    return build_client()


@pytest.fixture
def client(client_pub):
    return client_pub[0]


@pytest.fixture
def publisher(client_pub):
    return client_pub[1]
