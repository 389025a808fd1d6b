"""What the store hands out and takes in: sessions, poses waiting to be written with their
writer's lease, and the conversions between answers and rows."""

from __future__ import annotations

import datetime as dt
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

from sqlalchemy import func

from service.answer import FrameAnswer, flat_of, matrix_of
from service.storage.tables import PoseRow, SessionRow


class LeaseLost(Exception):
    """A pose write by a replica whose lease token is no longer the session's."""


@dataclass(frozen=True)
class Fence:
    """A writer's lease: its holder id, fencing token and how long a write renews it for."""

    holder: str
    token: int
    ttl_s: float

    def expiry(self) -> Any:
        """The new expiry on the database's clock (replicas' clocks never enter the lease)."""
        return func.now() + dt.timedelta(seconds=self.ttl_s)


SmoothedPose = tuple[int, list[float]]


@dataclass(frozen=True)
class SessionRecord:
    id: str
    owner: str
    name: str
    created_at: dt.datetime
    calibration: dict[str, Any]
    config: dict[str, Any]
    imu_noise: dict[str, Any] | None
    image_width: int
    image_height: int
    frame_count: int
    last_timestamp_ns: int | None
    resume_count: int


@dataclass(frozen=True)
class PendingPose:
    """One answered frame waiting to be stored, with the writer's lease and resume state."""

    answer: FrameAnswer
    fence: Fence | None = None
    resume_state: dict[str, Any] | None = None
    smoothed: Sequence[SmoothedPose] = ()  # the back end's poses finalised at this frame

    @property
    def session_id(self) -> str:
        return self.answer.session_id


def session_record(row: SessionRow) -> SessionRecord:
    created = row.created_at
    if created.tzinfo is None:  # SQLite drops the zone; everything is stored in UTC
        created = created.replace(tzinfo=dt.UTC)
    else:  # PostgreSQL answers in its session time zone: the API speaks UTC on every backend
        created = created.astimezone(dt.UTC)
    return SessionRecord(
        id=row.id,
        owner=row.owner,
        name=row.name,
        created_at=created,
        calibration=row.calibration,
        config=row.config,
        imu_noise=row.imu_noise,
        image_width=row.image_width,
        image_height=row.image_height,
        frame_count=row.frame_count,
        last_timestamp_ns=row.last_timestamp_ns,
        resume_count=row.resume_count,
    )


def answer_of(session_id: str, row: PoseRow) -> FrameAnswer:
    """A stored row as the frame's answer (the live-only fields stay at their defaults)."""
    return FrameAnswer(
        session_id=session_id,
        index=row.frame_index,
        timestamp_ns=row.timestamp_ns,
        pose=matrix_of(row.pose),
        frontend_pose=matrix_of(row.frontend_pose),
        relative_pose=matrix_of(row.relative_pose),
        status=row.status,
        matches=row.matches,
        inliers=row.inliers,
        support=row.support,
        timings_s=row.timings,
        message=row.message,
        resumed=row.resumed,
    )


def row_values(answer: FrameAnswer, fence: Fence | None = None) -> dict[str, Any]:
    """What storage keeps of an answer, as the pose table's column values: everything but the
    live-only fields, with the lease it was written under."""
    return {
        "session_id": answer.session_id,
        "frame_index": answer.index,
        "timestamp_ns": answer.timestamp_ns,
        "pose": flat_of(answer.pose),
        "frontend_pose": flat_of(answer.frontend_pose),
        "relative_pose": flat_of(answer.relative_pose),
        "status": answer.status,
        "matches": answer.matches,
        "inliers": answer.inliers,
        "support": answer.support,
        "timings": answer.timings_s,
        "message": answer.message,
        "resumed": answer.resumed,
        "fence_token": None if fence is None else fence.token,
        "writer": None if fence is None else fence.holder,
    }
