"""Can a filter trust the reported covariances? NEES of the relative motion over windows.

For windows [t_i, t_j] of ``window_s`` seconds, the estimated
motion of base_link E = P_i^-1 P_j (odometry poses) is compared with the true one
G = Q_i^-1 Q_j (ground-truth body poses): the error xi = Log(G^-1 E) (GTSAM tangent: rotation,
translation, in base_link at t_j) and its covariance C give NEES = xi^T C^-1 xi, which is
chi-square with 6 degrees of freedom when the covariances are right: mean 6.

Windows follow each other (``stride`` None) or start every ``stride`` frames. Overlapping
windows share most of their motion, so their NEES values are strongly correlated (two windows
k frames apart share 1 - k/n of an n-frame window): more windows smooth the mean over where a
window starts, but the mean rests on about as many independent windows as consecutive ones
would give (duration / window_s); its spread shrinks little.

Two readings of "the covariance of the relative motion" from what a message carries:

* ``pose``: odometry error accumulates like a random walk (independent increments, as the
  keyframe-to-keyframe measurements are), so C = P_j - Ad(E^-1) P_i Ad(E^-1)^T from the two
  pose covariances; directions where that difference is not positive (roll and pitch held by
  gravity) get the sum P_j + Ad P_i Ad^T instead, the bound for independent ends;
* ``twist``: the twist covariances integrated over the window as independent increments,
  C = sum_k Ad_k (dt_k^2 Sigma_k) Ad_k^T, the way a filter fusing the twist uses them.

The front end's own measurements are checked one by one too (:func:`measurement_nees`): each
T_ref_cur (left camera, keyframe to frame) against the ground-truth motion, with the covariance
it was reported with. This separates the two ways a window can go wrong: measurements whose
covariance is too small, or errors that are not independent from one measurement to the next
(``lag1_correlation``: consecutive measurements against the same keyframe share its points).
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass
from typing import Literal

import gtsam
import numpy as np

from estimator.formats.datasets import GroundTruth
from estimator.formats.odometry_msg import OdometryMessage
from estimator.geometry import invert_pose, transport_covariance

__all__ = [
    "MeasurementCheck",
    "NeesResult",
    "body_pose_covariance",
    "measurement_nees",
    "relative_nees",
]

CovarianceSource = Literal["pose", "twist"]
DOF = 6
_ROS_TO_GTSAM = [3, 4, 5, 0, 1, 2]  # (x y z roll pitch yaw) -> (rotation, translation)


@dataclass(frozen=True)
class NeesResult:
    values: np.ndarray  # (W,) one NEES per window
    rotation: np.ndarray  # (W,) NEES of the rotation block alone (3 DOF)
    translation: np.ndarray  # (W,) of the translation block alone (3 DOF)

    @property
    def windows(self) -> int:
        return len(self.values)

    def summary(self) -> dict[str, float | int]:
        """Means per DOF (1 = consistent) and the window count."""
        if not self.windows:
            return {"windows": 0}
        return {
            "windows": self.windows,
            "mean_nees": float(np.mean(self.values)),
            "mean_nees_per_dof": float(np.mean(self.values) / DOF),
            # chi-square(6) has median 5.35, i.e. 0.89 per DOF when consistent
            "median_nees_per_dof": float(np.median(self.values) / DOF),
            "rotation_per_dof": float(np.mean(self.rotation) / 3),
            "translation_per_dof": float(np.mean(self.translation) / 3),
        }


def body_pose_covariance(message: OdometryMessage) -> np.ndarray:
    """The message's pose covariance back in the body-frame tangent (rotation, translation)."""
    rotation = np.zeros((6, 6))
    rotation[:3, :3] = rotation[3:, 3:] = message.pose[:3, :3]
    body = rotation.T @ message.pose_covariance @ rotation
    return body[np.ix_(_ROS_TO_GTSAM, _ROS_TO_GTSAM)]


def _pose_window_covariance(first: OdometryMessage, last: OdometryMessage) -> np.ndarray:
    motion = invert_pose(first.pose) @ last.pose
    moved = transport_covariance(body_pose_covariance(first), motion)
    later = body_pose_covariance(last)
    values, vectors = np.linalg.eigh(later - moved)
    sums = np.einsum("ij,jk,ki->i", vectors.T, later + moved, vectors)
    # Growing directions: the increment; the others: independent ends.
    variances = np.where(values > 0, values, sums)
    return (vectors * variances) @ vectors.T


def _twist_window_covariance(window: list[OdometryMessage]) -> np.ndarray:
    covariance = np.zeros((6, 6))
    for previous, message in itertools.pairwise(window):
        dt = (message.stamp_ns - previous.stamp_ns) * 1e-9
        step = message.twist_covariance[np.ix_(_ROS_TO_GTSAM, _ROS_TO_GTSAM)] * dt**2
        motion = invert_pose(previous.pose) @ message.pose
        # carry the sum so far into this frame
        covariance = transport_covariance(covariance, motion) + step
    return covariance


