"""results: bounds_method and the radius matrices radii_A, radii_B (docs/uncertainty.md)

Revision ID: 0002
Revises: 0001
Create Date: 2026-12-01 09:30:00
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0002"
down_revision = "0001"
branch_labels = None
depends_on = None


def upgrade() -> None:
    with op.batch_alter_table("results", schema=None) as batch_op:
        batch_op.add_column(sa.Column("bounds_method", sa.String(length=32), nullable=True))
        batch_op.add_column(sa.Column("radii_A", sa.JSON(), nullable=True))
        batch_op.add_column(sa.Column("radii_B", sa.JSON(), nullable=True))


def downgrade() -> None:
    with op.batch_alter_table("results", schema=None) as batch_op:
        batch_op.drop_column("radii_B")
        batch_op.drop_column("radii_A")
        batch_op.drop_column("bounds_method")
