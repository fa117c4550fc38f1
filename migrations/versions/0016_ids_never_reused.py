"""SQLite: the tables whose ids name a row elsewhere get AUTOINCREMENT, so an id is
never handed out twice (service.db.models.NEVER_REUSED); PostgreSQL: nothing to do

Revision ID: 0016
Revises: 0015
"""

from __future__ import annotations

from alembic import op

revision = "0016"
down_revision = "0015"
branch_labels = None
depends_on = None

TABLES = (
    "teams",
    "users",
    "api_keys",
    "schedules",
    "datasets",
    "jobs",
    "work_units",
    "schedule_runs",
    "share_links",
    "sessions",
)


def upgrade() -> None:
    if op.get_bind().dialect.name != "sqlite":
        return
    # each table is copied into one declared with AUTOINCREMENT; the copy's explicit
    # ids set sqlite_sequence to the largest, so the next id is above every id kept
    for name in TABLES:
        with op.batch_alter_table(
            name, recreate="always", table_kwargs={"sqlite_autoincrement": True}
        ):
            pass


def downgrade() -> None:
    # AUTOINCREMENT is kept: the older schema reads and writes these tables as before
    pass
