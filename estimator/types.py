"""Data that flows between the stages: frames in, IMU in, one report per frame out.

These are the contracts between the front end, the back end, the CLI and the service.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import StrEnum

import numpy as np


@dataclass(frozen=True)
class StereoFrame:
    """One synchronised stereo pair as the cameras deliver it (not yet rectified)."""

    timestamp_ns: int
    left: np.ndarray  # (H, W) uint8/uint16 grey or (H, W, 3) colour
    right: np.ndarray


@dataclass(frozen=True)
class ImuBatch:
    """IMU samples (body frame, as EuRoC's imu0): gyro in rad/s, accel in m/s^2."""

    timestamps_ns: np.ndarray  # (M,) int64, increasing
    gyro: np.ndarray  # (M, 3)
    accel: np.ndarray  # (M, 3)

    def __len__(self) -> int:
        return len(self.timestamps_ns)

    @staticmethod
    def empty() -> ImuBatch:
        return ImuBatch(np.zeros(0, dtype=np.int64), np.zeros((0, 3)), np.zeros((0, 3)))

    def between(self, start_ns: int, end_ns: int) -> ImuBatch:
        """Samples with start_ns < t <= end_ns."""
        mask = (self.timestamps_ns > start_ns) & (self.timestamps_ns <= end_ns)
        return ImuBatch(self.timestamps_ns[mask], self.gyro[mask], self.accel[mask])


@dataclass(frozen=True)
class ImuNoise:
    """Continuous-time IMU noise, as in EuRoC's imu0/sensor.yaml."""

    gyro_noise_density: float = 1.6968e-4  # rad/s/sqrt(Hz)
    gyro_random_walk: float = 1.9393e-5  # rad/s^2/sqrt(Hz)
    accel_noise_density: float = 2.0e-3  # m/s^2/sqrt(Hz)
    accel_random_walk: float = 3.0e-3  # m/s^3/sqrt(Hz)
    rate_hz: float = 200.0


class TimestampOrderError(ValueError):
    """A frame whose timestamp does not come after the previous frame's."""


def check_timestamp_order(timestamp_ns: int, last_ns: int | None) -> None:
    """Frames come in strictly increasing time: the IMU windows and the smoother rely on it."""
    if last_ns is not None and timestamp_ns <= last_ns:
        raise TimestampOrderError(
            f"timestamp_ns {timestamp_ns} does not increase: the last frame is at {last_ns} "
            "(frame timestamps must increase)"
        )


class FrameStatus(StrEnum):
    OK = "ok"  # vision gave an accepted relative pose
    DEGRADED = "degraded"  # vision failed, pose advanced from IMU / motion prior
    LOST = "lost"  # vision failed and nothing else could carry the pose


@dataclass
class FrameReport:
    """What the pipeline answers for each frame.

    Poses are 4x4 left-camera-to-world transforms (world = first left-camera pose unless the
    back end gravity-aligns it). ``relative_pose`` maps points of the current left camera into
    the previous one (T_prev_cur), so ``pose = previous_pose @ relative_pose`` (paper eq. 2).
    """

    index: int
    timestamp_ns: int
    pose: np.ndarray  # fused pose when the back end runs, else the front-end pose
    frontend_pose: np.ndarray  # chained front-end pose
    relative_pose: np.ndarray  # front-end T_prev_cur (identity on the first frame)
    status: FrameStatus
    matches: int = 0  # 3D-3D correspondences handed to the estimator
    inliers: int = 0
    support: int = 0
    timings_s: dict[str, float] = field(default_factory=dict)
    message: str = ""
    # Earlier frames the back end's smoother has finished with at this frame, each once:
    # (timestamp_ns, left camera pose) with its final, smoothed estimate.
    final_poses: tuple[tuple[int, np.ndarray], ...] = ()
    # Uncertainty, for the odometry message (``estimator.formats.odometry_msg``). Covariances are
    # 6x6 in GTSAM's tangent order (rotation, translation), right perturbation:
    # the front end's T_ref_cur (left camera frame) against the frame stamped
    # ``reference_timestamp_ns``, floored as the back end uses it (the refinement's robust
    # sandwich with ``registration.refine_covariance`` "sandwich-reported", the default, while
    # the back end weighs the median-scaled one; None when it failed);
    measurement_covariance: np.ndarray | None = None
    reference_timestamp_ns: int | None = None
    # with the back end, the marginals of the fused body (IMU) pose and of the body motion
    # T_prev_cur from the previous frame, with that motion as estimated now.
    body_covariance: np.ndarray | None = None
    body_motion: np.ndarray | None = None
    body_motion_covariance: np.ndarray | None = None
    # Per-session factor on the reported covariances, measured online against the gyro
    # (``estimator.backend.covariance_scale``); 1 without an IMU or the back end.
    covariance_scale: float = 1.0
    # The factor on the pose covariance's growth: at least the one above, raised through episodes.
    pose_covariance_scale: float = 1.0
