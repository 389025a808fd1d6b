"""What the live view is sent: poses as compact columns, and a session's activity.

A browser drawing ten thousand poses needs positions, a heading, the status and two numbers per
frame, not three 4x4 matrices and a timing table each; columns of rounded numbers are about a
tenth of the JSON of :class:`~service.answer.FrameAnswer`.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from sqlalchemy import Row, select

from estimator.geometry import invert_pose
from service.answer import FrameAnswer
from service.sessions import LiveSession
from service.storage import PoseRow, SessionRecord, Store
from service.web.watch_messages import Activity, PosesMessage, SmoothedMessage

# One letter per pose status in the ``status`` column.
STATUS_CODES: dict[str, str] = {"ok": "o", "degraded": "d", "lost": "l"}
# A session is live while its poses keep coming: no frame for this long and it is idle.
LIVE_WINDOW_S = 5.0



# Stages of a frame before its pose is stored: what the view plots as the service's latency.
LATENCY_STAGES = ("queue_wait", "decode", "odometry", "transfer")


@dataclass(frozen=True)
class WorldFrame:
    """How to look at a session's world, read from its first pose.

    The world is the first left camera (x right, y down, z forward) unless the back end levels
    it with the accelerometer (z up, yaw of the first body pose). A camera looking roughly
    level is never at the identity in a z-up world, so frame 0's rotation tells which. The
    vision-only poses always start at the first camera; ``frontend_to_world`` brings them into
    the same world as the real-time poses so both paths can be drawn together.
    """

    levelled: bool
    frontend_to_world: np.ndarray

    @classmethod
    def of(cls, first: FrameAnswer) -> WorldFrame:
        pose = np.array(first.pose, dtype=float).reshape(4, 4)
        frontend = np.array(first.frontend_pose, dtype=float).reshape(4, 4)
        levelled = not np.allclose(pose[:3, :3], np.eye(3), atol=1e-6)
        return cls(levelled, pose @ invert_pose(frontend))

    def axes(self) -> dict[str, Any]:
        """World axes (index, sign) across and up each view, and their labels."""
        # The side view looks along whichever horizontal axis the path spans least.
        if self.levelled:
            return {"up": "z", "top": [[0, 1], [1, 1]], "side": [[0, 1], [2, 1]],
                    "side_across": [[0, 1, "x →"], [1, 1, "y →"]],
                    "top_labels": ["x →", "y ↑"], "side_labels": ["x →", "z ↑ (up)"],
                    "note": "world levelled by the accelerometer: z up"}
        return {"up": "-y", "top": [[0, 1], [2, 1]], "side": [[2, 1], [1, -1]],
                "side_across": [[2, 1, "z →"], [0, 1, "x →"]],
                "top_labels": ["x →", "z ↑ (forward)"], "side_labels": ["z →", "−y ↑ (up)"],
                "note": "world = first left camera: x right, y down, z forward"}


# Where a pose's translation and optical axis sit in its row-major 4x4.
_TRANSLATION = (3, 7, 11)
_OPTICAL_AXIS = (2, 6, 10)


def read_poses(
    store: Store, session_id: str, start: int = 0, limit: int | None = None
) -> Sequence[Row[Any]]:
    """The numbers the view draws, from frame ``start`` on, picked out by the database.

    A long run's backlog is most of the time to first draw. The database's own JSON functions
    (``json_extract`` in SQLite, ``->>`` in PostgreSQL) take out the 13 numbers needed instead
    of Python decoding three JSON documents per pose: about three times faster.
    """
    query = (
        select(
            PoseRow.frame_index, PoseRow.timestamp_ns, PoseRow.status, PoseRow.inliers,
            PoseRow.message,
            *(PoseRow.pose[i].as_float() for i in _TRANSLATION + _OPTICAL_AXIS),
            *(PoseRow.frontend_pose[i].as_float() for i in _TRANSLATION),
            *(PoseRow.timings[stage].as_float() for stage in LATENCY_STAGES),
        )
        .where(PoseRow.session_id == session_id, PoseRow.frame_index >= start)
        .order_by(PoseRow.frame_index)
        .limit(limit)
    )
    with store.engine.connect() as connection:
        return connection.execute(query).all()


def pose_columns(rows: Sequence[Row[Any]], world: WorldFrame) -> PosesMessage:
    """A ``poses`` message of rows of :func:`read_poses`: one column per quantity."""
    numbers = np.array([row[5:] for row in rows], dtype=float).reshape(len(rows), 13)
    rotation, offset = world.frontend_to_world[:3, :3], world.frontend_to_world[:3, 3]
    frontend = numbers[:, 6:9] @ rotation.T + offset
    latency_ms = 1000.0 * np.nansum(numbers[:, 9:13], axis=1)  # a missing stage counts 0
    return PosesMessage(
        index=[row.frame_index for row in rows],
        timestamp_ns=[row.timestamp_ns for row in rows],
        # 0.1 mm is far below what a screen shows and keeps the numbers short.
        position=np.round(numbers[:, 0:3], 4).ravel().tolist(),
        frontend_position=np.round(frontend, 4).ravel().tolist(),
        # The camera's optical axis in the world: the heading drawn at the newest pose.
        forward=np.round(numbers[:, 3:6], 3).ravel().tolist(),
        status="".join(STATUS_CODES.get(row.status, "l") for row in rows),
        inliers=[row.inliers for row in rows],
        latency_ms=np.round(latency_ms, 2).tolist(),
        message=rows[-1].message if rows else "",
    )


def smoothed_columns(smoothed: Sequence[tuple[int, list[float]]]) -> SmoothedMessage:
    """A ``smoothed`` message: the smoother's final poses (timestamp, flat 4x4) as columns."""
    matrices = np.array([pose for _, pose in smoothed], dtype=float).reshape(-1, 16)
    return SmoothedMessage(
        timestamp_ns=[stamp for stamp, _ in smoothed],
        position=np.round(matrices[:, list(_TRANSLATION)], 4).ravel().tolist(),
    )


