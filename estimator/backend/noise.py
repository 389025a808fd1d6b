"""Noise models of the graph: relative-pose covariance from the registration inliers.

A rigid fit from n 3D-3D pairs with residual RMS r determines its translation to about
r / sqrt(n) and its rotation to about r / (sqrt(n) * spread), spread being the RMS distance of
the points from their centroid (the lever arm of the rotation). The front end reports residual
norms and counts but not the spread, so that one comes from the configuration. Both sigmas are
clamped so a lucky fit cannot claim centimetre-free certainty and a poor one still carries
some information.
"""

from __future__ import annotations

import gtsam
import numpy as np

from estimator.config import BackendConfig

__all__ = ["pose_noise", "relative_pose_sigmas", "robust"]


def relative_pose_sigmas(
    residuals: np.ndarray | None, inlier_count: int, config: BackendConfig
) -> tuple[float, float]:
    """(rotation sigma rad, translation sigma m) per axis of one front-end relative pose."""
    if inlier_count < 0:
        raise ValueError(f"inlier_count must be >= 0, got {inlier_count}")
    if residuals is not None and len(residuals) > 0:
        residuals = np.asarray(residuals, dtype=float).ravel()
        if not np.all(np.isfinite(residuals)):
            raise ValueError("inlier residuals contain NaN or inf")
        # Norms of 3D residuals: per-axis RMS is the norm RMS / sqrt(3).
        rms = float(np.sqrt(np.mean(residuals**2) / 3.0))
    else:
        rms = config.fallback_residual_m / np.sqrt(3.0)
    root_n = np.sqrt(max(inlier_count, 1))
    translation = config.translation_sigma_scale * rms / root_n
    rotation = config.rotation_sigma_scale * rms / (root_n * config.point_spread_m)
    return (
        float(np.clip(rotation, config.min_rotation_sigma_rad, config.max_rotation_sigma_rad)),
        float(np.clip(translation, config.min_translation_sigma_m, config.max_translation_sigma_m)),
    )


def pose_noise(rotation_sigma: float, translation_sigma: float) -> gtsam.noiseModel.Diagonal:
    """Diagonal Pose3 noise in GTSAM's tangent order (rotation first, then translation)."""
    return gtsam.noiseModel.Diagonal.Sigmas(
        np.array([rotation_sigma] * 3 + [translation_sigma] * 3, dtype=float)
    )


def robust(base: gtsam.noiseModel.Base, kernel: str, parameter: float) -> gtsam.noiseModel.Base:
    """Wrap ``base`` in an M-estimator so one wrong relative pose cannot tear the trajectory."""
    if kernel == "none":
        return base
    if kernel == "huber":
        estimator = gtsam.noiseModel.mEstimator.Huber.Create(parameter)
    elif kernel == "cauchy":
        estimator = gtsam.noiseModel.mEstimator.Cauchy.Create(parameter)
    else:
        raise ValueError(f"unknown robust kernel {kernel!r} (huber, cauchy or none)")
    return gtsam.noiseModel.Robust.Create(estimator, base)
