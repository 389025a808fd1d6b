"""Request and answer bodies of the HTTP API (they also document it in the OpenAPI schema)."""

from __future__ import annotations

import datetime as dt
from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, Strict

from service.answer import FrameAnswer, SmoothedPose, matrix_of
from service.settings import Executor
from service.storage import SessionRecord

# Strict: JSON numbers only (no booleans, no numeric strings).
TimestampNs = Annotated[int, Strict(), Field(ge=0, le=2**63 - 1, description="nanoseconds")]
Number = Annotated[float, Strict()]
Vector3 = tuple[Number, Number, Number]


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
        description="{'left': camera, 'right': camera, optional 'calibration_exact': bool (the "
        "calibration is the rig's true geometry, e.g. a rendered rig: no calibration error in the "
        "covariances reported without an IMU)}; camera = width, height, fx, fy, cx, cy, "
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


class SmoothedOut(BaseModel):
    """The back end's final estimates, oldest first (stored as the frames are finalised)."""

    session_id: str
    poses: list[SmoothedPose]

    @classmethod
    def of(cls, session_id: str, smoothed: list[tuple[int, list[float]]]) -> SmoothedOut:
        return cls(
            session_id=session_id,
            poses=[SmoothedPose(timestamp_ns=t, pose=matrix_of(p)) for t, p in smoothed],
        )


class TrajectoryOut(BaseModel):
    session_id: str
    poses: list[FrameAnswer]


class Health(BaseModel):
    status: Literal["ok"]
    sessions_active: int
    database: str
    executor: Executor  # where the odometry runs
    workers: int


class ErrorOut(BaseModel):
    detail: str
