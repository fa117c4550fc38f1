"""reads: team retention, pruned jobs, stored reports, spec summaries

Revision ID: 0004
Revises: 0003
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0004"
down_revision = "0003"
branch_labels = None
depends_on = None


def upgrade() -> None:
    with op.batch_alter_table("teams", schema=None) as batch_op:
        batch_op.add_column(sa.Column("retention_days", sa.Integer(), nullable=True))
    with op.batch_alter_table("jobs", schema=None) as batch_op:
        batch_op.add_column(sa.Column("pruned_at", sa.DateTime(timezone=True), nullable=True))
        batch_op.add_column(sa.Column("spec_summary", sa.JSON(), nullable=True))
    op.create_table(
        "job_reports",
        sa.Column("job_id", sa.Integer(), nullable=False),
        sa.Column("html", sa.Text(), nullable=False),
        sa.Column("n_records", sa.Integer(), nullable=False),
        sa.Column("built_at", sa.DateTime(timezone=True), nullable=False),
        sa.ForeignKeyConstraint(["job_id"], ["jobs.id"], ondelete="CASCADE"),
        sa.PrimaryKeyConstraint("job_id"),
    )


def downgrade() -> None:
    op.drop_table("job_reports")
    with op.batch_alter_table("jobs", schema=None) as batch_op:
        batch_op.drop_column("spec_summary")
        batch_op.drop_column("pruned_at")
    with op.batch_alter_table("teams", schema=None) as batch_op:
        batch_op.drop_column("retention_days")
