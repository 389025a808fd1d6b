"""Request and answer bodies of the HTTP API (they also document it in the OpenAPI schema)."""

from __future__ import annotations

import datetime as dt
from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, Strict

from service.settings import Executor
from service.storage import PoseRecord, SessionRecord

# Strict: JSON numbers only (no booleans, no numeric strings).
TimestampNs = Annotated[int, Strict(), Field(ge=0, le=2**63 - 1, description="nanoseconds")]
Number = Annotated[float, Strict()]
Vector3 = tuple[Number, Number, Number]
Matrix4 = list[list[float]]


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)


class ImuSample(_Strict):
    timestamp_ns: TimestampNs
    gyro: Vector3 = Field(description="angular rate, rad/s, IMU/body frame")
    accel: Vector3 = Field(description="specific force, m/s^2, IMU/body frame")


class ImuBatchIn(_Strict):
    samples: list[ImuSample]


class ImuBatchOut(BaseModel):
    accepted: int
    buffered: int = Field(description="samples waiting for the next frames")


class ImuNoiseIn(_Strict):
    """Continuous-time IMU noise (EuRoC imu0/sensor.yaml terms)."""

    gyro_noise_density: float = Field(1.6968e-4, ge=0)
    gyro_random_walk: float = Field(1.9393e-5, ge=0)
    accel_noise_density: float = Field(2.0e-3, ge=0)
    accel_random_walk: float = Field(3.0e-3, ge=0)
    rate_hz: float = Field(200.0, gt=0)


class SessionCreate(_Strict):
    """A session from the plain calibration form (what ``StereoRig.to_dict`` writes)."""

    # No NUL: database text types cannot store it (PostgreSQL refuses it outright).
    name: str = Field("", max_length=200, pattern=r"^[^\x00]*$")
    calibration: dict[str, Any] = Field(
        description="{'left': camera, 'right': camera}; camera = width, height, fx, fy, cx, cy, "
        "distortion_model (radtan|equidistant|none), distortion, T_BS (4x4 camera->body)"
    )
    config: dict[str, Any] = Field(
        default_factory=dict, description="SwarmvoConfig overrides, e.g. {'seed': 3}"
    )
    imu_noise: ImuNoiseIn | None = None
    frame_rate_hz: float | None = Field(
        None, gt=0, le=10_000,
        description="camera frame rate; with it the frame-interval settings (search window) "
        "are derived at creation, without it from the first two frames' stamps. The settings "
        "derived from the rig are recorded in the session's config under 'rig_settings'",
    )


class SessionOut(BaseModel):
    id: str
    name: str
    created_at: dt.datetime
    image_width: int
    image_height: int
    frame_count: int
    last_timestamp_ns: int | None
    resume_count: int = Field(description="times the estimator restarted from a stored pose")
    calibration: dict[str, Any]
    config: dict[str, Any]
    imu_noise: dict[str, Any] | None

    @classmethod
    def of(cls, record: SessionRecord) -> SessionOut:
        return cls(
            id=record.id,
            name=record.name,
            created_at=record.created_at,
            image_width=record.image_width,
            image_height=record.image_height,
            frame_count=record.frame_count,
            last_timestamp_ns=record.last_timestamp_ns,
            resume_count=record.resume_count,
            calibration=record.calibration,
            config=record.config,
            imu_noise=record.imu_noise,
        )


class SessionList(BaseModel):
    sessions: list[SessionOut]


def _matrix(flat: list[float]) -> Matrix4:
    return [flat[0:4], flat[4:8], flat[8:12], flat[12:16]]


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


class PoseOut(BaseModel):
    """One answered frame; poses are 4x4 left-camera-to-world, row-major."""

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

    @classmethod
    def of(
        cls,
        session_id: str,
        record: PoseRecord,
        imu_samples: int = 0,
        odometry: dict[str, Any] | None = None,
        smoothed: list[tuple[int, list[float]]] | None = None,
    ) -> PoseOut:
        return cls(
            session_id=session_id,
            index=record.frame_index,
            timestamp_ns=record.timestamp_ns,
            pose=_matrix(record.pose),
            frontend_pose=_matrix(record.frontend_pose),
            relative_pose=_matrix(record.relative_pose),
            status=record.status,  # type: ignore[arg-type]
            matches=record.matches,
            inliers=record.inliers,
            support=record.support,
            timings_s=record.timings,
            message=record.message,
            resumed=record.resumed,
            imu_samples=imu_samples,
            odometry=OdometryOut.model_validate(odometry) if odometry is not None else None,
            smoothed=[
                SmoothedPose(timestamp_ns=stamp, pose=_matrix(pose))
                for stamp, pose in smoothed or ()
            ],
        )


class SmoothedOut(BaseModel):
    """The back end's final estimates, oldest first (stored as the frames are finalised)."""

    session_id: str
    poses: list[SmoothedPose]

    @classmethod
    def of(cls, session_id: str, smoothed: list[tuple[int, list[float]]]) -> SmoothedOut:
        return cls(
            session_id=session_id,
            poses=[SmoothedPose(timestamp_ns=t, pose=_matrix(p)) for t, p in smoothed],
        )


class TrajectoryOut(BaseModel):
    session_id: str
    poses: list[PoseOut]


class Health(BaseModel):
    status: Literal["ok"]
    sessions_active: int
    database: str
    executor: Executor  # where the odometry runs
    workers: int


class ErrorOut(BaseModel):
    detail: str
