"""The outlier gate: does a front-end relative pose agree with what the IMU and the constant
velocity predict (and, during the start-up rest, with a standstill)?"""

from __future__ import annotations

import gtsam
import numpy as np

from estimator.backend.imu import GyroPreintegration
from estimator.config import BackendConfig
from estimator.geometry import invert_pose

__all__ = ["agrees_with_standstill", "gate_distance"]

# Rotation spread added to the gyro prediction in the outlier gate: covers an unconverged gyro
# bias (0.1 rad/s over the frame interval, at least 50 ms) and small camera-IMU misalignment.
_GATE_GYRO_FLOOR_RAD = 0.005
_GATE_GYRO_BIAS_RATE = 0.1  # rad/s
# A relative pose within this squared Mahalanobis distance of the identity (6 DOF, 99.9 %)
# agrees with a standstill.
_STILL_CHI2 = 22.46


def agrees_with_standstill(body_motion: np.ndarray, covariance: np.ndarray) -> bool:
    """Whether a measured body motion is within its noise of no motion at all."""
    moved = gtsam.Pose3.Logmap(gtsam.Pose3(body_motion))
    return float(moved @ np.linalg.solve(covariance, moved)) <= _STILL_CHI2


def gate_distance(
    measured: np.ndarray,
    predicted: np.ndarray,
    covariance: np.ndarray,
    preintegration: GyroPreintegration | None,
    dt: float,
    since_fix_s: float,
    previous_motion: np.ndarray | None,
    previous_dt: float,
    config: BackendConfig,
) -> float:
    """Squared Mahalanobis distance of a relative pose from the prediction.

    The error is Log(predicted^-1 measured) with the measurement's 6x6 covariance plus the
    prediction's spread: the gyro covariance plus a floor for the bias uncertainty (else
    the constant-velocity sigma) for rotation, the constant-velocity sigma for
    translation; the motion-prior parts widen with the time since the last accepted vision
    (``since_fix_s`` before the previous frame, plus ``dt``) against the previous frame
    interval (a long gap extrapolates just as far, whether frames were missed or never came),
    so the gate reopens after a gap.
    """
    if previous_motion is None and preintegration is None:
        return 0.0  # nothing to compare with yet
    elapsed = since_fix_s + dt
    widen = max(1.0, elapsed / previous_dt) ** 2 if previous_dt > 0 else 1.0
    error = gtsam.Pose3.Logmap(gtsam.Pose3(invert_pose(predicted) @ measured))
    spread = covariance.copy()
    if preintegration is not None:
        floor = max(_GATE_GYRO_FLOOR_RAD, _GATE_GYRO_BIAS_RATE * dt)
        spread[:3, :3] += preintegration.covariance + np.eye(3) * floor**2
    else:
        spread[:3, :3] += np.eye(3) * config.cv_rotation_sigma_rad**2 * widen
    if previous_motion is None:  # no translation to compare with yet
        return float(error[:3] @ np.linalg.solve(spread[:3, :3], error[:3]))
    spread[3:, 3:] += np.eye(3) * config.cv_translation_sigma_m**2 * widen
    return float(error @ np.linalg.solve(spread, error))
