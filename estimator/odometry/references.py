"""The reference policy: which frames the next one is matched against, and the measured motion
(constant velocity, its rotation from the gyro when there is one) that predicts where it is."""

from __future__ import annotations

import numpy as np

from estimator.config import FrontendConfig
from estimator.frontend.stereo import StereoPoints
from estimator.frontend.temporal import PredictionUncertainty
from estimator.geometry import (
    invert_pose,
    rotation_angle_deg,
    rotation_vector,
    scale_motion,
)
from estimator.odometry.chains import PointSensitivity
from estimator.odometry.frames import Estimate, Reference, sensitivities_of
from estimator.odometry.gyro_prediction import GyroPrediction
from estimator.order_statistics import median
from estimator.types import ImuBatch

__all__ = ["References"]

_JITTER_NS = 1_000_000  # timestamp jitter tolerated by time limits
# A prediction over more than this many times the interval its motion was measured over
# bridges a gap (dropped frames): too uncertain for narrow windows.
_GAP_FACTOR = 2.0
# The level follows the largest recent prediction error: it rises at once (a turn begins)
# and falls by this factor per frame (a level 10x too high halves the window in 20 frames).
_LEVEL_DECAY = 0.9


class References:
    """The keyframe, the previous good frame and a last resort; the motion since them.

    All relative poses here are in the rectified left camera frame.
    """

    def __init__(self, frontend: FrontendConfig, gyro: GyroPrediction | None = None) -> None:
        self.frontend = frontend
        self.gyro = gyro  # the rotation between frames from the IMU (None: not used)
        self.reference: Reference | None = None  # keyframe (or previous frame)
        self.previous: Reference | None = None  # the last frame with an estimate
        self.fallback: Reference | None = None  # a later failed frame with enough points
        self.reference_from_previous = np.eye(4)  # rectified; for predicting the search
        # ... and its 6x6 covariance (right perturbation); None when not measured
        self.reference_from_previous_covariance: np.ndarray | None = None
        # ... and the estimate it came from, whose sensitivities to the previous frame's and
        # the keyframe's points the chain through the previous frame takes (odometry/chains.py)
        self.previous_estimate: Estimate | None = None
        # The keyframe before this one, with the keyframe's pose in it and its covariance,
        # while frames still register against it (None otherwise)
        self.older: Reference | None = None
        self.older_from_reference = np.eye(4)
        self.older_from_reference_covariance = np.zeros((6, 6))
        self.motion = np.eye(4)  # last measured motion (rectified), constant velocity ...
        self.motion_interval_ns = 1  # ... over this time: predictions scale it to theirs
        # The motion was measured by the last frame (not assumed, not left from before a
        # failed frame): only then are predictions good enough for narrow search windows.
        self.motion_measured = False
        # Decaying peak of what constant velocity missed, as accelerations (rad/s^2, m/s^2):
        # starts at the configured prior, then follows the session (a car turns 20x slower
        # than a hand-held or flying camera).
        self.angular_accel = float(np.radians(frontend.prediction_angular_accel_deg_s2))
        self.linear_accel = float(frontend.prediction_linear_accel_m_s2)
        self.last_fix_ns = 0  # timestamp of the last frame with a vision estimate

    def advance_gyro(self, imu: ImuBatch | None, now_ns: int) -> None:
        """Take the IMU samples since the last frame (before the frame is matched)."""
        if self.gyro is not None:
            self.gyro.advance(imu, now_ns)

    def motion_over(self, interval_ns: int) -> np.ndarray:
        """The last measured motion at the same velocity over ``interval_ns`` (rectified);
        its rotation is the gyro's when the span is the one since the last good frame."""
        motion = scale_motion(self.motion, interval_ns / self.motion_interval_ns)
        rotation = self._gyro_rotation(interval_ns)
        if rotation is not None:
            motion = motion.copy()
            motion[:3, :3] = rotation
        return motion

    def predicted_reference_from(self, now_ns: int) -> np.ndarray:
        """T_ref_cur predicted for a frame at ``now_ns`` (rectified): the measured keyframe ->
        previous frame step, then the last motion at the same velocity since the previous
        frame (a previous frame is set)."""
        assert self.previous is not None
        since_previous = self.motion_over(now_ns - self.previous.timestamp_ns)
        return self.reference_from_previous @ since_previous

    def velocity(self, interval_ns: int) -> tuple[np.ndarray, np.ndarray] | None:
        """The camera's predicted (angular rad/s, linear m/s) velocity in its own frame over
        the ``interval_ns`` since the last frame (rectified); None while there is no measured
        motion to predict from."""
        if not self.motion_measured or interval_ns <= 0:
            return None
        return _velocity(self.motion_over(interval_ns), interval_ns)

    def measured_velocity(self) -> tuple[np.ndarray, np.ndarray] | None:
        """The velocity of the motion the last frame measured (None: it measured none)."""
        if not self.motion_measured:
            return None
        return _velocity(self.motion, self.motion_interval_ns)

    def _gyro_rotation(self, span_ns: int) -> np.ndarray | None:
        return None if self.gyro is None else self.gyro.rotation_since_good(span_ns)

    def prediction_uncertainty(self, span_ns: int) -> PredictionUncertainty | None:
        """One sigma of the error of :meth:`motion_over` ``span_ns``: what the session's
        angular and linear acceleration levels do in that time (a T^2), or for the rotation
        the gyro's learned error (its rate error times T). None when the prediction is poor:
        no motion measured yet, the last frame failed, or ``span_ns`` bridges a gap."""
        if not self.motion_measured or span_ns > _GAP_FACTOR * self.motion_interval_ns:
            return None
        span_s2 = (max(span_ns, 0) * 1e-9) ** 2
        rotation_rad = self.angular_accel * span_s2
        if self.gyro is not None and self._gyro_rotation(span_ns) is not None:
            rotation_rad = self.gyro.sigma_rad(span_ns)
        return PredictionUncertainty(
            rotation_rad=rotation_rad, translation_m=self.linear_accel * span_s2
        )

    def _learn_prediction_error(self, motion: np.ndarray, interval_ns: int) -> None:
        """Fold in what the last motion, at constant velocity, missed of ``motion``."""
        span_s = interval_ns * 1e-9
        predicted = scale_motion(self.motion, interval_ns / self.motion_interval_ns)
        angle = np.radians(rotation_angle_deg(predicted[:3, :3].T @ motion[:3, :3]))
        shift = float(np.linalg.norm(motion[:3, 3] - predicted[:3, 3]))
        self.angular_accel = max(angle / span_s**2, _LEVEL_DECAY * self.angular_accel)
        self.linear_accel = max(shift / span_s**2, _LEVEL_DECAY * self.linear_accel)

    def keyframe_translation_m(self) -> float:
        """Translation from the keyframe beyond which a frame becomes the next keyframe:
        ``keyframe_max_parallax`` times the median depth of the keyframe's points when that is
        set (and the metre threshold is not configured), else ``keyframe_max_translation_m``."""
        frontend = self.frontend
        parallax = frontend.keyframe_max_parallax
        explicit = "keyframe_max_translation_m" in frontend.model_fields_set
        if parallax is None or explicit or self.reference is None:
            return frontend.keyframe_max_translation_m
        depth = self.reference.points.points[:, 2]
        if len(depth) == 0:
            return frontend.keyframe_max_translation_m
        return parallax * median(depth)

    @property
    def previous_sensitivity(self) -> tuple[PointSensitivity | None, PointSensitivity | None]:
        """How keyframe -> previous moves with the previous frame's and the keyframe's points
        (None: not known); formed on first use (``sensitivities_of``)."""
        if self.previous_estimate is None:
            return None, None
        return sensitivities_of(self.previous_estimate)

    def held(self, now_ns: int) -> bool:
        """Whether a frame without an estimate at ``now_ns`` holds the pose: the last vision fix
        is more than ``frontend.max_coast_s`` old (1 ms more for timestamp jitter)."""
        elapsed_ns = now_ns - self.last_fix_ns
        return elapsed_ns > self.frontend.max_coast_s * 1e9 + _JITTER_NS

    def update(
        self,
        index: int,
        points: StereoPoints,
        image: np.ndarray,
        pose: np.ndarray,
        estimate: Estimate,
        timestamp_ns: int,
    ) -> None:
        """Keep the keyframe while it still tracks well; otherwise this frame becomes it.

        A failed frame (black, blurred, or just not registered) replaces neither the keyframe
        nor the previous frame while the pose coasts: the next frame is matched against the
        last good ones at once, with the prediction scaled to the time since them, so the
        failure does not reach later frames. A failed frame with enough points is kept as a
        last resort (when the view has moved on, the next frame may only match it); once the
        pose is held such a frame becomes the new reference, so that tracking restarts.
        """
        frontend = self.frontend
        current = Reference(index, int(timestamp_ns), points, image, pose)
        reference_from_current = estimate.reference_from_current
        first = self.reference is None
        failed = reference_from_current is None and not first
        was_measured = self.motion_measured
        self.motion_measured = reference_from_current is not None
        self._gyro_frame_done(failed, estimate)
        if not failed:
            self.last_fix_ns = int(timestamp_ns)
        if failed:
            held = self.held(int(timestamp_ns))
            if held:
                self.motion = np.eye(4)  # the pose is held from now on
            usable = len(points) >= frontend.keyframe_min_inliers
            if usable:
                self.fallback = current  # the last resort if the good references fail
            if not held or not usable:
                return  # keep the last good references
        elif reference_from_current is not None:
            assert self.previous is not None and estimate.reference is not None
            if estimate.reference is self.reference:
                motion = invert_pose(self.reference_from_previous) @ reference_from_current
                since_ns = self.previous.timestamp_ns
            else:
                motion = reference_from_current  # measured against a later frame
                since_ns = estimate.reference.timestamp_ns
            interval_ns = max(int(timestamp_ns) - since_ns, 1)
            if was_measured:
                self._learn_prediction_error(motion, interval_ns)
            self.motion, self.motion_interval_ns = motion, interval_ns
        self.fallback = None
        if first or failed or self._needs_new_reference(estimate):
            self._keep_older(estimate)
            self.reference = current
            self.reference_from_previous = np.eye(4)
            self.reference_from_previous_covariance = np.zeros((6, 6))
            self.previous_estimate = None
        else:
            self._link_previous(estimate)
        self.previous = current

    def go_back_to(self, keyframe: Reference, estimate: Estimate) -> None:
        """An older ``keyframe`` is the reference again, the last frame measured in it by
        ``estimate`` (a keyframe revisit, odometry/revisits.py)."""
        self.reference = keyframe
        self.older = None
        self._link_previous(estimate)

    def _link_previous(self, estimate: Estimate) -> None:
        """The frame ``estimate`` measured in the reference is the previous one: the link the
        next frame is predicted and chained by (the combination's covariance when a chain was
        combined into it)."""
        assert estimate.reference_from_current is not None
        self.reference_from_previous = estimate.reference_from_current
        self.reference_from_previous_covariance = (
            estimate.covariance if estimate.chain_covariance is None
            else estimate.chain_covariance
        )  # fmt: skip
        self.previous_estimate = estimate

    def _gyro_frame_done(self, failed: bool, estimate: Estimate) -> None:
        """The gyro learns from vision's rotation since the last good frame (the previous)."""
        if self.gyro is None:
            return
        measured = None
        current = estimate.reference_from_current
        if current is not None and estimate.reference is self.reference:
            measured = (invert_pose(self.reference_from_previous) @ current)[:3, :3]
        self.gyro.frame_done(not failed, measured)

    def _keep_older(self, estimate: Estimate) -> None:
        """The keyframe being replaced stays as a second reference when the new one was
        measured against it with a covariance."""
        measured = estimate.reference_from_current
        if measured is None or estimate.covariance is None or estimate.reference is None:
            self.older = None
            return
        if estimate.reference is not self.reference:
            self.older = None
            return
        self.older = self.reference
        self.older_from_reference = measured
        self.older_from_reference_covariance = estimate.covariance

    def _needs_new_reference(self, estimate: Estimate) -> bool:
        frontend = self.frontend
        if frontend.tracking == "frame" or estimate.reference is not self.reference:
            return True
        motion = estimate.reference_from_current
        assert estimate.result is not None and motion is not None
        return bool(
            estimate.result.inliers.sum() < frontend.keyframe_min_inliers
            or np.linalg.norm(motion[:3, 3]) > self.keyframe_translation_m()
            or rotation_angle_deg(motion[:3, :3]) > frontend.keyframe_max_rotation_deg
        )


def _velocity(motion: np.ndarray, interval_ns: int) -> tuple[np.ndarray, np.ndarray]:
    """(angular rad/s, linear m/s) of ``motion`` (T_earlier_later) over ``interval_ns``."""
    seconds = interval_ns * 1e-9
    angular = rotation_vector(motion[:3, :3]) / seconds
    return angular, motion[:3, 3] / seconds