@dataclass(frozen=True)
class SessionActivity:
    """Whether frames are arriving on this server, and how fast."""

    activity: Activity
    frames_per_s: float | None
    last_update: float | None  # Unix time of the newest stored pose seen by this server
    queued: int

    @classmethod
    def of(cls, session: LiveSession | None, now: float | None = None) -> SessionActivity:
        """From the live session; a session without one received no frame recently."""
        if session is None:
            return cls("idle", None, None, 0)
        now = time.time() if now is None else now
        stamps = [t for t in session.stored_at if now - t <= LIVE_WINDOW_S]
        queued = session.queue.qsize() + int(session.busy)
        active = bool(stamps) or queued > 0
        rate = None
        if len(stamps) >= 2 and stamps[-1] > stamps[0]:
            rate = (len(stamps) - 1) / (stamps[-1] - stamps[0])
        elif active:
            rate = 0.0
        last = session.stored_at[-1] if session.stored_at else None
        return cls("live" if active else "idle", rate, last, queued)

    def as_json(self) -> dict[str, Any]:
        return {
            "activity": self.activity,
            "frames_per_s": None if self.frames_per_s is None else round(self.frames_per_s, 2),
            "last_update": self.last_update,
            "queued": self.queued,
        }


def session_summary(
    record: SessionRecord, live: LiveSession | None, last: FrameAnswer | None
) -> dict[str, Any]:
    """One row of the sessions list."""
    return {
        "id": record.id,
        "name": record.name,
        "created_at": record.created_at.isoformat(),
        "frame_count": record.frame_count if live is None else live.next_index,
        "last_timestamp_ns": record.last_timestamp_ns,
        "last_status": None if last is None else last.status,
        **SessionActivity.of(live).as_json(),
    }
