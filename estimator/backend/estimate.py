"""The back end's answer for one frame, and the checks on the poses it is given."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from estimator.types import FrameStatus

__all__ = ["FusedEstimate", "check_pose"]


@dataclass(frozen=True)
class FusedEstimate:
    """The back end's answer for one frame."""

    pose: np.ndarray  # (4, 4) left camera in world
    body_pose: np.ndarray  # (4, 4) body (IMU) in world
    status: FrameStatus
    message: str = ""
    gyro_bias: np.ndarray | None = None  # (3,) rad/s, current estimate (None without IMU)
    # Body motion T_prev_cur as estimated now (the previous pose is revised too, so this is
    # smoother than the difference of two consecutive ``body_pose`` outputs).
    body_motion: np.ndarray | None = None
    # Earlier frames the smoother has finished with at this frame: (timestamp_ns, left camera
    # pose in world) with their final, smoothed estimate; each frame appears once.
    final_poses: tuple[tuple[int, np.ndarray], ...] = ()
    # With the accelerometer: world gravity (m/s^2) and accelerometer bias, current estimates.
    gravity: np.ndarray | None = None
    accel_bias: np.ndarray | None = None
    # Marginal covariances (GTSAM tangent: rotation then translation, right perturbation in
    # the body frame) of ``body_pose`` and of ``body_motion``, from the smoother's Bayes tree;
    # with the IMU the pose's is widened for the keyframe-shared error the graph does not
    # model (``systematic_noise.shared_error_growth``).
    body_covariance: np.ndarray | None = None
    body_motion_covariance: np.ndarray | None = None
    # The frame's relative pose failed the outlier gate: the front end must not learn from it
    # (noise level, reference frame) either.
    vision_rejected: bool = False
    # Factor on the covariances reported for this frame, measured against the gyro
    # (``covariance_scale.py``; 1 without an IMU). The graph's own noise does not use it.
    covariance_scale: float = 1.0
    pose_covariance_scale: float = 1.0  # the pose's growth: raised through episodes as well


_EYE3 = np.eye(3)
_BOTTOM_ROW = np.array([0.0, 0.0, 0.0, 1.0])


def check_pose(name: str, pose: np.ndarray) -> np.ndarray:
    pose = np.asarray(pose, dtype=float)
    if pose.shape != (4, 4):
        raise ValueError(f"{name} must be a 4x4 matrix, got shape {pose.shape}")
    if not np.all(np.isfinite(pose)):
        raise ValueError(f"{name} contains NaN or inf")
    rotation = pose[:3, :3]
    # Plain max-abs tests (np.allclose costs ~15 us each, on every frame).
    if np.abs(rotation @ rotation.T - _EYE3).max() > 1e-5 or np.linalg.det(rotation) < 0:
        raise ValueError(f"{name} does not have a proper rotation block")
    if np.abs(pose[3] - _BOTTOM_ROW).max() > 1e-5:
        raise ValueError(f"{name} bottom row must be [0, 0, 0, 1]")
    return pose
