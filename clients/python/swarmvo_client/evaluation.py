"""Absolute trajectory error with a rigid (Umeyama, no scale) alignment, in plain numpy."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class TrajectoryError:
    pairs: int
    ate_rmse_m: float
    ate_max_m: float
    path_length_m: float


def rigid_align(source: np.ndarray, target: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """R, t minimising sum |R source_i + t - target_i|^2 (Umeyama 1991 without scale)."""
    mu_s, mu_t = source.mean(axis=0), target.mean(axis=0)
    covariance = (target - mu_t).T @ (source - mu_s) / len(source)
    u, _, vt = np.linalg.svd(covariance)
    sign = np.eye(3)
    sign[2, 2] = np.sign(np.linalg.det(u) * np.linalg.det(vt)) or 1.0
    rotation = u @ sign @ vt
    return rotation, mu_t - rotation @ mu_s


def trajectory_error(
    timestamps_ns: np.ndarray,
    positions: np.ndarray,
    gt_timestamps_ns: np.ndarray,
    gt_positions: np.ndarray,
) -> TrajectoryError | None:
    """ATE of estimated positions against ground truth interpolated at their timestamps.

    Only the positions are compared (the estimate is the left camera, the ground truth may be
    another body frame; the alignment absorbs the rotation, a lever arm remains and is small).
    """
    inside = (timestamps_ns >= gt_timestamps_ns[0]) & (timestamps_ns <= gt_timestamps_ns[-1])
    if inside.sum() < 3:
        return None
    times = timestamps_ns[inside].astype(float)
    reference = np.stack(
        [np.interp(times, gt_timestamps_ns.astype(float), gt_positions[:, k]) for k in range(3)],
        axis=1,
    )
    estimate = positions[inside]
    rotation, translation = rigid_align(estimate, reference)
    residual = np.linalg.norm(estimate @ rotation.T + translation - reference, axis=1)
    path = float(np.linalg.norm(np.diff(reference, axis=0), axis=1).sum())
    return TrajectoryError(
        int(inside.sum()), float(np.sqrt(np.mean(residual**2))), float(residual.max()), path
    )
