"""The factor graph: front-end relative poses + IMU factors + a motion prior (docs/backend.md).

``FusionBackend`` reads as the steps of a frame; each concern lives in a module of its own:
the smoother and its keys (``smoother.py``), the frames it still holds and their final
estimates (``window.py``), the IMU factors (``imu_terms.py``), the front end's relative pose
as a gated factor (``vision_factors.py``, with the outlier gate in ``gating.py``), the motion
prior (``motion_prior.py``), the start-up standstill (``standstill.py``), the priors a graph
starts from (``anchor.py``) and, as an option, the inliers as stereo landmarks
(``landmarks.py``).

Per frame k (one Pose3, body in world, and with an IMU one gyro bias): the front-end relative
pose as a robust ``BetweenFactorPose3`` from the frame it was measured against (a keyframe) to
X_k, with its 6x6 covariance (``noise.py``), unless it fails the outlier gate; the IMU factors;
otherwise the constant-velocity motion prior. ``pose`` is the newest frame's estimate when it
arrives; the final, smoothed estimate of a frame is handed out once when it leaves the window
(``FusedEstimate.final_poses``, then ``flush()``). World: the first body pose, levelled (z up,
yaw 0) from the first frame's accelerometer samples when the IMU is used.
"""

from __future__ import annotations

from dataclasses import replace
from typing import Any

import gtsam
import numpy as np

from estimator.backend.anchor import Anchor, InertialPrior
from estimator.backend.answer import SmoothedAnswer
from estimator.backend.covariance_scale import GyroCalibration
from estimator.backend.estimate import FusedEstimate, check_pose
from estimator.backend.imu import GRAVITY, SpecificForceDelta, gravity_aligned_rotation
from estimator.backend.imu_terms import ImuTerms
from estimator.backend.motion_prior import add_motion_prior, constant_velocity
from estimator.backend.noise import relative_pose_covariance
from estimator.backend.observations import StereoObservations
from estimator.backend.recording import BackendFrame, BackendObserver, BackendSetup
from estimator.backend.smoother import (
    ACCEL_BIAS_KEY,
    GRAVITY_KEY,
    STAMP_MARGIN_S,
    Smoother,
    bias_key,
    pose_key,
)
from estimator.backend.standstill import StartupRest
from estimator.backend.step import Step
from estimator.backend.systematic_noise import shared_error_growth
from estimator.backend.vision_factors import PreviousFrame, VisionFactors
from estimator.backend.window import FrameWindow, OpenFrame
from estimator.config import BackendConfig
from estimator.geometry import invert_pose, make_pose, nearest_rigid, se3_adjoint
from estimator.types import FrameStatus, ImuBatch, ImuNoise, check_timestamp_order

__all__ = ["FusedEstimate", "FusionBackend"]

