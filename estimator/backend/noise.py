"""Noise models of the graph: relative-pose covariance from the registration inliers.

With the inlier points the covariance is the full 6x6 one of the rigid fit (``fit_covariance``):
the points sit metres in front of the camera, so a rotation error of the fit comes with a
translation error of the camera of the same lever arm - in the rendered sequences the two are
99 % correlated. A diagonal covariance drops that coupling: when the gyro then corrects the
rotation, the translation keeps its now uncompensated share of the error.

Without the points (``relative_pose_sigmas``): a rigid fit from n 3D-3D pairs with residual
RMS r determines its translation to about r / sqrt(n) and its rotation to about
r / (sqrt(n) * spread), spread being the RMS distance of the points from their centroid (the
lever arm of the rotation), which then comes from the configuration. Both sigmas are clamped
so a lucky fit cannot claim centimetre-free certainty and a poor one still carries some
information.
"""

from __future__ import annotations

import math

import gtsam
import numpy as np

from estimator.backend.systematic_noise import fit_floor_covariance
from estimator.config import BackendConfig
from estimator.geometry import skew

__all__ = [
    "CHI2_6DOF_99",
    "fit_covariance",
    "kernel_scale",
    "measured_covariance",
    "pose_noise",
    "relative_pose_covariance",
    "relative_pose_sigmas",
    "robust",
    "sigma_covariance",
]

# 99 % quantile of chi-square with 6 DOF, and the weight the default Cauchy kernel leaves a
# measurement there (``kernel_scale``).
CHI2_6DOF_99 = 16.812
REAL_RIG_KERNEL_SCALE = 3.0
CONSISTENT_WEIGHT = 0.9


def relative_pose_sigmas(
    residuals: np.ndarray | None, inlier_count: int, config: BackendConfig
) -> tuple[float, float]:
    """(rotation sigma rad, translation sigma m) per axis of one front-end relative pose."""
    if inlier_count < 0:
        raise ValueError(f"inlier_count must be >= 0, got {inlier_count}")
    rms = np.sqrt(_residual_variance(residuals, config))
    root_n = np.sqrt(max(inlier_count, 1))
    translation = config.translation_sigma_scale * rms / root_n
    rotation = config.rotation_sigma_scale * rms / (root_n * config.point_spread_m)
    return (
        float(np.clip(rotation, config.min_rotation_sigma_rad, config.max_rotation_sigma_rad)),
        float(np.clip(translation, config.min_translation_sigma_m, config.max_translation_sigma_m)),
    )


def _residual_variance(residuals: np.ndarray | None, config: BackendConfig) -> float:
    """Per-axis variance of the fit residuals (norms of 3D residuals: RMS^2 / 3)."""
    if residuals is None or len(residuals) == 0:
        return config.fallback_residual_m**2 / 3.0
    residuals = np.asarray(residuals, dtype=float).ravel()
    if not np.all(np.isfinite(residuals)):
        raise ValueError("inlier residuals contain NaN or inf")
    return float(np.mean(residuals**2) / 3.0)


def fit_covariance(
    points: np.ndarray, residuals: np.ndarray | None, config: BackendConfig
) -> np.ndarray:
    """6x6 covariance of a rigid fit p ~ R q + t from its inlier points q (current frame).

    GTSAM's Pose3 tangent ([rotation, translation], perturbation on the right, i.e. in the
    current frame): a point moves by R (-[q]x d_rot + d_trans), so with isotropic residual
    variance s^2 the information is sum_i [-[q_i]x, I]^T [-[q_i]x, I] / s^2. The configured
    maximum sigmas enter as a weak prior (degenerate point sets stay invertible) and the
    minimum sigmas as a floor, so a fit from few, perfect points cannot claim absurd certainty.
    """
    points = np.asarray(points, dtype=float).reshape(-1, 3)
    if not np.all(np.isfinite(points)):
        raise ValueError("inlier points contain NaN or inf")
    variance = _residual_variance(residuals, config)
    variance = max(variance, 1e-12)
    total = points.sum(axis=0)
    cross = skew(total)
    information = np.zeros((6, 6))
    information[:3, :3] = np.sum(points**2) * np.eye(3) - points.T @ points
    information[:3, 3:] = cross
    information[3:, :3] = -cross
    information[3:, 3:] = len(points) * np.eye(3)
    information /= variance
    information += np.diag(
        [config.max_rotation_sigma_rad**-2] * 3 + [config.max_translation_sigma_m**-2] * 3
    )
    floor = fit_floor_covariance(config)
    covariance = config.fit_covariance_scale**2 * np.linalg.inv(information) + floor
    return 0.5 * (covariance + covariance.T)


