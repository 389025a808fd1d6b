"""Smoothed poses are stored: the back end's final estimate of each frame, per session.

Revision ID: 0004
Revises: 0003
Create Date: 2026-12-02
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0004"
down_revision = "0003"
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.create_table(
        "smoothed_poses",
        sa.Column(
            "id",
            sa.BigInteger().with_variant(sa.Integer(), "sqlite"),
            primary_key=True,
            autoincrement=True,
        ),
        sa.Column(
            "session_id",
            sa.String(32),
            sa.ForeignKey("sessions.id", ondelete="CASCADE"),
            nullable=False,
        ),
        sa.Column("timestamp_ns", sa.BigInteger(), nullable=False),
        sa.Column("pose", sa.JSON(), nullable=False),
        sa.UniqueConstraint("session_id", "timestamp_ns", name="uq_smoothed_stamp"),
    )
    op.create_index("ix_smoothed_poses_session_id", "smoothed_poses", ["session_id"])


def downgrade() -> None:
    op.drop_index("ix_smoothed_poses_session_id", table_name="smoothed_poses")
    op.drop_table("smoothed_poses")
