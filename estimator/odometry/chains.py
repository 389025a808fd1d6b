"""Two measurements of one frame's pose against the keyframe, combined by their covariances.

Against the keyframe alone, the error of each frame's pose is the error of one registration,
so consecutive frames differ by two independent errors and the frame-to-frame motion is noisier
than either. The frame is also measured against the previous frame, whose pose relative to the
keyframe is already known with its covariance; chained, that gives a second estimate of the
same pose. The two are combined in the tangent space of the keyframe measurement, weighed by
their covariances (a Kalman update with the keyframe measurement as the prior).

Poses here use the refinement's right perturbation (``estimator/registration/refine.py``):
xi = (omega, v) with R <- R Exp(omega), t <- t + R v, so a refined covariance applies as is.
The two estimates share the current frame's points, so their errors are not independent.
Each registration's linear sensitivity to its points (``estimator/registration/sensitivity.py``)
gives the cross-covariance those shared points cause, and the combination is the best linear
unbiased one of two correlated estimates. Still treated as independent: the keyframe's points,
shared by the keyframe measurement and the previous frame's (inside the chain), and the previous
frame's points, shared by the two links of the chain.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from estimator.geometry import (
    make_pose,
    matrix_to_quat,
    quat_to_matrix,
    quat_to_rotation_vector,
    rotation_vector_to_quat,
    se3_adjoint,
    transport_covariance,
)

__all__ = [
    "PointSensitivity",
    "chain_covariance",
    "fuse_correlated",
    "fuse_poses",
    "fused_sensitivity",
    "inverse_covariance",
    "pose_difference",
    "shared_covariance",
]


@dataclass
class PointSensitivity:
    """How a pose estimate (right perturbation in the current frame) moves with the current
    frame's points: error ~ sum_j gains_j e_j, e_j ~ N(0, covariances_j)."""

    current_index: np.ndarray  # (n,) into the current frame's StereoPoints
    gains: np.ndarray  # (n, 6, 3), scaled by the square root of the variance factor
    covariances: np.ndarray  # (n, 3, 3)


def pose_difference(first: np.ndarray, second: np.ndarray) -> np.ndarray:
    """xi (6,) with ``second`` = ``first`` perturbed on the right by xi."""
    rotation = first[:3, :3].T @ second[:3, :3]
    omega = quat_to_rotation_vector(matrix_to_quat(rotation))
    return np.concatenate([omega, first[:3, :3].T @ (second[:3, 3] - first[:3, 3])])


def perturbed(pose: np.ndarray, xi: np.ndarray) -> np.ndarray:
    """``pose`` perturbed on the right by xi = (omega, v)."""
    rotation = pose[:3, :3] @ quat_to_matrix(rotation_vector_to_quat(xi[:3]))
    return make_pose(rotation, pose[:3, 3] + pose[:3, :3] @ xi[3:])


def chain_covariance(
    first_covariance: np.ndarray, second: np.ndarray, second_covariance: np.ndarray
) -> np.ndarray:
    """Covariance (6x6, right perturbation) of A @ B from those of A and B (independent).

    Perturbing A on the right moves A @ B by Ad(B^-1) (``transport_covariance``): by
    R_B^T omega in rotation and by R_B^T (v - [t_B]x omega) in translation; perturbing B
    passes through unchanged.
    """
    return transport_covariance(first_covariance, second) + second_covariance


def inverse_covariance(pose: np.ndarray, covariance: np.ndarray) -> np.ndarray:
    """Covariance (6x6, right perturbation) of the inverse of ``pose``.

    Perturbing the pose by (omega, v) moves its inverse by -Ad(pose) (omega, v): by -R omega
    in rotation and by -[t]x R omega - R v in translation; the sign cancels in the covariance.
    """
    adjoint = se3_adjoint(pose)
    return adjoint @ covariance @ adjoint.T


def fuse_poses(
    first: np.ndarray,
    first_covariance: np.ndarray,
    second: np.ndarray,
    second_covariance: np.ndarray,
) -> tuple[np.ndarray, np.ndarray] | None:
    """The covariance-weighted combination of two estimates of one pose and its covariance;
    None when a covariance is not positive definite (nothing to weigh by)."""
    try:
        first_information = np.linalg.inv(first_covariance)
        second_information = np.linalg.inv(second_covariance)
        covariance = np.linalg.inv(first_information + second_information)
        np.linalg.cholesky(first_covariance)
        np.linalg.cholesky(second_covariance)
    except np.linalg.LinAlgError:
        return None
    xi = covariance @ second_information @ pose_difference(first, second)
    if not np.isfinite(xi).all():
        return None
    return perturbed(first, xi), 0.5 * (covariance + covariance.T)


def shared_covariance(first: PointSensitivity, second: PointSensitivity) -> np.ndarray:
    """(6, 6) cross-covariance of two estimates caused by the current points both used."""
    _, mine, theirs = np.intersect1d(
        first.current_index, second.current_index, assume_unique=False, return_indices=True
    )
    return np.einsum(
        "nij,njk,nlk->il", first.gains[mine], first.covariances[mine], second.gains[theirs]
    )


def fuse_correlated(
    first: np.ndarray,
    first_covariance: np.ndarray,
    second: np.ndarray,
    second_covariance: np.ndarray,
    cross: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """The best linear unbiased combination of two estimates of one pose whose errors have
    the cross-covariance ``cross`` = E[e_first e_second^T]: pose, covariance and the gain G
    (xi = G (second - first)); None when a covariance is not positive definite.

    With ``cross`` = 0 this is ``fuse_poses``; a shared error gets no weight twice.
    """
    shared = first_covariance - cross
    difference = first_covariance + second_covariance - cross - cross.T
    try:
        np.linalg.cholesky(first_covariance)
        np.linalg.cholesky(second_covariance)
        np.linalg.cholesky(0.5 * (difference + difference.T))
        gain = np.linalg.solve(difference.T, shared.T).T  # shared @ difference^-1
    except np.linalg.LinAlgError:
        return None
    xi = gain @ pose_difference(first, second)
    covariance = first_covariance - gain @ shared.T
    if not (np.isfinite(xi).all() and np.isfinite(covariance).all()):
        return None
    return perturbed(first, xi), 0.5 * (covariance + covariance.T), gain


def fused_sensitivity(
    first: PointSensitivity, second: PointSensitivity, gain: np.ndarray
) -> PointSensitivity:
    """The sensitivity of first + G (second - first) to the current points of either."""
    index = np.union1d(first.current_index, second.current_index)
    gains = np.zeros((len(index), 6, 3))
    covariances = np.zeros((len(index), 3, 3))
    for part, weight in ((first, np.eye(6) - gain), (second, gain)):
        position = np.searchsorted(index, part.current_index)
        np.add.at(gains, position, np.einsum("ij,njk->nik", weight, part.gains))
        covariances[position] = part.covariances
    return PointSensitivity(index, gains, covariances)
