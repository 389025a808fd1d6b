"""Session ownership across replicas: a lease with a fencing token, and resumable state.

- ``sessions.lease_holder`` / ``lease_expires_at`` / ``lease_token``: the replica processing
  the session, until when, and a counter raised at every change of holder. Every pose write
  checks the token in the same transaction, so a replica that lost the lease cannot write.
- ``sessions.resume_state``: what the estimator needs to continue the session elsewhere.
- ``poses.fence_token`` / ``poses.writer``: the token and replica each pose was written under
  (audit: writes without the lease are visible in the data).
- ``uq_pose_timestamp``: one pose per session and timestamp (a resent frame is answered from
  the stored pose, never processed twice).

Revision ID: 0003
Revises: 0002
Create Date: 2026-12-02
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0003"
down_revision = "0002"
branch_labels = None
depends_on = None


def upgrade() -> None:
    with op.batch_alter_table("sessions") as table:
        table.add_column(sa.Column("lease_holder", sa.String(64), nullable=True))
        table.add_column(
            sa.Column("lease_expires_at", sa.DateTime(timezone=True), nullable=True)
        )
        table.add_column(
            sa.Column("lease_token", sa.BigInteger(), nullable=False, server_default="0")
        )
        table.add_column(sa.Column("resume_state", sa.JSON(), nullable=True))
    with op.batch_alter_table("poses") as table:
        table.add_column(sa.Column("fence_token", sa.BigInteger(), nullable=True))
        table.add_column(sa.Column("writer", sa.String(64), nullable=True))
        table.create_unique_constraint("uq_pose_timestamp", ["session_id", "timestamp_ns"])


def downgrade() -> None:
    with op.batch_alter_table("poses") as table:
        table.drop_constraint("uq_pose_timestamp", type_="unique")
        table.drop_column("writer")
        table.drop_column("fence_token")
    with op.batch_alter_table("sessions") as table:
        table.drop_column("resume_state")
        table.drop_column("lease_token")
        table.drop_column("lease_expires_at")
        table.drop_column("lease_holder")
