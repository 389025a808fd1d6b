"""What every registration estimator returns, and the small builders they share.

An estimator hands back a :class:`RegistrationResult`; ``pose_result`` and ``failed_result``
build one consistently (rotation and unit quaternion agree, identity on failure) and the
option checks keep every estimator's error messages alike. Kept apart from the estimators and
the registry so that both import it and neither imports the other.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from estimator.geometry import matrix_to_quat, quat_to_matrix

__all__ = [
    "RegistrationResult",
    "check_positive",
    "failed_result",
    "pose_result",
    "reject_unknown_options",
    "relative_scales",
    "residual_norms",
]


@dataclass
class RegistrationResult:
    """target ~ rotation @ source + translation, with the pairs that support it."""

    rotation: np.ndarray  # (3, 3), det +1
    translation: np.ndarray  # (3,)
    quaternion: np.ndarray  # (w, x, y, z), unit norm, w >= 0
    inliers: np.ndarray  # (N,) bool
    support: int
    cost: float
    iterations: int
    elapsed_s: float
    success: bool
    method: str = ""
    message: str = ""


def residual_norms(
    rotation: np.ndarray, translation: np.ndarray, source: np.ndarray, target: np.ndarray
) -> np.ndarray:
    """||target_j - (R source_j + t)|| for every pair."""
    difference = target - source @ rotation.T - translation
    return np.sqrt(np.einsum("ij,ij->i", difference, difference))


def pose_result(
    rotation: np.ndarray,
    translation: np.ndarray,
    inliers: np.ndarray,
    *,
    cost: float,
    iterations: int,
    quaternion: np.ndarray | None = None,
    success: bool = True,
    message: str = "",
) -> RegistrationResult:
    """A successful-looking result whose rotation and unit quaternion agree.

    Without ``quaternion`` the rotation is converted and rebuilt from it; with one (a fit
    that produced both, e.g. ``geometry.horn``) both are taken as they are.
    """
    if quaternion is None:
        quaternion = matrix_to_quat(rotation)
        rotation = quat_to_matrix(quaternion)
    return RegistrationResult(
        rotation=np.asarray(rotation, dtype=float),
        translation=np.asarray(translation, dtype=float).copy(),
        quaternion=np.asarray(quaternion, dtype=float),
        inliers=np.asarray(inliers, dtype=bool),
        support=int(np.count_nonzero(inliers)),
        cost=float(cost),
        iterations=int(iterations),
        elapsed_s=0.0,
        success=success,
        message=message,
    )


def failed_result(count: int, message: str, iterations: int = 0) -> RegistrationResult:
    """Identity pose, no inliers, ``success=False``: the data cannot support an estimate."""
    return RegistrationResult(
        rotation=np.eye(3),
        translation=np.zeros(3),
        quaternion=np.array([1.0, 0.0, 0.0, 0.0]),
        inliers=np.zeros(count, dtype=bool),
        support=0,
        cost=math.inf,
        iterations=iterations,
        elapsed_s=0.0,
        success=False,
        message=message,
    )


def relative_scales(sigmas: object, count: int) -> np.ndarray:
    """sigma_j / median(sigma) after checking that ``sigmas`` is N finite positive numbers."""
    values = np.asarray(sigmas, dtype=float)
    if values.shape != (count,):
        raise ValueError(f"sigmas must have shape ({count},) (one per pair), got {values.shape}")
    if not np.isfinite(values).all():
        raise ValueError("sigmas must be finite")
    if not (values > 0.0).all():
        raise ValueError(f"sigmas must be positive, got min {values.min()}")
    return values / np.median(values) if count else values


def check_positive(**values: float) -> None:
    """ValueError naming the first option that is not > 0."""
    for name, value in values.items():
        if not value > 0:
            raise ValueError(f"{name} must be positive, got {value}")


def reject_unknown_options(method: str, unknown: dict[str, object]) -> None:
    """A misspelt option must fail loudly, not be silently ignored."""
    if unknown:
        raise ValueError(f"{method}: unknown option(s) {sorted(unknown)}")
