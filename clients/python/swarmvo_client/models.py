"""Typed views of the server's answers."""

from __future__ import annotations

import datetime as dt
from dataclasses import dataclass, field
from typing import Any

import numpy as np


@dataclass(frozen=True)
class Session:
    id: str
    name: str
    created_at: dt.datetime
    image_width: int
    image_height: int
    frame_count: int
    last_timestamp_ns: int | None
    resume_count: int
    calibration: dict[str, Any]
    config: dict[str, Any]
    imu_noise: dict[str, Any] | None

    @classmethod
    def from_json(cls, data: dict[str, Any]) -> Session:
        return cls(
            id=data["id"],
            name=data["name"],
            created_at=dt.datetime.fromisoformat(data["created_at"]),
            image_width=int(data["image_width"]),
            image_height=int(data["image_height"]),
            frame_count=int(data["frame_count"]),
            last_timestamp_ns=data.get("last_timestamp_ns"),
            resume_count=int(data.get("resume_count", 0)),
            calibration=data["calibration"],
            config=data["config"],
            imu_noise=data.get("imu_noise"),
        )


@dataclass(frozen=True)
class Pose:
    """One answered frame; 4x4 left-camera-to-world poses."""

    session_id: str
    index: int
    timestamp_ns: int
    pose: np.ndarray
    frontend_pose: np.ndarray
    relative_pose: np.ndarray
    status: str
    matches: int
    inliers: int
    support: int
    timings_s: dict[str, float]
    message: str
    resumed: bool
    imu_samples: int = 0
    # The frame in the robotics convention (nav_msgs/Odometry layout: header, child_frame_id,
    # pose.pose/covariance, twist.twist/covariance, status, camera_pose); None when the server
    # did not send it (stored trajectories).
    odometry: dict[str, Any] | None = None
    # Earlier frames the server's smoother finished with at this frame: (timestamp_ns, 4x4
    # final left-camera pose), each frame once.
    smoothed: tuple[tuple[int, np.ndarray], ...] = ()

    @classmethod
    def from_json(cls, data: dict[str, Any]) -> Pose:
        return cls(
            session_id=data["session_id"],
            index=int(data["index"]),
            timestamp_ns=int(data["timestamp_ns"]),
            pose=np.array(data["pose"], dtype=float),
            frontend_pose=np.array(data["frontend_pose"], dtype=float),
            relative_pose=np.array(data["relative_pose"], dtype=float),
            status=data["status"],
            matches=int(data["matches"]),
            inliers=int(data["inliers"]),
            support=int(data["support"]),
            timings_s=dict(data.get("timings_s", {})),
            message=data.get("message", ""),
            resumed=bool(data.get("resumed", False)),
            imu_samples=int(data.get("imu_samples", 0)),
            odometry=data.get("odometry"),
            smoothed=tuple(
                (int(item["timestamp_ns"]), np.array(item["pose"], dtype=float))
                for item in data.get("smoothed", ())
            ),
        )


@dataclass(frozen=True)
class DroppedFrame:
    """The server discarded this queued frame for a newer one (policy ``drop_oldest``)."""

    timestamp_ns: int
    detail: str


@dataclass(frozen=True)
class RejectedFrame:
    """The server refused this frame (queue full, bad image, timestamp order, ...)."""

    timestamp_ns: int | None
    status: int
    detail: str


@dataclass
class ImuData:
    """IMU samples: timestamps (N,) ns, gyro (N, 3) rad/s, accel (N, 3) m/s^2."""

    timestamps_ns: np.ndarray
    gyro: np.ndarray
    accel: np.ndarray
    extra: dict[str, Any] = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.timestamps_ns)

    def between(self, start_ns: int | None, end_ns: int) -> ImuData:
        """Samples with start_ns < t <= end_ns (all up to end_ns when start_ns is None)."""
        mask = self.timestamps_ns <= end_ns
        if start_ns is not None:
            mask &= self.timestamps_ns > start_ns
        return ImuData(self.timestamps_ns[mask], self.gyro[mask], self.accel[mask])

    def to_samples(self) -> list[dict[str, Any]]:
        """The JSON form the server reads (exact float64 through Python's float repr)."""
        return [
            {
                "timestamp_ns": int(t),
                "gyro": [float(v) for v in g],
                "accel": [float(v) for v in a],
            }
            for t, g, a in zip(self.timestamps_ns, self.gyro, self.accel, strict=True)
        ]
