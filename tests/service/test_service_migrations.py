"""Alembic is the only way tables are made, and the migrations match the models."""

from __future__ import annotations

from alembic.autogenerate import compare_metadata
from alembic.migration import MigrationContext
from sqlalchemy import inspect

from service.db.migrate import current_revision, downgrade, upgrade
from service.db.models import Base
from service.db.session import create_db_engine


def test_upgrade_matches_models_and_downgrades(tmp_path):
    url = f"sqlite:///{tmp_path / 'm.db'}"
    upgrade(url)
    engine = create_db_engine(url)
    with engine.connect() as conn:
        diff = compare_metadata(MigrationContext.configure(conn), Base.metadata)
        assert diff == []
        assert set(inspect(conn).get_table_names()) >= set(Base.metadata.tables)
    assert current_revision(url) is not None
    downgrade(url)
    with engine.connect() as conn:
        assert set(inspect(conn).get_table_names()) <= {"alembic_version"}
    engine.dispose()


def test_postgres_schema_matches_models(engine):
    with engine.connect() as conn:
        assert compare_metadata(MigrationContext.configure(conn), Base.metadata) == []


def test_new_sqlite_database_has_8k_pages_and_an_old_one_keeps_its_own(tmp_path):
    """A results row (~380 bytes) fits 21 times in an 8 KB page, 10 times in 4 KB."""
    import sqlite3

    from service.db.session import SQLITE_PAGE_SIZE

    new = tmp_path / "new.db"
    upgrade(f"sqlite:///{new}")
    old = tmp_path / "old.db"
    with sqlite3.connect(old) as c:  # made elsewhere, with SQLite's default pages
        c.execute("CREATE TABLE t (x)")
    upgrade(f"sqlite:///{old}")
    pages = {p: sqlite3.connect(p).execute("PRAGMA page_size").fetchone()[0] for p in (new, old)}
    assert pages == {new: SQLITE_PAGE_SIZE, old: 4096} and SQLITE_PAGE_SIZE == 8192