class FusionBackend:
    """Incremental fusion of per-frame relative poses with the IMU (see module doc)."""

    def __init__(
        self,
        config: BackendConfig,
        body_from_camera: np.ndarray,
        imu_noise: ImuNoise | None,
        observer: BackendObserver | None = None,
    ) -> None:
        """``observer``, when given, sees the construction and every frame (recording.py)."""
        self._observer = observer
        if observer is not None:
            observer(BackendSetup(config, body_from_camera, imu_noise))
        self.config = config
        if config.body_from_camera is not None:
            body_from_camera = np.asarray(config.body_from_camera, dtype=float).reshape(4, 4)
        self.body_from_camera = nearest_rigid(check_pose("body_from_camera", body_from_camera))
        self.camera_from_body = invert_pose(self.body_from_camera)
        self._adjoint = se3_adjoint(self.body_from_camera)
        self.use_imu = bool(config.use_imu and imu_noise is not None)
        self._use_accel = bool(self.use_imu and config.use_accelerometer)
        self._calibration = GyroCalibration(config, self.body_from_camera) if self.use_imu else None
        self._shared_error_growth = shared_error_growth(config)
        self._answer = SmoothedAnswer(config.answer_smoothing_s or 0.0)
        self._imu: ImuTerms | None = None
        if self.use_imu:
            assert imu_noise is not None
            self._imu = ImuTerms(config, imu_noise, self._use_accel)
        self._gravity = np.array([0.0, 0.0, -GRAVITY])  # world, latest estimate
        self._accel_bias = np.zeros(3)
        self._smoother = Smoother(config)
        self._window = FrameWindow(self._smoother, self.body_from_camera)
        self._vision = VisionFactors(config, self.body_from_camera, self._smoother, self._window)
        self._index = -1
        self._last_ns = 0
        self._body_pose = np.eye(4)
        self._previous_motion: np.ndarray | None = None  # body T_k-2,k-1 (estimated)
        self._previous_dt = 0.0
        self._bias = np.zeros(3)
        self._rest = StartupRest(
            config,
            self._imu.noise if self._imu is not None else None,
            bool(self.use_imu and config.static_init),
        )

    # ------------------------------------------------------------------ public

    @property
    def frame_count(self) -> int:
        return self._index + 1

    @property
    def rest_summary(self) -> tuple[float, np.ndarray] | None:
        """(duration s, mean gyro) of the start-up rest once it has ended."""
        return self._rest.summary

    @property
    def smoother(self) -> Smoother:
        """The smoother (graph, keys, estimates): what the window holds, for inspection."""
        return self._smoother

    @property
    def landmark_count(self) -> int:
        """Stereo landmarks in the window (0 without ``config.landmarks``)."""
        return self._vision.landmark_count

    def add_frame(
        self,
        timestamp_ns: int,
        relative_pose: np.ndarray | None,
        inlier_residuals: np.ndarray | None,
        inlier_count: int,
        imu: ImuBatch | None,
        reference_ns: int | None = None,
        inlier_points: np.ndarray | None = None,
        covariance: np.ndarray | None = None,
        stereo: StereoObservations | None = None,
    ) -> FusedEstimate:
        """Add frame ``timestamp_ns``; ``relative_pose`` is the front-end T_ref_cur (camera).

        ``reference_ns`` is the timestamp of the frame the relative pose was measured against
        (a keyframe); None means the previous frame. A keyframe measurement ties the two frames
        directly, so its error is not chained through the frames in between.
        ``inlier_points`` (N, 3), the registration inliers in the current left camera frame,
        give the relative pose its full covariance (rotation and translation errors of a fit
        are strongly correlated); without them it gets the diagonal one from the residuals.
        ``covariance`` (6, 6), the relative pose's own covariance in the camera frame (GTSAM
        tangent, right perturbation) when the front end computed one (the Mahalanobis
        refinement), takes precedence over both. ``stereo``, the inliers' pixels in both
        frames, adds them as landmarks when ``config.landmarks`` is on (``landmarks.py``).
        """
        if self._observer is not None:
            arguments = {
                "relative_pose": relative_pose, "inlier_residuals": inlier_residuals,
                "inlier_count": inlier_count, "imu": imu, "reference_ns": reference_ns,
                "inlier_points": inlier_points, "covariance": covariance, "stereo": stereo,
            }  # fmt: skip
            self._observer(BackendFrame(timestamp_ns, arguments))
        timestamp_ns = int(timestamp_ns)
        check_timestamp_order(timestamp_ns, self._last_ns if self._index >= 0 else None)
        if inlier_count < 0:
            raise ValueError(f"inlier_count must be >= 0, got {inlier_count}")
        if relative_pose is None:
            covariance = None
        else:
            relative_pose = check_pose("relative_pose", relative_pose)
            covariance = relative_pose_covariance(
                covariance, inlier_points, inlier_residuals, inlier_count, self.config
            )
            # Into the body frame: T_BS T Exp(xi) T_SB = (T_BS T T_SB) Exp(Ad(T_BS) xi).
            covariance = self._adjoint @ covariance @ self._adjoint.T
        if imu is not None and self._imu is not None:
            self._imu.buffer.extend(imu)
        if self._index < 0:
            return self._start(timestamp_ns)
        return self._advance(timestamp_ns, relative_pose, covariance, reference_ns, stereo)

    def state(self) -> dict[str, Any]:
        """The estimates a continuation in another process starts from (JSON-ready)."""
        return {
            "gyro_bias": self._bias.tolist(),
            "accel_bias": self._accel_bias.tolist(),
            "gravity": self._gravity.tolist(),
            "covariance_scale": self._calibration.state() if self._calibration else None,
        }

    def restore(self, state: dict[str, Any]) -> None:
        """Start from another instance's biases instead of looking for rest (before frame 0).

        The smoother itself starts afresh at the next frame (its world is levelled again from
        that frame's accelerometer samples); the gyro bias is its prior mean.
        """
        if self._index >= 0:
            raise ValueError("restore() must come before the first frame")
        self._bias = np.asarray(state["gyro_bias"], dtype=float).reshape(3)
        self._accel_bias = np.asarray(state["accel_bias"], dtype=float).reshape(3)
        self._gravity = np.asarray(state["gravity"], dtype=float).reshape(3)
        if self._calibration is not None and state.get("covariance_scale"):
            self._calibration.restore(state["covariance_scale"])
        self._rest.starting = False

    def flush(self) -> tuple[tuple[int, np.ndarray], ...]:
        """Final estimates of the frames still in the smoother (end of a run), oldest first."""
        self._window.finish_before(float("inf"))
        return self._window.take_final_poses()

    # ------------------------------------------------------------------ the first frame

    def _start(self, timestamp_ns: int) -> FusedEstimate:
        self._index = 0
        self._smoother.start_ns = self._last_ns = self._vision.last_fix_ns = timestamp_ns
        rotation, levelled, message = self._level(timestamp_ns)
        gyro_bias = None
        if self._imu is not None:
            bias_mean = self._bias.copy()  # zero unless restored from another instance
            bias_sigma = self.config.gyro_bias_prior_sigma
            if self._rest.starting:
                bias_mean, bias_sigma, note = self._rest.before_first_frame(
                    self._imu.buffer, timestamp_ns + self._imu.offset_ns
                )
                if note:
                    message += "; " + note
            gyro_bias = (bias_mean, bias_sigma)
        self._body_pose = make_pose(rotation, np.zeros(3))
        inertial = None
        if self._use_accel:
            # Levelled: gravity is -z up to the tilt error of an accelerometer that may already
            # see motion; otherwise its direction in the first body frame is unknown.
            self._gravity = np.array([0.0, 0.0, -GRAVITY]) if levelled else np.zeros(3)
            gravity_sigma = self.config.gravity_prior_sigma if levelled else 2.0 * GRAVITY
            inertial = self._inertial_prior(gravity_sigma)
        factors, values, keys = Anchor(0, self._body_pose, gyro_bias, inertial).graph()
        self._smoother.update(factors, values, keys, self._last_ns)
        return self._estimate(FrameStatus.OK, message)

    def _level(self, timestamp_ns: int) -> tuple[np.ndarray, bool, str]:
        """World rotation from the first frame's accelerometer samples (z up), when used."""
        if self._imu is None or not self.config.gravity_align:
            return np.eye(3), False, "world = first body pose"
        buffer = self._imu.buffer
        accel = buffer.accel[buffer.timestamps_ns <= timestamp_ns + self._imu.offset_ns]
        if not len(accel):
            no_samples = "world = first body pose (no accelerometer samples with frame 0)"
            return np.eye(3), False, no_samples
        try:
            rotation = gravity_aligned_rotation(accel)
        except ValueError as error:
            return np.eye(3), False, f"world = first body pose ({error})"
        return rotation, True, f"world gravity-aligned from {len(accel)} accelerometer samples"

    def _inertial_prior(self, gravity_sigma: float) -> InertialPrior:
        return InertialPrior(
            self._gravity, gravity_sigma, self._accel_bias, self.config.accel_bias_prior_sigma
        )

    # ------------------------------------------------------------------ one frame

    def _advance(
        self,
        timestamp_ns: int,
        relative_pose: np.ndarray | None,
        covariance: np.ndarray | None,
        reference_ns: int | None = None,
        stereo: StereoObservations | None = None,
    ) -> FusedEstimate:
        """One frame: its factors (IMU, vision, motion prior, standstill), the update, status."""
        dt = (timestamp_ns - self._last_ns) * 1e-9
        stamp = self._smoother.stamp(timestamp_ns)
        step = Step(
            previous=self._index,
            current=self._index + 1,
            dt=dt,
            stamp=stamp,
            cutoff=stamp - self.config.smoother_lag_s,  # keys stamped before it are dropped now
            timestamp_ns=timestamp_ns,
        )
        step.keys.append(pose_key(step.current))
        self._add_imu(step, timestamp_ns, relative_pose, covariance, reference_ns)
        motion = constant_velocity(self._previous_motion, self._previous_dt, dt)
        inertial = None
        if self._imu is not None:
            inertial = self._imu.inertial_factor(
                step, self._window, self._body_pose, self._gravity, self._accel_bias
            )
        prediction = self._prediction(step, motion, inertial)
        previous = PreviousFrame(
            self._body_pose, self._last_ns, self._previous_motion, self._previous_dt
        )
        guess = self._vision.add(
            step, previous, relative_pose, self._weighed(covariance), reference_ns, prediction,
            stereo,
        )  # fmt: skip
        if self.config.motion_prior == "always" or not (step.accepted or inertial is not None):
            add_motion_prior(step, motion, self.config)
        guess = self._rest.add(step, guess)
        step.values.insert(
            pose_key(step.current), gtsam.Pose3(nearest_rigid(self._body_pose @ guess))
        )
        previous_pose = self._commit(step, timestamp_ns, guess)
        status = self._status(step)
        self._previous_motion = invert_pose(previous_pose) @ self._smoother.pose(step.current)
        self._previous_dt = dt
        estimate = self._estimate(
            status, "; ".join(step.notes), self._previous_motion.copy(), step.delta
        )
        return replace(estimate, vision_rejected=step.rejected)

    def _weighed(self, covariance: np.ndarray | None) -> np.ndarray | None:
        """The measurement covariance the graph weighs (and gates with).

        With ``covariance_scale_factors`` it is inflated by the session factor measured
        against the gyro when that factor exceeds 1 (the calibration itself keeps comparing
        the covariance as handed over). Only inflated: where the noise model is conservative
        (rendered flights, factor 0.2-0.5) trusting vision more did not help the fused answer.
        """
        if covariance is None or not self.config.covariance_scale_factors:
            return covariance
        if self._calibration is None:
            return covariance
        return max(self._calibration.value, 1.0) * covariance

    def _add_imu(
        self,
        step: Step,
        timestamp_ns: int,
        relative_pose: np.ndarray | None,
        covariance: np.ndarray | None,
        reference_ns: int | None,
    ) -> None:
        """The interval's rest test, gyro factors and the covariance calibration's sample."""
        if self._imu is not None and self._rest.starting:
            offset = self._imu.offset_ns
            step.rest_samples = self._rest.interval(
                self._imu.buffer, self._last_ns + offset, timestamp_ns + offset
            )
        step.still = step.rest_samples is not None
        if self._imu is not None:
            self._imu.add_factors(step, self._last_ns, timestamp_ns, self._bias)
        if self._calibration is not None:
            reference = reference_ns if reference_ns is not None else self._last_ns
            self._calibration.add_frame(
                timestamp_ns, step.preintegration, reference, relative_pose, covariance, self._bias
            )

    def _prediction(
        self,
        step: Step,
        motion: np.ndarray,
        inertial: tuple[gtsam.CustomFactor, np.ndarray] | None,
    ) -> np.ndarray:
        """Body motion expected for this frame (initial guess and outlier gate): gyro rotation
        (else constant velocity) with the IMU's translation (else constant velocity). Adds the
        inertial factor when there is one."""
        prediction = motion.copy()
        if step.preintegration is not None:
            prediction[:3, :3] = step.preintegration.delta_rotation
        if inertial is not None:
            step.factors.add(inertial[0])
            prediction[:3, 3] = self._body_pose[:3, :3].T @ (inertial[1] - self._body_pose[:3, 3])
        return prediction

    # ------------------------------------------------------------------ update and answer

    def _commit(self, step: Step, timestamp_ns: int, guess: np.ndarray) -> np.ndarray:
        """Update the smoother with the step (restarting it after a numerical failure).

        Returns the previous frame's pose estimate after the update.
        """
        previous = step.previous
        # The previous frame's keys would be marginalised by this update when the gap exceeds
        # the lag (its estimate is needed just below): restamped, it stays in the window.
        if self._window.open[previous].stamp_s <= step.cutoff + STAMP_MARGIN_S:
            step.keep += [pose_key(previous)] + ([bias_key(previous)] if self.use_imu else [])
            self._window.open[previous].stamp_s = step.stamp
        if self._use_accel:
            step.keep += [GRAVITY_KEY, ACCEL_BIAS_KEY]
        self._last_ns = timestamp_ns
        self._index = step.current
        self._window.finish_before(step.cutoff)
        try:
            self._smoother.update(
                step.factors, step.values, step.keys, self._last_ns, tuple(step.keep)
            )
            return self._smoother.pose(previous)
        except RuntimeError as error:  # numerical failure inside GTSAM: restart the graph
            self._window.finish_before(float("inf"), read=False)
            self._restart(step.current, self._body_pose @ guess)
            reason = str(error).strip().splitlines()[0]
            step.notes.append(f"back end restarted at this frame ({reason})")
            return self._body_pose

    def _restart(self, index: int, body_pose: np.ndarray) -> None:
        """A fresh smoother anchored at ``body_pose``: the trajectory goes on from here."""
        self._smoother.reset()
        self._vision.reset()
        self._answer.reset()
        gyro_bias = (self._bias, self.config.gyro_bias_prior_sigma) if self.use_imu else None
        inertial = (
            self._inertial_prior(self.config.gravity_prior_sigma) if self._use_accel else None
        )
        factors, values, keys = Anchor(index, body_pose, gyro_bias, inertial).graph()
        self._smoother.update(factors, values, keys, self._last_ns)

    def _status(self, step: Step) -> FrameStatus:
        """OK with accepted vision, else DEGRADED (gyro) or LOST; notes the last fix."""
        if step.accepted:
            self._vision.last_fix_index, self._vision.last_fix_ns = step.current, self._last_ns
            return FrameStatus.OK
        if step.preintegration is not None:
            step.notes.insert(0, "no vision: rotation from gyro, translation from motion prior")
            return FrameStatus.DEGRADED
        step.notes.insert(0, "no vision, no gyro: pose from the constant-velocity prior")
        return FrameStatus.LOST

    def _estimate(
        self,
        status: FrameStatus,
        message: str,
        motion: np.ndarray | None = None,
        delta: SpecificForceDelta | None = None,
    ) -> FusedEstimate:
        """Read the newest frame's estimates, open it in the window and build the answer."""
        self._body_pose = self._smoother.pose(self._index)
        self._window.remember(self._last_ns, self._index, self._body_pose)
        self._window.open[self._index] = OpenFrame(
            self._index,
            self._last_ns,
            self._smoother.stamp(self._last_ns),
            delta,
            self._body_pose.copy(),
        )
        bias = None
        if self.use_imu:
            self._bias = self._smoother.bias(self._index)
            bias = self._bias.copy()
        if self._use_accel:
            self._gravity = self._smoother.vector(GRAVITY_KEY)
            self._accel_bias = self._smoother.vector(ACCEL_BIAS_KEY)
        covariance, motion_covariance = self._smoother.marginals(self._index, motion)
        answer = self._answer.update(self._body_pose, motion, self._previous_dt)
        if covariance is not None and self.use_imu:
            covariance = self._shared_error_growth * covariance
        placement = self._vision.placement
        covariance = placement.report(self._index, self._body_pose, covariance)
        placement.forget_before(self._window.oldest_reference, self._window.kept_indices())
        return FusedEstimate(
            pose=answer @ self.body_from_camera,
            body_pose=answer,
            status=status,
            message=message,
            gyro_bias=bias,
            body_motion=motion,
            final_poses=self._window.take_final_poses(),
            gravity=self._gravity.copy() if self._use_accel else None,
            accel_bias=self._accel_bias.copy() if self._use_accel else None,
            body_covariance=covariance,
            body_motion_covariance=motion_covariance,
            covariance_scale=self._calibration.value if self._calibration is not None else 1.0,
            pose_covariance_scale=self._calibration.pose_value if self._calibration else 1.0,
        )
