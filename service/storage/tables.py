"""The tables as ORM classes: sessions (with their lease and resume state), every answered
pose, and the smoother's final poses.

The schema is owned by the Alembic migrations in ``service/migrations`` (run at start-up); the
classes below mirror it. Poses are stored as JSON lists of 16 floats: Python's float repr
round-trips float64 exactly, so a trajectory read back equals the one answered, bit for bit.
On PostgreSQL the columns are ``json`` (kept as written), not ``jsonb`` (which would turn -0.0
into 0); both backends are exercised live by tests/test_service_postgres.py.
"""

from __future__ import annotations

import datetime as dt
from typing import Any

from sqlalchemy import (
    JSON,
    BigInteger,
    Boolean,
    DateTime,
    ForeignKey,
    Integer,
    String,
    Text,
    UniqueConstraint,
)
from sqlalchemy.orm import DeclarativeBase, Mapped, mapped_column


class Base(DeclarativeBase):
    pass


class SessionRow(Base):
    __tablename__ = "sessions"

    id: Mapped[str] = mapped_column(String(32), primary_key=True)
    owner: Mapped[str] = mapped_column(String(64), index=True)
    name: Mapped[str] = mapped_column(String(200), default="")
    created_at: Mapped[dt.datetime] = mapped_column(DateTime(timezone=True))
    calibration: Mapped[dict[str, Any]] = mapped_column(JSON)
    config: Mapped[dict[str, Any]] = mapped_column(JSON)
    imu_noise: Mapped[dict[str, Any] | None] = mapped_column(JSON, nullable=True)
    image_width: Mapped[int] = mapped_column(Integer)
    image_height: Mapped[int] = mapped_column(Integer)
    frame_count: Mapped[int] = mapped_column(Integer, default=0)
    last_timestamp_ns: Mapped[int | None] = mapped_column(BigInteger, nullable=True)
    resume_count: Mapped[int] = mapped_column(Integer, default=0)
    # Ownership across replicas (service.lease): holder, expiry, and the fencing token that
    # rises at every change of holder (migration 0003).
    lease_holder: Mapped[str | None] = mapped_column(String(64), nullable=True)
    lease_expires_at: Mapped[dt.datetime | None] = mapped_column(
        DateTime(timezone=True), nullable=True
    )
    lease_token: Mapped[int] = mapped_column(BigInteger, default=0, server_default="0")
    # What the estimator needs to continue from the last stored pose (Odometry.state()).
    resume_state: Mapped[dict[str, Any] | None] = mapped_column(JSON, nullable=True)


class PoseRow(Base):
    __tablename__ = "poses"
    __table_args__ = (
        UniqueConstraint("session_id", "frame_index", name="uq_pose_frame"),
        # A resent frame gets the stored answer; a second pose for it is refused.
        UniqueConstraint("session_id", "timestamp_ns", name="uq_pose_timestamp"),
    )

    # 64-bit on PostgreSQL (migration 0002); SQLite's INTEGER PRIMARY KEY is its 64-bit rowid.
    id: Mapped[int] = mapped_column(
        BigInteger().with_variant(Integer, "sqlite"), primary_key=True, autoincrement=True
    )
    session_id: Mapped[str] = mapped_column(
        String(32), ForeignKey("sessions.id", ondelete="CASCADE"), index=True
    )
    frame_index: Mapped[int] = mapped_column(Integer)
    timestamp_ns: Mapped[int] = mapped_column(BigInteger)
    pose: Mapped[list[float]] = mapped_column(JSON)
    frontend_pose: Mapped[list[float]] = mapped_column(JSON)
    relative_pose: Mapped[list[float]] = mapped_column(JSON)
    status: Mapped[str] = mapped_column(String(16))
    matches: Mapped[int] = mapped_column(Integer, default=0)
    inliers: Mapped[int] = mapped_column(Integer, default=0)
    support: Mapped[int] = mapped_column(Integer, default=0)
    timings: Mapped[dict[str, float]] = mapped_column(JSON)
    message: Mapped[str] = mapped_column(Text, default="")
    resumed: Mapped[bool] = mapped_column(Boolean, default=False)
    # The lease token and replica the pose was written under (None without leases: SQLite).
    fence_token: Mapped[int | None] = mapped_column(BigInteger, nullable=True)
    writer: Mapped[str | None] = mapped_column(String(64), nullable=True)


class SmoothedPoseRow(Base):
    """The back end's final (smoothed) estimate of one frame, left camera in world."""

    __tablename__ = "smoothed_poses"
    __table_args__ = (
        UniqueConstraint("session_id", "timestamp_ns", name="uq_smoothed_stamp"),
    )

    id: Mapped[int] = mapped_column(
        BigInteger().with_variant(Integer, "sqlite"), primary_key=True, autoincrement=True
    )
    session_id: Mapped[str] = mapped_column(
        String(32), ForeignKey("sessions.id", ondelete="CASCADE"), index=True
    )
    timestamp_ns: Mapped[int] = mapped_column(BigInteger)
    pose: Mapped[list[float]] = mapped_column(JSON)


# A smoothed pose as answered: (timestamp_ns, row-major flat 4x4 left camera in world).
