"""A private PostgreSQL database for a bench: created on the server of
``SVROBS_BENCH_DATABASE_URL`` (else ``SVROBS_TEST_DATABASE_URL``) and dropped after,
so that a bench never writes into the database of that URL itself."""

from __future__ import annotations

import os
import uuid
from collections.abc import Iterator
from contextlib import contextmanager

from sqlalchemy import create_engine
from sqlalchemy.engine import make_url

from service.db.session import dispose_all


def bench_pg_url() -> str | None:
    return os.environ.get("SVROBS_BENCH_DATABASE_URL") or os.environ.get("SVROBS_TEST_DATABASE_URL")


@contextmanager
def private_database(base: str, prefix: str, *, keep: bool = False) -> Iterator[str]:
    """``with private_database(url, "svrobs_x") as url: ...`` -> the new database's URL."""
    name = f"{prefix}_{uuid.uuid4().hex[:8]}"
    admin = create_engine(make_url(base), isolation_level="AUTOCOMMIT")
    with admin.connect() as c:
        c.exec_driver_sql(f'CREATE DATABASE "{name}"')
    try:
        yield make_url(base).set(database=name).render_as_string(hide_password=False)
    finally:
        dispose_all()
        if not keep:
            with admin.connect() as c:
                c.exec_driver_sql(f'DROP DATABASE IF EXISTS "{name}" WITH (FORCE)')
        admin.dispose()
