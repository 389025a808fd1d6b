"""What the odometry measures inside one frame, for whoever wants to look at it.

A frame's answer is one combined measurement; the registrations behind it (against the
keyframe, through the previous frame, the retries) are gone once the frame is answered. An
evaluation that needs them (how a chain link errs against the ground truth, where a
registration's error comes from) passes an observer to ``Odometry``: it is called with each
measurement as it is made. Without one nothing is formed.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from enum import StrEnum

import numpy as np

from estimator.frontend.stereo import StereoPoints
from estimator.frontend.stereo_noise import StereoNoiseModel
from estimator.frontend.temporal import Correspondences
from estimator.odometry.frames import CurrentFrame, Estimate, Reference, inlier_flow
from estimator.odometry.measurements import CameraFrames

__all__ = ["MeasurementKind", "MeasurementObserver", "ObservedMeasurement", "observed"]


class MeasurementKind(StrEnum):
    """Which measurement of the frame an observation is."""

    # Every registration against a reference as it came out, before the plausibility check
    # (failed ones too: their pose is None).
    REGISTRATION = "registration"
    # The plausible measurement against the keyframe, before a chain is combined with it.
    KEYFRAME = "keyframe"
    # A chain's plausible last step (its reference -> the current frame), before it is
    # combined with the keyframe measurement; its covariance without the link's bias.
    LINK = "link"
    # A registration against an older keyframe tried as the reference again (keyframe
    # revisits, odometry/revisits.py), as it came out (refused ones too).
    REVISIT = "revisit"


@dataclass(frozen=True)
class ObservedMeasurement:
    """One measurement of the current frame against a reference, as it was when made."""

    kind: MeasurementKind
    index: int  # the current frame's
    timestamp_ns: int  # the current frame's
    reference: Reference
    points: StereoPoints  # the current frame's stereo points
    # T_ref_cur of the rectified left camera and of the original one; None: no pose.
    reference_from_current: np.ndarray | None
    camera_reference_from_current: np.ndarray | None
    covariance: np.ndarray | None  # 6x6, right perturbation; None: not refined
    pairs: Correspondences | None  # None: no temporal matching happened
    inliers: np.ndarray | None  # (len(pairs),) bool; None: no registration result
    point_covariances: tuple[np.ndarray, np.ndarray] | None  # of pairs' current, reference
    inlier_flow_px: np.ndarray  # (N,) image motion of the inliers (empty: none)
    # The stereo noise model's support gate (squared Mahalanobis) when it was made: the
    # level it learns from the frame comes after all of the frame's measurements.
    gate_chi2: float


MeasurementObserver = Callable[[ObservedMeasurement], None]


def observed(
    kind: MeasurementKind,
    estimate: Estimate,
    current: CurrentFrame,
    noise: StereoNoiseModel,
) -> ObservedMeasurement:
    """The record of ``estimate`` (measured against ``estimate.reference``) under the
    session's ``noise``, copied where the combination later replaces a part of it."""
    rectification = noise.rectification
    assert estimate.reference is not None
    pose = estimate.reference_from_current
    camera_pose = None
    if pose is not None:
        camera_pose = CameraFrames(rectification.R_left).in_camera(pose)
    covariance = estimate.covariance
    return ObservedMeasurement(
        kind=kind,
        index=current.index,
        timestamp_ns=current.timestamp_ns,
        reference=estimate.reference,
        points=current.points,
        reference_from_current=None if pose is None else pose.copy(),
        camera_reference_from_current=camera_pose,
        covariance=None if covariance is None else covariance.copy(),
        pairs=estimate.pairs,
        inliers=None if estimate.result is None else estimate.result.inliers,
        point_covariances=estimate.point_covariances,
        inlier_flow_px=inlier_flow(estimate, rectification),
        gate_chi2=noise.gate_chi2,
    )
