"""The constant-velocity motion prior: the previous estimated motion, rescaled to this frame
interval, as a loose factor X_k-1 -> X_k on frames without an accepted relative pose (or on
every frame with ``motion_prior="always"``); with the gyro present its rotation part is left
free so it cannot bend the bias."""

from __future__ import annotations

import gtsam
import numpy as np

from estimator.backend.noise import pose_noise
from estimator.backend.smoother import pose_key
from estimator.backend.step import Step
from estimator.config import BackendConfig

__all__ = ["add_motion_prior", "constant_velocity"]

# Rotation sigma of the motion prior when the gyro provides the rotation (effectively free).
_FREE_ROTATION_SIGMA = 10.0


def constant_velocity(
    previous_motion: np.ndarray | None, previous_dt: float, dt: float
) -> np.ndarray:
    """Constant body twist: the previous motion rescaled to this frame interval."""
    if previous_motion is None:
        return np.eye(4)
    twist = gtsam.Pose3.Logmap(gtsam.Pose3(previous_motion))
    return gtsam.Pose3.Expmap(twist * (dt / previous_dt)).matrix()


def add_motion_prior(step: Step, motion: np.ndarray, config: BackendConfig) -> None:
    """Constant-velocity prior from the previous frame (loose)."""
    # With the gyro the prior carries translation only: its rotation part would
    # otherwise leak into the bias estimate.
    rotation_sigma = (
        _FREE_ROTATION_SIGMA if step.preintegration is not None else config.cv_rotation_sigma_rad
    )
    step.factors.add(
        gtsam.BetweenFactorPose3(
            pose_key(step.previous),
            pose_key(step.current),
            gtsam.Pose3(motion),
            pose_noise(rotation_sigma, config.cv_translation_sigma_m),
        )
    )
