"""Run the Alembic migrations programmatically (``svrobs migrate``, tests, ``serve``)."""

from __future__ import annotations

import os

from alembic import command
from alembic.config import Config

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))


def alembic_config(url: str) -> Config:
    cfg = Config(os.path.join(ROOT, "alembic.ini"))
    cfg.set_main_option("script_location", os.path.join(ROOT, "migrations"))
    cfg.attributes["configure_logging"] = False
    # ConfigParser interpolation: a literal % in a password must be doubled
    cfg.set_main_option("sqlalchemy.url", url.replace("%", "%%"))
    return cfg


def upgrade(url: str, revision: str = "head") -> None:
    """``alembic upgrade head`` against ``url`` (the caller's SVROBS_DATABASE_URL)."""
    command.upgrade(alembic_config(url), revision)


def downgrade(url: str, revision: str = "base") -> None:
    command.downgrade(alembic_config(url), revision)


def current_revision(url: str) -> str | None:
    from alembic.runtime.migration import MigrationContext

    from service.db.session import get_engine

    with get_engine(url).connect() as conn:
        return MigrationContext.configure(conn).get_current_revision()


def missing_database(url: str) -> str | None:
    """Why ``url`` holds no svrobs database, without creating one (a connection to a
    SQLite path that does not exist would create the file): the file is not there, or
    no migration ever ran on it. None when the tables are there."""
    from sqlalchemy.engine import make_url

    u = make_url(url)
    shown = u.render_as_string(hide_password=True)
    if u.get_backend_name() == "sqlite" and u.database not in (None, "", ":memory:"):
        if not u.database.startswith("file:") and not os.path.exists(u.database):
            return f"no svrobs database at {shown} (no such file)"
    if current_revision(url) is None:
        return f"no svrobs tables in the database at {shown} (never migrated)"
    return None
