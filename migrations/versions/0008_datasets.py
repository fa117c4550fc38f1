"""datasets of measured rollouts: datasets, dataset_chunks, jobs.dataset_id

A dataset row holds an upload's shapes, channel names and statistics
(docs/datasets.md#the-data-model); ``dataset_chunks`` its original bytes and its
float64 arrays in pieces of at most 1 MiB; ``jobs.dataset_id`` the dataset a job
runs on (a foreign key without cascade: a dataset that jobs use is not deleted).
On SQLite the jobs table is rebuilt to add the foreign key (batch mode).

Revision ID: 0008
Revises: 0007
Create Date: 2026-12-01 14:00:00
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0008"
down_revision = "0007"
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.create_table(
        "datasets",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("team_id", sa.Integer(), nullable=False),
        sa.Column("user_id", sa.Integer(), nullable=True),
        sa.Column("name", sa.String(length=200), nullable=False),
        sa.Column("description", sa.Text(), nullable=True),
        sa.Column("filename", sa.String(length=255), nullable=True),
        sa.Column("format", sa.String(length=16), nullable=False),
        sa.Column("sha256", sa.String(length=64), nullable=False),
        sa.Column("arrays_sha256", sa.String(length=64), nullable=False),
        sa.Column("size_bytes", sa.BigInteger(), nullable=False),
        sa.Column("n", sa.Integer(), nullable=False),
        sa.Column("m", sa.Integer(), nullable=False),
        sa.Column("rollouts", sa.Integer(), nullable=False),
        sa.Column("samples", sa.BigInteger(), nullable=False),
        sa.Column("t_min", sa.Integer(), nullable=False),
        sa.Column("t_max", sa.Integer(), nullable=False),
        sa.Column("lengths", sa.JSON(), nullable=False),
        sa.Column("sample_time", sa.Float(), nullable=True),
        sa.Column("state_names", sa.JSON(), nullable=False),
        sa.Column("input_names", sa.JSON(), nullable=False),
        sa.Column("stats", sa.JSON(), nullable=False),
        sa.Column("created_at", sa.DateTime(timezone=True), nullable=False),
        sa.ForeignKeyConstraint(["team_id"], ["teams.id"], ondelete="CASCADE"),
        sa.ForeignKeyConstraint(["user_id"], ["users.id"], ondelete="SET NULL"),
        sa.PrimaryKeyConstraint("id"),
    )
    op.create_index("ix_datasets_team_created", "datasets", ["team_id", "created_at"])
    op.create_table(
        "dataset_chunks",
        sa.Column("dataset_id", sa.Integer(), nullable=False),
        sa.Column("part", sa.String(length=8), nullable=False),
        sa.Column("seq", sa.Integer(), nullable=False),
        sa.Column("data", sa.LargeBinary(), nullable=False),
        sa.ForeignKeyConstraint(["dataset_id"], ["datasets.id"], ondelete="CASCADE"),
        sa.PrimaryKeyConstraint("dataset_id", "part", "seq"),
    )
    with op.batch_alter_table("jobs", schema=None) as batch_op:
        batch_op.add_column(sa.Column("dataset_id", sa.Integer(), nullable=True))
        batch_op.create_index(batch_op.f("ix_jobs_dataset_id"), ["dataset_id"], unique=False)
        batch_op.create_foreign_key("fk_jobs_dataset_id", "datasets", ["dataset_id"], ["id"])


def downgrade() -> None:
    # jobs on datasets are refused before any downgrade step (migrations/env.py)
    with op.batch_alter_table("jobs", schema=None) as batch_op:
        batch_op.drop_constraint("fk_jobs_dataset_id", type_="foreignkey")
        batch_op.drop_index(batch_op.f("ix_jobs_dataset_id"))
        batch_op.drop_column("dataset_id")
    op.drop_table("dataset_chunks")
    op.drop_index("ix_datasets_team_created", table_name="datasets")
    op.drop_table("datasets")