def measured_covariance(covariance: np.ndarray, config: BackendConfig) -> np.ndarray:
    """A front-end covariance checked, symmetrised and floored like the fitted ones."""
    covariance = np.asarray(covariance, dtype=float)
    if covariance.shape != (6, 6) or not np.all(np.isfinite(covariance)):
        raise ValueError("covariance must be a finite 6x6 matrix")
    covariance = config.fit_covariance_scale**2 * covariance + fit_floor_covariance(config)
    return 0.5 * (covariance + covariance.T)


def sigma_covariance(sigmas: tuple[float, float]) -> np.ndarray:
    """The diagonal 6x6 covariance of (rotation sigma, translation sigma)."""
    rotation, translation = sigmas
    return np.diag([rotation**2] * 3 + [translation**2] * 3)


def pose_noise(rotation_sigma: float, translation_sigma: float) -> gtsam.noiseModel.Diagonal:
    """Diagonal Pose3 noise in GTSAM's tangent order (rotation first, then translation)."""
    return gtsam.noiseModel.Diagonal.Sigmas(
        np.array([rotation_sigma] * 3 + [translation_sigma] * 3, dtype=float)
    )


def kernel_scale(
    kernel: str, parameter: float | None = None, calibration_exact: bool = False
) -> float:
    """The kernel's threshold on the whitened 6-DOF error norm: ``parameter`` when given, else
    the rig's.

    A rig not known to be exact: 3, chosen on a real rig whose measurement covariances miss
    its calibration error (MH_01: NEES 2-4 per DOF), which the kernel then also absorbs. A rig
    whose calibration is exact has consistent covariances: the squared norm of a 6-DOF error is
    chi-square with 6 DOF (mean 6, 99 % below 16.8) and a consistent measurement keeps nearly
    full weight. Huber: its threshold at the 99 % quantile (weight 1 below). Cauchy, weight
    1 / (1 + e^2 / k^2): k^2 = 16.8 x 9, weight 0.9 at the 99 % quantile, 0.96 at the mean,
    0.6 at 10 sigma, 0.13 at 30 sigma (a scale of 3 weighed a consistent measurement 0.6 and
    set vision below the gyro on the rendered drives; docs/backend.md).
    """
    if parameter is not None:
        return parameter
    if not calibration_exact:
        return REAL_RIG_KERNEL_SCALE
    if kernel == "huber":
        return math.sqrt(CHI2_6DOF_99)
    return math.sqrt(CHI2_6DOF_99 * CONSISTENT_WEIGHT / (1.0 - CONSISTENT_WEIGHT))


def robust(
    base: gtsam.noiseModel.Base, kernel: str, parameter: float | None = None
) -> gtsam.noiseModel.Base:
    """Wrap ``base`` in an M-estimator so one wrong relative pose cannot tear the trajectory
    (threshold: ``kernel_scale``)."""
    if kernel == "none":
        return base
    parameter = kernel_scale(kernel, parameter)
    if kernel == "huber":
        estimator = gtsam.noiseModel.mEstimator.Huber.Create(parameter)
    elif kernel == "cauchy":
        estimator = gtsam.noiseModel.mEstimator.Cauchy.Create(parameter)
    else:
        raise ValueError(f"unknown robust kernel {kernel!r} (huber, cauchy or none)")
    return gtsam.noiseModel.Robust.Create(estimator, base)


def relative_pose_covariance(
    covariance: np.ndarray | None,
    inlier_points: np.ndarray | None,
    inlier_residuals: np.ndarray | None,
    inlier_count: int,
    config: BackendConfig,
) -> np.ndarray:
    """Camera-frame covariance of a relative pose: the front end's own when it has one, else
    the rigid fit's from the inlier points, else the diagonal one from the residuals."""
    if covariance is not None:
        return measured_covariance(covariance, config)
    if inlier_points is not None and len(inlier_points) > 0:
        return fit_covariance(inlier_points, inlier_residuals, config)
    return sigma_covariance(relative_pose_sigmas(inlier_residuals, inlier_count, config))
