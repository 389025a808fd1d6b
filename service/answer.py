"""The answer to one frame, from the worker that computes it to the client that reads it.

Pydantic only (no server imports), so storage, the routes, the stream messages and the worker
processes all share it.
"""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, Field

Matrix4 = list[list[float]]


def matrix_of(flat: list[float]) -> Matrix4:
    """A row-major 4x4 from its 16 values (how storage keeps a pose)."""
    return [flat[0:4], flat[4:8], flat[8:12], flat[12:16]]


def flat_of(matrix: Matrix4) -> list[float]:
    """The 16 row-major values of a 4x4 (how storage keeps a pose)."""
    return [float(v) for row in matrix for v in row]


class Header(BaseModel):
    stamp_ns: int = Field(description="frame timestamp, ns (ROS: sec = ns // 1e9, nanosec)")
    frame_id: str = Field(description="'odom'")


class Point(BaseModel):
    x: float
    y: float
    z: float


class Quaternion(BaseModel):
    x: float
    y: float
    z: float
    w: float


class PoseInOdom(BaseModel):
    position: Point = Field(description="base_link origin in odom, m")
    orientation: Quaternion = Field(description="base_link orientation in odom")


class PoseWithCovariance(BaseModel):
    pose: PoseInOdom
    covariance: list[float] = Field(
        min_length=36, max_length=36,
        description="6x6 row-major: x, y, z, rotation about odom X, Y, Z (m^2, rad^2)",
    )


class Twist(BaseModel):
    linear: Point = Field(description="m/s in base_link")
    angular: Point = Field(description="rad/s in base_link")


class TwistWithCovariance(BaseModel):
    twist: Twist
    covariance: list[float] = Field(
        min_length=36, max_length=36, description="6x6 row-major: vx, vy, vz, wx, wy, wz"
    )


class OdometryOut(BaseModel):
    """nav_msgs/Odometry of one frame: base_link (the body/IMU frame, the left camera on a rig
    without T_BS) in odom (the first body pose, levelled with gravity when IMU samples came
    with the first frame); covariances never zero (docs/robot-integration.md)."""

    header: Header
    child_frame_id: str = Field(description="'base_link'")
    pose: PoseWithCovariance
    twist: TwistWithCovariance
    status: Literal["ok", "degraded", "lost"]
    camera_pose: list[float] = Field(
        min_length=16, max_length=16, description="left camera in odom, 4x4 row-major"
    )


class SmoothedPose(BaseModel):
    timestamp_ns: int
    pose: Matrix4 = Field(description="final smoothed left camera in world, row-major")


class FrameAnswer(BaseModel):
    """One answered frame; poses are 4x4 left-camera-to-world, row-major.

    The only shape of a frame's answer: the worker builds it, the session completes it, storage
    keeps it (``storage.PoseRow``, without the live-only fields) and REST and the stream send it.
    """

    session_id: str
    index: int
    timestamp_ns: int
    pose: Matrix4 = Field(description="fused pose (back end), left camera in world")
    frontend_pose: Matrix4
    relative_pose: Matrix4 = Field(description="front end T_prev_cur")
    status: Literal["ok", "degraded", "lost"]
    matches: int
    inliers: int
    support: int
    timings_s: dict[str, float] = Field(
        description="queue_wait, decode, odometry (and its stages), persist, total"
    )
    message: str
    resumed: bool = Field(description="the estimator restarted from the last stored pose")
    imu_samples: int = Field(0, description="IMU samples used for this frame")
    odometry: OdometryOut | None = Field(
        None, description="the frame in the robotics convention (live answers only)"
    )
    smoothed: list[SmoothedPose] = Field(
        default_factory=list,
        description="earlier frames the back end's smoother finished with at this frame, each "
        "once, with their final estimate (live answers only)",
    )
