"""Pose ids are 64-bit on PostgreSQL: a busy service outgrows 2^31 stored poses.

SQLite's INTEGER PRIMARY KEY is already the 64-bit rowid, so nothing changes there.

Revision ID: 0002
Revises: 0001
Create Date: 2026-12-01
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0002"
down_revision = "0001"
branch_labels = None
depends_on = None


def upgrade() -> None:
    if op.get_bind().dialect.name != "postgresql":
        return
    op.alter_column("poses", "id", type_=sa.BigInteger(), existing_type=sa.Integer())
    op.execute("ALTER SEQUENCE IF EXISTS poses_id_seq AS BIGINT")


def downgrade() -> None:
    if op.get_bind().dialect.name != "postgresql":
        return
    op.execute("ALTER SEQUENCE IF EXISTS poses_id_seq AS INTEGER")
    op.alter_column("poses", "id", type_=sa.Integer(), existing_type=sa.BigInteger())
