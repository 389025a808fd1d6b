"""The chain step: the keyframe measurement combined with the chain through the previous frame
and, with ``frontend.fuse_previous_keyframe``, with the chain through the keyframe before this
one. The combination's math is in ``chains.py``; here are which chains run, what they are
measured against and the error their covariances leave out."""

from __future__ import annotations

import numpy as np

from estimator.config import FrontendConfig
from estimator.formats.calibration import Rectification, StereoRig
from estimator.geometry import invert_pose
from estimator.odometry.chains import (
    Measured,
    combine_chain,
    inverse_covariance,
    link_bias_covariance,
)
from estimator.odometry.estimation import PoseEstimation
from estimator.odometry.frames import (
    CurrentFrame,
    Estimate,
    Reference,
    inlier_flow,
    sensitivities_of,
)
from estimator.odometry.observation import MeasurementKind
from estimator.odometry.references import References
from estimator.order_statistics import median
from estimator.rig_settings import common_rotation_bias

__all__ = ["ChainCombination", "chains_through_previous", "measurement_bias"]


def chains_through_previous(frontend: FrontendConfig, imu_fused: bool) -> bool:
    """``frontend.fuse_previous_frame``; unset, on only when no IMU is fused.

    Vision alone the chain through the previous frame lowers MH_01's rotation error per
    frame by a fifth; with the IMU the back end already smooths the rotation, and the
    chain's errors, shared by consecutive combined measurements, cost fused ATE
    (docs/frontend.md, "Tracking against a keyframe").
    """
    configured = frontend.fuse_previous_frame
    return configured if configured is not None else not imu_fused


def measurement_bias(estimate: Estimate, rate: float, rectification: Rectification) -> np.ndarray:
    """Covariance of a measurement's rotation error that does not average out over its
    points, from its inliers' image motion (``frontend.chain_link_rotation_bias``,
    chains.py): for a chain link, and for the keyframe measurement it is combined with."""
    if rate == 0.0:
        return np.zeros((6, 6))
    return link_bias_covariance(rate, inlier_flow(estimate, rectification), rectification.fx)


class ChainCombination:
    """The keyframe measurement combined with the chains through other references."""

    def __init__(
        self,
        frontend: FrontendConfig,
        rig: StereoRig,
        estimation: PoseEstimation,
        references: References,
        through_previous: bool,
    ) -> None:
        self.frontend = frontend
        self.rectification = rig.rectification
        self.estimation = estimation
        self.references = references
        self.through_previous = through_previous
        common = frontend.chain_common_rotation_bias
        # The keyframe measurement's error that the combination cannot average out, per unit
        # of its image motion (``frontend.chain_common_rotation_bias``; unset: the rig's).
        self.common_rate = common if common is not None else common_rotation_bias(rig).value

    def combined(self, estimate: Estimate, current: CurrentFrame) -> Estimate:
        """``estimate`` (against the keyframe) combined with the chains through the previous
        frame and through the keyframe before this one, each where it is on and measured."""
        references = self.references
        keyframe, previous, older = references.reference, references.previous, references.older
        combine_previous = (
            self.through_previous and previous is not keyframe and self._moving(estimate)
        )
        if previous is not None and combine_previous:
            covariance = references.reference_from_previous_covariance
            link = None
            if covariance is not None:
                link = Measured(
                    references.reference_from_previous, covariance, *references.previous_sensitivity
                )
            estimate, _ = self._through(estimate, previous, link, current)
        if older is not None and self.frontend.fuse_previous_keyframe:
            to_older = invert_pose(references.older_from_reference)
            covariance = inverse_covariance(
                references.older_from_reference, references.older_from_reference_covariance
            )
            estimate, tracked = self._through(
                estimate, older, Measured(to_older, covariance), current
            )
            if not tracked:
                references.older = None  # out of view: not tried again
        return estimate

    def _through(
        self,
        estimate: Estimate,
        reference: Reference,
        link: Measured | None,
        current: CurrentFrame,
    ) -> tuple[Estimate, bool]:
        """``estimate`` (against the keyframe) combined with the chain keyframe -> ``reference``
        -> current (``link`` = keyframe -> ``reference``), and whether ``reference`` was
        tracked; the estimate is kept as it was when either part has no covariance."""
        measured = estimate.reference_from_current
        if measured is None or estimate.covariance is None or link is None:
            return estimate, True
        prediction = invert_pose(link.pose) @ measured  # sharper than velocity
        span_ns = current.timestamp_ns - reference.timestamp_ns
        chained = self.estimation.measured(reference, prediction, current, span_ns)
        step = chained.reference_from_current
        if step is None or chained.covariance is None:
            return estimate, False
        self.estimation.observe(MeasurementKind.LINK, chained, current)
        step_covariance = chained.covariance + self.bias(chained)
        fused = combine_chain(
            Measured(measured, estimate.covariance, *sensitivities_of(estimate)),
            link,
            Measured(step, step_covariance, *sensitivities_of(chained)),
        )
        if fused is not None:
            # The same motion-proportional error that a link carries (``bias``) is in the
            # keyframe measurement too, and the blur of the current frame behind it errs
            # both estimates alike: the combination cannot average it out. Its covariance is
            # counted once on top of the combination's for the report and the back end; the
            # next frame's link takes the combination's alone (its own bias is added then).
            common = self.bias(estimate, self.common_rate)
            estimate.reference_from_current = fused.pose
            estimate.chain_covariance = fused.covariance
            estimate.covariance = fused.covariance + common
            estimate.sensitivity, estimate.reference_sensitivity = fused.current, fused.reference
            estimate.reported_covariance = None  # the combination's is the one to report
        return estimate, True

    def _moving(self, estimate: Estimate) -> bool:
        """Whether the keyframe measurement's inliers moved ``frontend.chain_min_flow_px`` or
        more in the image (median): the chain through the previous frame pays only then."""
        threshold = self.frontend.chain_min_flow_px
        if threshold == 0.0:
            return True
        moved = inlier_flow(estimate, self.rectification)
        return len(moved) > 0 and median(moved) >= threshold

    def bias(self, estimate: Estimate, rate: float | None = None) -> np.ndarray:
        """:func:`measurement_bias` at ``rate`` (None: a link's own,
        ``frontend.chain_link_rotation_bias``)."""
        if rate is None:
            rate = self.frontend.chain_link_rotation_bias
        return measurement_bias(estimate, rate, self.rectification)
