"""Alembic environment: the URL is `-x url=...`, else the config's sqlalchemy.url
(set by service.db.migrate), else SVROBS_DATABASE_URL via service.config."""

from __future__ import annotations

from logging.config import fileConfig

from alembic import context

from service.db.models import Base

config = context.config
if config.config_file_name is not None and config.attributes.get("configure_logging", True):
    fileConfig(config.config_file_name, disable_existing_loggers=False)

target_metadata = Base.metadata


def _url() -> str:
    x = context.get_x_argument(as_dictionary=True)
    if x.get("url"):
        return x["url"]
    url = config.get_main_option("sqlalchemy.url")
    if url:
        return url
    from service.config import get_settings

    return get_settings().DATABASE_URL


def run_migrations_offline() -> None:
    url = _url()
    context.configure(
        url=url,
        target_metadata=target_metadata,
        literal_binds=True,
        render_as_batch=url.startswith("sqlite"),
    )
    with context.begin_transaction():
        context.run_migrations()


def run_migrations_online() -> None:
    connection = config.attributes.get("connection")
    if connection is not None:  # an open connection handed over by service.db.migrate
        _run(connection)
        return
    from service.db.session import create_db_engine

    engine = create_db_engine(_url())
    try:
        with engine.connect() as conn:
            _run(conn)
            conn.commit()
    finally:
        engine.dispose()


DATASETS = "0008"  # the revision that adds datasets and jobs.dataset_id


def _below_datasets(connection) -> bool:
    """Whether this command goes from DATASETS or later to a revision before it."""
    from alembic.migration import MigrationContext
    from alembic.script import ScriptDirectory

    current = MigrationContext.configure(connection).get_current_revision()
    target = context.get_revision_argument() or "base"  # None: to base
    if current is None or current < DATASETS or not isinstance(target, str):
        return False
    if target.startswith("-") and target[1:].isdigit():  # relative: step down from current
        script, rev = ScriptDirectory.from_config(config), current
        for _ in range(int(target[1:])):
            rev = script.get_revision(rev).down_revision if rev else None
        target = rev or "base"
    return target == "base" or target < DATASETS


def _refuse_unholdable_downgrade(connection) -> None:
    """A downgrade below DATASETS while jobs run on datasets is refused before any of
    its steps: their specs have no systems, which the older schema cannot hold (and
    SQLite commits each revision's DDL on its own, so a refusal inside 0008 would
    come after the later revisions had dropped their tables)."""
    import sqlalchemy as sa

    began = not connection.in_transaction()
    try:
        on_datasets = _below_datasets(connection) and connection.scalar(
            sa.text("SELECT count(*) FROM jobs WHERE dataset_id IS NOT NULL")
        )
    finally:
        if began and connection.in_transaction():  # read only: leave none open (the
            connection.rollback()  # foreign-key pragma below needs none)
    if on_datasets:
        raise RuntimeError(
            f"{on_datasets} job(s) run on uploaded datasets, which the schema before "
            f"{DATASETS} cannot hold: delete them (`svrobs delete JOB_ID`) before "
            "downgrading; nothing was changed"
        )


def _run(connection) -> None:
    _refuse_unholdable_downgrade(connection)
    if connection.dialect.name == "sqlite" and not connection.in_transaction():
        # batch mode rebuilds a table by copy, drop and rename: with foreign keys on,
        # dropping e.g. the old `jobs` would cascade-delete every row that refers to
        # it (Alembic's batch docs: turn them off; the pragma is a no-op in a transaction)
        connection.connection.dbapi_connection.execute("PRAGMA foreign_keys = OFF")
    context.configure(
        connection=connection,
        target_metadata=target_metadata,
        render_as_batch=connection.dialect.name == "sqlite",
    )
    with context.begin_transaction():
        context.run_migrations()


if context.is_offline_mode():
    run_migrations_offline()
else:
    run_migrations_online()
