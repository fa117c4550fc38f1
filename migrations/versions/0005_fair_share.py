"""fair share, cancel and schedules: jobs.cells_done, schedule_runs.skipped_reason

Revision ID: 0005
Revises: 0004
Create Date: 2026-12-01 09:45:00
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0005"
down_revision = "0004"
branch_labels = None
depends_on = None


def upgrade() -> None:
    with op.batch_alter_table("jobs", schema=None) as batch_op:
        batch_op.add_column(
            sa.Column("cells_done", sa.Integer(), nullable=False, server_default="0")
        )
    with op.batch_alter_table("schedule_runs", schema=None) as batch_op:
        batch_op.add_column(sa.Column("skipped_reason", sa.Text(), nullable=True))


def downgrade() -> None:
    with op.batch_alter_table("schedule_runs", schema=None) as batch_op:
        batch_op.drop_column("skipped_reason")
    with op.batch_alter_table("jobs", schema=None) as batch_op:
        batch_op.drop_column("cells_done")
