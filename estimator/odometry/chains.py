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
unbiased one of two correlated estimates. The same holds for the keyframe's points (used by the
keyframe measurement and, inside the chain, by the previous frame's) and for the previous
frame's points (used by both links of the chain). Each combined estimate keeps its own
sensitivities, so the next frame's chain through it knows them.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from estimator.geometry import (
    make_pose,
    quat_to_matrix,
    rotation_vector,
    rotation_vector_to_quat,
    se3_adjoint,
    transport_covariance,
)
from estimator.order_statistics import median

__all__ = [
    "Measured",
    "PointSensitivity",
    "chain_covariance",
    "combine_chain",
    "fuse_correlated",
    "fuse_poses",
    "fused_sensitivity",
    "inverse_covariance",
    "link_bias_covariance",
    "pose_difference",
    "shared_covariance",
    "transported",
]


@dataclass
class PointSensitivity:
    """How a pose estimate (right perturbation in the current frame) moves with one frame's
    points: error ~ sum_j gains_j e_j, e_j ~ N(0, covariances_j)."""

    current_index: np.ndarray  # (n,) into the StereoPoints of the frame the points belong to
    gains: np.ndarray  # (n, 6, 3), scaled by the square root of the variance factor
    covariances: np.ndarray  # (n, 3, 3)


def pose_difference(first: np.ndarray, second: np.ndarray) -> np.ndarray:
    """xi (6,) with ``second`` = ``first`` perturbed on the right by xi."""
    rotation = first[:3, :3].T @ second[:3, :3]
    omega = rotation_vector(rotation)
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


def link_bias_covariance(rate: float, flow_px: np.ndarray, focal_px: float) -> np.ndarray:
    """6x6 covariance of the rotation error of one frame-to-frame link that its registration
    covariance leaves out: sigma = ``rate`` x median image motion / focal length per axis.

    The registration's covariance counts only the points' random noise, so chaining links
    treats their errors as averaging out; an error that grows with the image motion (motion
    blur moves the points of consecutive frames alike) does not, and without this term the
    chain gets too much weight where the camera moves fast.
    """
    covariance = np.zeros((6, 6))
    if rate == 0.0 or len(flow_px) == 0:
        return covariance
    sigma = rate * median(flow_px) / focal_px
    covariance[:3, :3] = np.eye(3) * sigma**2
    return covariance


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
    """(6, 6) cross-covariance of two estimates caused by the points (of one frame) both
    used."""
    _, mine, theirs = np.intersect1d(
        first.current_index, second.current_index, assume_unique=False, return_indices=True
    )
    # sum_n K_n C_n K'_n^T: the per-point products stacked, then one contraction over n and k.
    spread = first.gains[mine] @ first.covariances[mine]
    return np.tensordot(spread, second.gains[theirs], axes=([0, 2], [0, 2]))


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


def transported(sensitivity: PointSensitivity, adjoint: np.ndarray) -> PointSensitivity:
    """The sensitivity of the perturbation ``adjoint`` @ xi (a pose moved on to another)."""
    gains = adjoint @ sensitivity.gains
    return PointSensitivity(sensitivity.current_index, gains, sensitivity.covariances)


def fused_sensitivity(
    first: PointSensitivity, second: PointSensitivity, gain: np.ndarray
) -> PointSensitivity:
    """The sensitivity of first + G (second - first) to the current points of either."""
    index = np.union1d(first.current_index, second.current_index)
    gains = np.zeros((len(index), 6, 3))
    covariances = np.zeros((len(index), 3, 3))
    for part, weight in ((first, np.eye(6) - gain), (second, gain)):
        position = np.searchsorted(index, part.current_index)
        np.add.at(gains, position, weight @ part.gains)
        covariances[position] = part.covariances
    return PointSensitivity(index, gains, covariances)


@dataclass
class Measured:
    """One relative pose with its covariance and how it moves with the points of its current
    frame and of its reference (None: not known, taken as sharing nothing)."""

    pose: np.ndarray
    covariance: np.ndarray
    current: PointSensitivity | None = None
    reference: PointSensitivity | None = None


def _shared(first: PointSensitivity | None, second: PointSensitivity | None) -> np.ndarray:
    if first is None or second is None:
        return np.zeros((6, 6))
    return shared_covariance(first, second)


def combine_chain(measured: Measured, link: Measured, step: Measured) -> Measured | None:
    """T_kc measured against the keyframe k combined with the chain T_kp @ T_pc (``link``
    @ ``step``); None when a covariance is not positive definite.

    Shared points: the current frame's (by ``measured`` and ``step``), the keyframe's (by
    ``measured`` and, through the link, the chain) and the previous frame's (by both links of
    the chain). A perturbation of the link reaches the chain's end through Ad(T_pc^-1).
    """
    adjoint = se3_adjoint(step.pose, inverse=True)
    through = [
        None if part is None else transported(part, adjoint)
        for part in (link.current, link.reference)
    ]
    links = _shared(through[0], step.reference)
    chain = chain_covariance(link.covariance, step.pose, step.covariance) + links + links.T
    cross = _shared(measured.current, step.current) + _shared(measured.reference, through[1])
    fused = fuse_correlated(measured.pose, measured.covariance, link.pose @ step.pose, chain, cross)
    if fused is None:
        return None
    pose, covariance, gain = fused
    current = reference = None
    if measured.current is not None and step.current is not None:
        current = fused_sensitivity(measured.current, step.current, gain)
    if measured.reference is not None and through[1] is not None:
        reference = fused_sensitivity(measured.reference, through[1], gain)
    return Measured(pose, covariance, current, reference)