def relative_nees(
    messages: list[OdometryMessage],
    ground_truth: GroundTruth,
    window_s: float = 1.0,
    source: CovarianceSource = "pose",
    stride: int | None = None,
) -> NeesResult:
    """NEES of the base_link motion over windows of ``window_s``, one after the other or
    starting every ``stride`` frames (module doc)."""
    if stride is not None and stride < 1:
        raise ValueError(f"stride must be at least one frame, got {stride}")
    stamps = np.array([m.stamp_ns for m in messages], dtype=np.int64)
    inside = ground_truth.covers(stamps)
    values, rotation, translation = [], [], []
    start = int(np.argmax(inside)) if inside.any() else len(messages)
    while start < len(messages):
        end = int(np.searchsorted(stamps, stamps[start] + round(window_s * 1e9)))
        if end >= len(messages) or not inside[end]:
            break
        first, last = messages[start], messages[end]
        truth = ground_truth.interpolate(np.array([first.stamp_ns, last.stamp_ns]))
        estimated = invert_pose(first.pose) @ last.pose
        actual = invert_pose(truth[0]) @ truth[1]
        error = np.asarray(gtsam.Pose3.Logmap(gtsam.Pose3(invert_pose(actual) @ estimated)))
        if source == "pose":
            covariance = _pose_window_covariance(first, last)
        else:
            covariance = _twist_window_covariance(messages[start : end + 1])
        values.append(float(error @ np.linalg.solve(covariance, error)))
        rotation.append(float(error[:3] @ np.linalg.solve(covariance[:3, :3], error[:3])))
        translation.append(float(error[3:] @ np.linalg.solve(covariance[3:, 3:], error[3:])))
        start = end if stride is None else start + stride
    return NeesResult(np.array(values), np.array(rotation), np.array(translation))


@dataclass(frozen=True)
class MeasurementCheck:
    """Per-measurement NEES of the front end, and how its errors follow each other."""

    nees: NeesResult
    # Correlation of consecutive measurement errors (mean over the six axes): against the same
    # keyframe, and across a keyframe change (0 for independent measurements).
    lag1_same_reference: float
    lag1_new_reference: float

    def summary(self) -> dict[str, float | int]:
        return {
            **self.nees.summary(),
            "lag1_same_reference": self.lag1_same_reference,
            "lag1_new_reference": self.lag1_new_reference,
        }


def measurement_nees(
    reports: list,
    ground_truth: GroundTruth,
    body_from_camera: np.ndarray,
    calibrated: bool = True,
) -> MeasurementCheck:
    """NEES of each reported front-end measurement T_ref_cur (right perturbation of the left
    camera, GTSAM order) against the ground-truth motion of the left camera; ``calibrated``:
    with the report's covariance scale applied, as the odometry messages apply it."""
    pose_of = {r.timestamp_ns: r.frontend_pose for r in reports}
    measured = [
        r for r in reports
        if r.measurement_covariance is not None and r.reference_timestamp_ns in pose_of
        and ground_truth.covers(np.array([r.reference_timestamp_ns, r.timestamp_ns])).all()
    ]
    stamps = np.array([[r.reference_timestamp_ns, r.timestamp_ns] for r in measured], np.int64)
    truth = ground_truth.interpolate(stamps.reshape(-1)).reshape(-1, 2, 4, 4) @ body_from_camera
    errors, covariances, references = [], [], []
    for report, (first, last) in zip(measured, truth, strict=True):
        actual = invert_pose(first) @ last
        motion = invert_pose(pose_of[report.reference_timestamp_ns]) @ report.frontend_pose
        errors.append(gtsam.Pose3.Logmap(gtsam.Pose3(invert_pose(actual) @ motion)))
        scale = report.covariance_scale if calibrated else 1.0
        covariances.append(scale * report.measurement_covariance)
        references.append(report.reference_timestamp_ns)
    error, covariance = np.array(errors).reshape(-1, 6), np.array(covariances).reshape(-1, 6, 6)
    values = np.einsum("ni,ni->n", error, np.linalg.solve(covariance, error[:, :, None])[..., 0])
    rotation = np.einsum(
        "ni,ni->n", error[:, :3], np.linalg.solve(covariance[:, :3, :3], error[:, :3, None])[..., 0]
    )
    translation = np.einsum(
        "ni,ni->n", error[:, 3:], np.linalg.solve(covariance[:, 3:, 3:], error[:, 3:, None])[..., 0]
    )
    same = np.array(references[1:]) == np.array(references[:-1])
    return MeasurementCheck(
        NeesResult(values, rotation, translation),
        _lag1_correlation(error, same),
        _lag1_correlation(error, ~same),
    )


def _lag1_correlation(error: np.ndarray, pairs: np.ndarray) -> float:
    """Mean over the axes of the correlation of error k with error k + 1, where ``pairs``."""
    if pairs.sum() < 3:
        return float("nan")
    before, after = error[:-1][pairs], error[1:][pairs]
    return float(np.mean([np.corrcoef(before[:, k], after[:, k])[0, 1] for k in range(6)]))
