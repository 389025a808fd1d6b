"""The factor graph: front-end relative poses + gyro rotation factors + a motion prior.

(About 950 lines: one class owns the smoother and its per-frame state; each step of a frame,
``FusionBackend._advance``, is a method of its own that fits on a screen.)

One Pose3 per frame (body in world) and, with an IMU, one gyro bias per frame. Per frame k:

* the front-end relative pose (left camera, moved into the body frame) as a robust
  ``BetweenFactorPose3`` from the frame it was measured against (a keyframe) to X_k, with the
  full 6x6 covariance of the rigid fit when the inlier points are given (``noise.py``),
  unless it fails the outlier gate against the prediction (gyro rotation, constant-velocity
  translation);
* the gyro preintegrated over the frame interval (shifted by the camera-IMU time offset) as a
  rotation factor on (X_k-1, X_k, B_k-1) (``factors.py``) and a bias random walk B_k-1 -> B_k;
* with the accelerometer, the inertial factor on (X_k-2, X_k-1, X_k, G, A): their velocity
  change against the preintegrated specific force, with world gravity G and accelerometer
  bias A as variables of the graph (``inertial.py``); it carries the translation through
  vision gaps;
* otherwise a constant-velocity prior X_k-1 -> X_k (the previous estimated motion, rescaled to
  this interval) with a loose covariance, on frames without an accepted relative pose (or on
  every frame with ``motion_prior="always"``); with the gyro present its rotation part is left
  free so it cannot bend the bias.

Smoothed output: ``pose`` is the newest frame's estimate when it arrives (a filter answer);
the smoother keeps revising a frame until it leaves the window, and that final estimate is
handed out once (``FusedEstimate.final_poses``, then ``flush()`` at the end of a run).

Static initialisation (``rest.py``), with the IMU: when the samples before the first frame
show the platform at rest, the first gyro bias gets the prior mean gyro +- density / sqrt(T)
(with the bias walk) instead of 0 +- ``gyro_bias_prior_sigma``; and for as long as every frame
interval from the start shows rest too (IMU tests, and the relative pose when vision has one),
consecutive poses are tied by a tight zero-motion factor. The gyro factors of those intervals
then estimate the bias in the graph exactly as the mean gyro would, with no sample used twice.
The first interval that moves ends the start-up for good.

World frame: the first body pose, rotated so that z is up (roll and pitch from the mean
accelerometer reading of the first frame's IMU batch, yaw = 0) when the IMU is used; without
IMU (or without accelerometer data with the first frame) the world is the first body pose.
"""

from __future__ import annotations

import math
from collections import OrderedDict
from dataclasses import dataclass, field, replace
from typing import Any

import gtsam
import numpy as np

from estimator.backend.covariance_scale import GyroCalibration
from estimator.backend.factors import gyro_rotation_factor
from estimator.backend.imu import (
    GRAVITY,
    GyroPreintegration,
    ImuBuffer,
    SpecificForceDelta,
    gravity_aligned_rotation,
    preintegrate_gyro,
    preintegrate_specific_force,
    rotation_params,
)
from estimator.backend.inertial import (
    InertialTerms,
    inertial_factor,
    inertial_factor_sigma,
    predict_position,
)
from estimator.backend.noise import (
    fit_covariance,
    measured_covariance,
    pose_noise,
    relative_pose_sigmas,
    robust,
    sigma_covariance,
)
from estimator.backend.rest import RestWindow, at_rest
from estimator.config import BackendConfig
from estimator.geometry import invert_pose, make_pose, nearest_rigid
from estimator.types import FrameStatus, ImuBatch, ImuNoise, check_timestamp_order

__all__ = ["FusedEstimate", "FusionBackend"]

# The first pose defines the world: pinned with a tight prior.
_ORIGIN_SIGMA = 1e-6
# Rotation spread added to the gyro prediction in the outlier gate: covers an unconverged gyro
# bias (0.1 rad/s over the frame interval, at least 50 ms) and small camera-IMU misalignment.
_GATE_GYRO_FLOOR_RAD = 0.005
_GATE_GYRO_BIAS_RATE = 0.1  # rad/s
# Rotation sigma of the motion prior when the gyro provides the rotation (effectively free).
_FREE_ROTATION_SIGMA = 10.0
# A relative pose within this squared Mahalanobis distance of the identity (6 DOF, 99.9 %)
# agrees with a standstill.
_STILL_CHI2 = 22.46
# A key is used by new factors only if its smoother stamp is this far inside the window.
_STAMP_MARGIN_S = 1e-6


def _pose_key(index: int) -> int:
    return gtsam.symbol("x", index)


def _bias_key(index: int) -> int:
    return gtsam.symbol("b", index)


# World gravity and accelerometer bias: one variable each, restamped with every update so the
# fixed-lag smoother keeps them (marginalising old frames folds their information in).
_GRAVITY_KEY = gtsam.symbol("g", 0)
_ACCEL_BIAS_KEY = gtsam.symbol("a", 0)


@dataclass(frozen=True)
class FusedEstimate:
    """The back end's answer for one frame."""

    pose: np.ndarray  # (4, 4) left camera in world
    body_pose: np.ndarray  # (4, 4) body (IMU) in world
    status: FrameStatus
    message: str = ""
    gyro_bias: np.ndarray | None = None  # (3,) rad/s, current estimate (None without IMU)
    # Body motion T_prev_cur as estimated now (the previous pose is revised too, so this is
    # smoother than the difference of two consecutive ``body_pose`` outputs).
    body_motion: np.ndarray | None = None
    # Earlier frames the smoother has finished with at this frame: (timestamp_ns, left camera
    # pose in world) with their final, smoothed estimate; each frame appears once.
    final_poses: tuple[tuple[int, np.ndarray], ...] = ()
    # With the accelerometer: world gravity (m/s^2) and accelerometer bias, current estimates.
    gravity: np.ndarray | None = None
    accel_bias: np.ndarray | None = None
    # Marginal covariances (GTSAM tangent: rotation then translation, right perturbation in
    # the body frame) of ``body_pose`` and of ``body_motion``, from the smoother's Bayes tree.
    body_covariance: np.ndarray | None = None
    body_motion_covariance: np.ndarray | None = None
    # The frame's relative pose failed the outlier gate: the front end must not learn from it
    # (noise level, reference frame) either.
    vision_rejected: bool = False
    # Factor on the covariances reported for this frame, measured against the gyro
    # (``covariance_scale.py``; 1 without an IMU). The graph's own noise does not use it.
    covariance_scale: float = 1.0
    pose_covariance_scale: float = 1.0  # the pose's growth: raised through episodes as well


@dataclass
class _OpenFrame:
    """A frame the smoother still holds: what is needed to finish it."""

    index: int
    timestamp_ns: int
    stamp_s: float  # smoother time of its keys
    delta: SpecificForceDelta | None  # accelerometer over the interval ending here
    body_pose: np.ndarray = field(default_factory=lambda: np.eye(4))  # latest estimate


@dataclass
class _Step:
    """One frame's additions to the graph while ``FusionBackend._advance`` builds them."""

    previous: int
    current: int
    dt: float
    stamp: float  # smoother time of the new keys
    cutoff: float  # keys stamped before it are dropped by this update
    factors: gtsam.NonlinearFactorGraph = field(default_factory=gtsam.NonlinearFactorGraph)
    values: gtsam.Values = field(default_factory=gtsam.Values)
    keys: list[int] = field(default_factory=list)
    keep: list[int] = field(default_factory=list)  # existing keys to restamp
    notes: list[str] = field(default_factory=list)
    preintegration: GyroPreintegration | None = None
    delta: SpecificForceDelta | None = None
    rest_samples: ImuBatch | None = None  # the interval's IMU if it continues the rest
    still: bool = False
    accepted: bool = False  # the relative pose passed the gate
    rejected: bool = False  # the relative pose failed the gate


_EYE3 = np.eye(3)
_BOTTOM_ROW = np.array([0.0, 0.0, 0.0, 1.0])


def _check_pose(name: str, pose: np.ndarray) -> np.ndarray:
    pose = np.asarray(pose, dtype=float)
    if pose.shape != (4, 4):
        raise ValueError(f"{name} must be a 4x4 matrix, got shape {pose.shape}")
    if not np.all(np.isfinite(pose)):
        raise ValueError(f"{name} contains NaN or inf")
    rotation = pose[:3, :3]
    # Plain max-abs tests (np.allclose costs ~15 us each, on every frame).
    if np.abs(rotation @ rotation.T - _EYE3).max() > 1e-5 or np.linalg.det(rotation) < 0:
        raise ValueError(f"{name} does not have a proper rotation block")
    if np.abs(pose[3] - _BOTTOM_ROW).max() > 1e-5:
        raise ValueError(f"{name} bottom row must be [0, 0, 0, 1]")
    return pose


class FusionBackend:
    """Incremental fusion of per-frame relative poses with the gyro (see module doc)."""

    def __init__(
        self,
        config: BackendConfig,
        body_from_camera: np.ndarray,
        imu_noise: ImuNoise | None,
    ) -> None:
        self.config = config
        if config.body_from_camera is not None:
            body_from_camera = np.asarray(config.body_from_camera, dtype=float).reshape(4, 4)
        self.body_from_camera = nearest_rigid(_check_pose("body_from_camera", body_from_camera))
        self.camera_from_body = invert_pose(self.body_from_camera)
        self._adjoint = np.asarray(gtsam.Pose3(self.body_from_camera).AdjointMap())
        self.use_imu = bool(config.use_imu and imu_noise is not None)
        self._calibration = GyroCalibration(config, self.body_from_camera) if self.use_imu else None
        self._imu_params = None
        self._bias_sigma_density = 0.0
        self._imu_noise: ImuNoise | None = None
        if self.use_imu:
            assert imu_noise is not None
            scale = config.imu_noise_scale
            self._imu_noise = replace(
                imu_noise,
                gyro_noise_density=imu_noise.gyro_noise_density * scale,
                accel_noise_density=imu_noise.accel_noise_density * scale,
                gyro_random_walk=imu_noise.gyro_random_walk * scale,
                accel_random_walk=imu_noise.accel_random_walk * scale,
            )
            self._imu_params = rotation_params(imu_noise, config.imu_noise_scale)
            self._bias_sigma_density = (
                config.gyro_random_walk
                if config.gyro_random_walk is not None
                else imu_noise.gyro_random_walk * config.imu_noise_scale
            )
        self._offset_ns = round(config.imu_time_offset_s * 1e9)
        self._max_gap_ns = round(config.imu_max_gap_s * 1e9)
        self._buffer = ImuBuffer()
        self._use_accel = bool(self.use_imu and config.use_accelerometer)
        self._gravity = np.array([0.0, 0.0, -GRAVITY])  # world, latest estimate
        self._accel_bias = np.zeros(3)
        # Frames still in the smoother (oldest first), and the final poses handed out with the
        # next estimate.
        self._open: OrderedDict[int, _OpenFrame] = OrderedDict()
        self._final_poses: list[tuple[int, np.ndarray]] = []
        self._smoother = self._make_smoother()
        self._index = -1
        self._start_ns = 0
        self._last_ns = 0
        self._body_pose = np.eye(4)
        self._previous_motion: np.ndarray | None = None  # body T_k-2,k-1 (estimated)
        self._previous_dt = 0.0
        self._bias = np.zeros(3)
        # The newest frame with accepted vision (or the first): its time widens the gate after
        # a gap, and a measurement whose reference has left the window is chained through it.
        self._last_fix_index = 0
        self._last_fix_ns = 0
        # Frames that may still be referenced by a keyframe measurement: stamp -> (index, latest
        # body pose estimate), the pose for references that have left the smoother's window.
        self._frames: OrderedDict[int, tuple[int, np.ndarray]] = OrderedDict()
        self._oldest_reference = 0
        # Static initialisation: looking for rest while True; the rest window so far.
        self._starting = bool(self.use_imu and config.static_init)
        self._rest: RestWindow | None = None
        # (duration s, mean gyro) of the start-up rest once it has ended, for reports.
        self.rest_summary: tuple[float, np.ndarray] | None = None

    # ------------------------------------------------------------------ public

    @property
    def frame_count(self) -> int:
        return self._index + 1

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
        refinement), takes precedence over both.
        """
        timestamp_ns = int(timestamp_ns)
        check_timestamp_order(timestamp_ns, self._last_ns if self._index >= 0 else None)
        if inlier_count < 0:
            raise ValueError(f"inlier_count must be >= 0, got {inlier_count}")
        if relative_pose is None:
            covariance = None
        else:
            relative_pose = _check_pose("relative_pose", relative_pose)
            if covariance is not None:
                covariance = measured_covariance(covariance, self.config)
            elif inlier_points is not None and len(inlier_points) > 0:
                covariance = fit_covariance(inlier_points, inlier_residuals, self.config)
            else:
                sigmas = relative_pose_sigmas(inlier_residuals, inlier_count, self.config)
                covariance = sigma_covariance(sigmas)
            # Into the body frame: T_BS T Exp(xi) T_SB = (T_BS T T_SB) Exp(Ad(T_BS) xi).
            covariance = self._adjoint @ covariance @ self._adjoint.T
        if imu is not None and self.use_imu:
            self._buffer.extend(imu)
        if self._index < 0:
            return self._start(timestamp_ns)
        return self._advance(timestamp_ns, relative_pose, covariance, reference_ns)

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
        self._starting = False

    # ------------------------------------------------------------------ graph building

    def _make_smoother(self) -> gtsam.ISAM2 | gtsam.IncrementalFixedLagSmoother:
        params = gtsam.ISAM2Params()
        thresholds = gtsam.ISAM2ThresholdMap()
        rotation, translation = (
            self.config.relinearize_rotation_rad,
            self.config.relinearize_translation_m,
        )
        thresholds.insert(("x", np.array([rotation] * 3 + [translation] * 3)))
        thresholds.insert(("b", np.full(3, self.config.relinearize_bias)))
        # Gravity and accelerometer bias: the inertial factor is linear in both, so its
        # linearisation is exact at any point and a change of theirs never needs one.
        thresholds.insert(("g", np.full(3, np.inf)))
        thresholds.insert(("a", np.full(3, np.inf)))
        params.setRelinearizeThreshold(thresholds)
        # QR: the bias random walk (~4e-6 rad/s per frame) against a 0.05 rad/s prior is too
        # ill-conditioned for Cholesky when no gyro factor ties the biases to the poses.
        params.setFactorization("QR")
        params.relinearizeSkip = 1
        if self.config.smoother == "isam2":
            return gtsam.ISAM2(params)
        return gtsam.IncrementalFixedLagSmoother(self.config.smoother_lag_s, params)

    def _update(
        self,
        factors: gtsam.NonlinearFactorGraph,
        values: gtsam.Values,
        keys: list[int],
        keep: tuple[int, ...] = (),
    ):
        """Add factors and values; ``keys`` (and ``keep``) are stamped with the current time.

        ``keep`` lists existing keys the new factors touch: restamping them stops the fixed-lag
        smoother from marginalising them in this very update (a frame gap longer than the lag),
        so their estimates can still be read afterwards.
        """
        if isinstance(self._smoother, gtsam.ISAM2):
            self._smoother.update(factors, values)
            for _ in range(self.config.extra_iterations):
                self._smoother.update()
            return
        stamp = self._stamp(self._last_ns)
        self._smoother.update(factors, values, dict.fromkeys([*keys, *keep], stamp))
        for _ in range(self.config.extra_iterations):
            self._smoother.update()

    def _stamp(self, timestamp_ns: int) -> float:
        """Smoother time of a frame's keys: seconds since the first frame, rounded down to
        ``marginalize_block_s``.

        GTSAM's fixed-lag smoother drops the keys stamped more than the lag before the newest
        one; each such marginalisation linearises again the factors around the dropped frames,
        so rounding the stamps down makes frames leave in blocks, at about the cost of one.
        """
        seconds = (timestamp_ns - self._start_ns) * 1e-9
        block = self.config.marginalize_block_s
        return math.floor(seconds / block) * block if block > 0 else seconds

    def _pose_estimate(self, index: int) -> np.ndarray:
        return self._smoother.calculateEstimatePose3(_pose_key(index)).matrix()

    def _bias_estimate(self, index: int) -> np.ndarray:
        return np.asarray(self._smoother.calculateEstimateVector(_bias_key(index)))

    def _start(self, timestamp_ns: int) -> FusedEstimate:
        self._index = 0
        self._start_ns = self._last_ns = self._last_fix_ns = timestamp_ns
        message = "world = first body pose"
        rotation = np.eye(3)
        levelled = False
        if self.use_imu and self.config.gravity_align:
            accel = self._buffer.accel[self._buffer.timestamps_ns <= timestamp_ns + self._offset_ns]
            if len(accel):
                try:
                    rotation = gravity_aligned_rotation(accel)
                    levelled = True
                    message = f"world gravity-aligned from {len(accel)} accelerometer samples"
                except ValueError as error:
                    message = f"world = first body pose ({error})"
            else:
                message = "world = first body pose (no accelerometer samples with frame 0)"
        bias_mean = self._bias.copy()  # zero unless restored from another instance
        bias_sigma = self.config.gyro_bias_prior_sigma
        if self._starting:
            bias_mean, bias_sigma, note = self._rest_before(timestamp_ns + self._offset_ns)
            if note:
                message += "; " + note
        self._body_pose = make_pose(rotation, np.zeros(3))
        factors = gtsam.NonlinearFactorGraph()
        values = gtsam.Values()
        keys = [_pose_key(0)]
        origin = gtsam.Pose3(self._body_pose)
        factors.add(
            gtsam.PriorFactorPose3(
                _pose_key(0), origin, gtsam.noiseModel.Isotropic.Sigma(6, _ORIGIN_SIGMA)
            )
        )
        values.insert(_pose_key(0), origin)
        if self.use_imu:
            factors.add(
                gtsam.PriorFactorVector(
                    _bias_key(0), bias_mean, gtsam.noiseModel.Isotropic.Sigma(3, bias_sigma)
                )
            )
            values.insert(_bias_key(0), bias_mean)
            keys.append(_bias_key(0))
        if self._use_accel:
            # Levelled: gravity is -z up to the tilt error of an accelerometer that may already
            # see motion; otherwise its direction in the first body frame is unknown.
            self._gravity = np.array([0.0, 0.0, -GRAVITY]) if levelled else np.zeros(3)
            gravity_sigma = self.config.gravity_prior_sigma if levelled else 2.0 * GRAVITY
            self._add_inertial_variables(factors, values, keys, gravity_sigma)
        self._update(factors, values, keys)
        return self._estimate(FrameStatus.OK, message)

    def _add_inertial_variables(
        self,
        factors: gtsam.NonlinearFactorGraph,
        values: gtsam.Values,
        keys: list[int],
        gravity_sigma: float,
    ) -> None:
        """Gravity and accelerometer bias with their priors (at the latest estimates)."""
        for key, mean, sigma in (
            (_GRAVITY_KEY, self._gravity, gravity_sigma),
            (_ACCEL_BIAS_KEY, self._accel_bias, self.config.accel_bias_prior_sigma),
        ):
            factors.add(
                gtsam.PriorFactorVector(key, mean, gtsam.noiseModel.Isotropic.Sigma(3, sigma))
            )
            values.insert(key, mean)
            keys.append(key)

    def _rest_before(self, end_ns: int) -> tuple[np.ndarray, float, str]:
        """Bias prior (mean, sigma, note) from the IMU before the first frame if it was at rest."""
        assert self._imu_noise is not None
        samples = self._buffer.between(-(2**62), end_ns)
        stamps = samples.timestamps_ns
        loose = (np.zeros(3), self.config.gyro_bias_prior_sigma, "")
        if len(stamps) < 2 or (stamps[-1] - stamps[0]) * 1e-9 < self.config.rest_min_duration_s:
            return loose
        if not at_rest(samples.gyro, samples.accel, self._imu_noise, self.config.rest_z):
            self._starting = False  # already moving: no static initialisation
            return (*loose[:2], "IMU not at rest before frame 0")
        self._rest = RestWindow.of(samples.timestamps_ns, samples.gyro, samples.accel)
        sigma = self._rest.bias_sigma(self._imu_noise)
        return (
            self._rest.gyro_mean,
            sigma,
            f"at rest for {self._rest.duration_s:.2f} s before frame 0: gyro bias prior "
            f"{np.array2string(self._rest.gyro_mean, precision=5)} +- {sigma:.1e} rad/s",
        )

    def _still_interval(self, start_ns: int, end_ns: int) -> ImuBatch | None:
        """The IMU samples of this frame interval if they continue the start-up rest."""
        assert self._imu_noise is not None
        samples = self._buffer.between(start_ns + self._offset_ns, end_ns + self._offset_ns)
        if len(samples) < 2 or not at_rest(
            samples.gyro, samples.accel, self._imu_noise, self.config.rest_z, self._rest
        ):
            return None
        return samples

    def _end_start_up(self, notes: list[str]) -> None:
        self._starting = False
        if self._rest is not None:
            duration = self._rest.duration_s
            notes.append(f"start-up standstill ended after {duration:.2f} s of rest")
            self.rest_summary = (duration, self._rest.gyro_mean.copy())

    def _preintegrate(
        self, start_ns: int, end_ns: int
    ) -> tuple[GyroPreintegration | None, SpecificForceDelta | None]:
        """Gyro (and, when used, accelerometer) preintegrated over one frame interval."""
        start_ns += self._offset_ns
        end_ns += self._offset_ns
        if not self._buffer.covers(start_ns, end_ns, self._max_gap_ns):
            return None, None
        samples = self._buffer.window(start_ns, end_ns)
        preintegration = preintegrate_gyro(
            samples.timestamps_ns, samples.gyro, start_ns, end_ns, self._imu_params, self._bias
        )
        delta = None
        if self._use_accel:
            delta = preintegrate_specific_force(
                samples.timestamps_ns, samples.gyro, samples.accel, start_ns, end_ns, self._bias
            )
        self._buffer.drop_before(end_ns)
        return preintegration, delta

    def _motion_prior(self, dt: float) -> np.ndarray:
        """Constant body twist: the previous motion rescaled to this frame interval."""
        if self._previous_motion is None:
            return np.eye(4)
        twist = gtsam.Pose3.Logmap(gtsam.Pose3(self._previous_motion))
        return gtsam.Pose3.Expmap(twist * (dt / self._previous_dt)).matrix()

    def _restart(self, index: int, body_pose: np.ndarray) -> None:
        """A fresh smoother anchored at ``body_pose``: the trajectory goes on from here."""
        self._smoother = self._make_smoother()
        factors = gtsam.NonlinearFactorGraph()
        values = gtsam.Values()
        keys = [_pose_key(index)]
        anchor = gtsam.Pose3(body_pose)
        factors.add(
            gtsam.PriorFactorPose3(
                _pose_key(index), anchor, gtsam.noiseModel.Isotropic.Sigma(6, _ORIGIN_SIGMA)
            )
        )
        values.insert(_pose_key(index), anchor)
        if self.use_imu:
            factors.add(
                gtsam.PriorFactorVector(
                    _bias_key(index),
                    self._bias,
                    gtsam.noiseModel.Isotropic.Sigma(3, self.config.gyro_bias_prior_sigma),
                )
            )
            values.insert(_bias_key(index), self._bias)
            keys.append(_bias_key(index))
        if self._use_accel:
            self._add_inertial_variables(factors, values, keys, self.config.gravity_prior_sigma)
        self._update(factors, values, keys)

    def _gate_distance(
        self,
        measured: np.ndarray,
        predicted: np.ndarray,
        covariance: np.ndarray,
        preintegration: GyroPreintegration | None,
        dt: float,
    ) -> float:
        """Squared Mahalanobis distance of a relative pose from the prediction.

        The error is Log(predicted^-1 measured) with the measurement's 6x6 covariance plus the
        prediction's spread: the gyro covariance plus a floor for the bias uncertainty (else
        the constant-velocity sigma) for rotation, the constant-velocity sigma for
        translation; the motion-prior parts widen with the time since the last accepted vision
        against the previous frame interval (a long gap extrapolates just as far, whether
        frames were missed or never came), so the gate reopens after a gap.
        """
        if self._previous_motion is None and preintegration is None:
            return 0.0  # nothing to compare with yet
        elapsed = (self._last_ns - self._last_fix_ns) * 1e-9 + dt
        widen = max(1.0, elapsed / self._previous_dt) ** 2 if self._previous_dt > 0 else 1.0
        error = gtsam.Pose3.Logmap(gtsam.Pose3(invert_pose(predicted) @ measured))
        spread = covariance.copy()
        if preintegration is not None:
            floor = max(_GATE_GYRO_FLOOR_RAD, _GATE_GYRO_BIAS_RATE * dt)
            spread[:3, :3] += preintegration.covariance + np.eye(3) * floor**2
        else:
            spread[:3, :3] += np.eye(3) * self.config.cv_rotation_sigma_rad**2 * widen
        if self._previous_motion is None:  # no translation to compare with yet
            return float(error[:3] @ np.linalg.solve(spread[:3, :3], error[:3]))
        spread[3:, 3:] += np.eye(3) * self.config.cv_translation_sigma_m**2 * widen
        return float(error @ np.linalg.solve(spread, error))

    def _in_window(self, index: int, cutoff: float) -> bool:
        """Whether frame ``index`` has a variable that survives an update dropping the keys
        stamped before ``cutoff`` (the same comparison GTSAM makes, with a small margin).

        A reference that would be marginalised is not kept alive by restamping it: with its
        neighbours already gone, GTSAM's fixed-lag smoother fails to marginalise it later
        ("remove variables ... that are not unused"); such a measurement is chained through
        the previous frame instead.
        """
        if isinstance(self._smoother, gtsam.ISAM2):
            return bool(self._smoother.valueExists(_pose_key(index)))
        frame = self._open.get(index)
        return (
            frame is not None
            and frame.stamp_s > cutoff + _STAMP_MARGIN_S
            and bool(self._smoother.getISAM2().valueExists(_pose_key(index)))
        )

    def _reference_index(self, reference_ns: int | None) -> int | None:
        """Frame index of ``reference_ns`` (None: the previous frame; unknown: None + note)."""
        if reference_ns is None:
            return self._index
        frame = self._frames.get(int(reference_ns))
        return None if frame is None else frame[0]

    def _advance(
        self,
        timestamp_ns: int,
        relative_pose: np.ndarray | None,
        covariance: np.ndarray | None,
        reference_ns: int | None = None,
    ) -> FusedEstimate:
        """One frame: its factors (IMU, vision, motion prior, standstill), the update, status."""
        dt = (timestamp_ns - self._last_ns) * 1e-9
        stamp = self._stamp(timestamp_ns)
        step = _Step(
            previous=self._index,
            current=self._index + 1,
            dt=dt,
            stamp=stamp,
            cutoff=stamp - self.config.smoother_lag_s,  # keys stamped before it are dropped now
        )
        step.keys.append(_pose_key(step.current))
        if self._starting:
            step.rest_samples = self._still_interval(self._last_ns, timestamp_ns)
        step.still = step.rest_samples is not None
        if self.use_imu:
            self._add_imu_factors(step, timestamp_ns)
        if self._calibration is not None:
            reference = reference_ns if reference_ns is not None else self._last_ns
            self._calibration.add_frame(
                timestamp_ns, step.preintegration, reference, relative_pose, covariance, self._bias
            )
        motion = self._motion_prior(dt)
        inertial = self._inertial_factor(step.current, step.delta, step.cutoff)
        prediction = self._prediction(step, motion, inertial)
        guess = self._add_vision_factor(step, relative_pose, covariance, reference_ns, prediction)
        if self.config.motion_prior == "always" or not (step.accepted or inertial is not None):
            self._add_motion_prior(step, motion)
        guess = self._add_standstill(step, guess)
        step.values.insert(
            _pose_key(step.current), gtsam.Pose3(nearest_rigid(self._body_pose @ guess))
        )
        previous_pose = self._commit(step, timestamp_ns, guess)
        status = self._status(step)
        self._previous_motion = invert_pose(previous_pose) @ self._pose_estimate(step.current)
        self._previous_dt = dt
        estimate = self._estimate(
            status, "; ".join(step.notes), self._previous_motion.copy(), step.delta
        )
        return replace(estimate, vision_rejected=step.rejected)

    def _add_imu_factors(self, step: _Step, timestamp_ns: int) -> None:
        """Gyro rotation factor over the interval and the bias random walk into this frame."""
        previous, current = step.previous, step.current
        step.preintegration, step.delta = self._preintegrate(self._last_ns, timestamp_ns)
        if step.preintegration is not None:
            step.factors.add(
                gyro_rotation_factor(
                    _pose_key(previous),
                    _pose_key(current),
                    _bias_key(previous),
                    step.preintegration,
                )
            )
        else:
            step.notes.append("no gyro for this interval")
        walk = self._bias_sigma_density * np.sqrt(step.dt)
        step.factors.add(
            gtsam.BetweenFactorVector(
                _bias_key(previous),
                _bias_key(current),
                np.zeros(3),
                gtsam.noiseModel.Isotropic.Sigma(3, walk),
            )
        )
        step.values.insert(_bias_key(current), self._bias)
        step.keys.append(_bias_key(current))

    def _prediction(
        self,
        step: _Step,
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

    def _add_vision_factor(
        self,
        step: _Step,
        relative_pose: np.ndarray | None,
        covariance: np.ndarray | None,
        reference_ns: int | None,
        prediction: np.ndarray,
    ) -> np.ndarray:
        """The front-end relative pose as a robust factor unless the gate rejects it.

        Returns the initial guess of the body motion (the measurement when accepted, else the
        prediction); clears ``step.still`` when vision disagrees with a standstill.
        """
        reference = None
        if relative_pose is not None and covariance is not None:
            reference = self._reference_index(reference_ns)
            if reference is None:
                step.notes.append(
                    f"relative pose not used (reference frame {reference_ns} is unknown or "
                    "older than the latest reference)"
                )
        if reference is None:
            return prediction
        assert relative_pose is not None and covariance is not None
        previous = step.previous
        body_measured = nearest_rigid(self.body_from_camera @ relative_pose @ self.camera_from_body)
        # The measurement seen as a motion from the previous frame, through the current
        # estimates: for the gate and the initial guess (and as the factor itself when the
        # reference has already left the window).
        body_motion = body_measured
        live = reference == previous or self._in_window(reference, step.cutoff)
        if reference != previous:
            reference_pose = (
                self._pose_estimate(reference) if live else self._frames[int(reference_ns)][1]
            )
            body_motion = nearest_rigid(
                invert_pose(self._body_pose) @ reference_pose @ body_measured
            )
        if step.still:  # vision must agree with the standstill too
            moved = gtsam.Pose3.Logmap(gtsam.Pose3(body_motion))
            step.still = float(moved @ np.linalg.solve(covariance, moved)) <= _STILL_CHI2
        distance = self._gate_distance(
            body_motion, prediction, covariance, step.preintegration, step.dt
        )
        gate = self.config.outlier_gate_chi2
        if not (gate is None or distance <= gate):
            step.notes.append(
                f"relative pose rejected (squared Mahalanobis distance {distance:.0f} "
                f"> {gate:g} from the prediction)"
            )
            step.rejected = True
            return prediction
        step.accepted = True
        base = gtsam.noiseModel.Gaussian.Covariance(covariance)
        source, measured = (reference, body_measured) if live else (previous, body_motion)
        if not live and self._last_fix_index != previous:
            source, measured = self._chained(step, measured, body_motion)
        step.factors.add(
            gtsam.BetweenFactorPose3(
                _pose_key(source),
                _pose_key(step.current),
                gtsam.Pose3(measured),
                robust(base, self.config.robust_kernel, self.config.robust_parameter),
            )
        )
        self._oldest_reference = max(self._oldest_reference, reference)
        return body_motion

    def _chained(
        self, step: _Step, measured: np.ndarray, body_motion: np.ndarray
    ) -> tuple[int, np.ndarray]:
        """Source frame and relative pose for a measurement whose reference has left the
        window, after frames without vision: chained through the last frame with accepted
        vision while it is in the window, not through the previous (coasted) frame, whose
        IMU-only estimate would otherwise carry its error into every frame after the gap."""
        anchor = self._last_fix_index
        if not self._in_window(anchor, step.cutoff):
            return step.previous, measured
        # body_motion is T_prev_cur through the current estimates: T_anchor_cur follows.
        anchor_from_previous = invert_pose(self._pose_estimate(anchor)) @ self._body_pose
        return anchor, nearest_rigid(anchor_from_previous @ body_motion)

    def _add_motion_prior(self, step: _Step, motion: np.ndarray) -> None:
        """Constant-velocity prior from the previous frame (loose)."""
        # With the gyro the prior carries translation only: its rotation part would
        # otherwise leak into the bias estimate.
        rotation_sigma = (
            _FREE_ROTATION_SIGMA
            if step.preintegration is not None
            else self.config.cv_rotation_sigma_rad
        )
        step.factors.add(
            gtsam.BetweenFactorPose3(
                _pose_key(step.previous),
                _pose_key(step.current),
                gtsam.Pose3(motion),
                pose_noise(rotation_sigma, self.config.cv_translation_sigma_m),
            )
        )

    def _add_standstill(self, step: _Step, guess: np.ndarray) -> np.ndarray:
        """During the start-up rest: extend it and tie the poses by a zero-motion factor;
        the first interval that moves ends the start-up. Returns the initial guess."""
        if not step.still:
            if self._starting:
                self._end_start_up(step.notes)
            return guess
        samples = step.rest_samples
        assert samples is not None
        if self._rest is None:
            self._rest = RestWindow.of(samples.timestamps_ns, samples.gyro, samples.accel)
        else:
            self._rest.extend(samples.timestamps_ns, samples.gyro, samples.accel)
        step.factors.add(
            gtsam.BetweenFactorPose3(
                _pose_key(step.previous),
                _pose_key(step.current),
                gtsam.Pose3(),
                pose_noise(self.config.zero_motion_sigma_rad, self.config.zero_motion_sigma_m),
            )
        )
        return np.eye(4)

    def _commit(self, step: _Step, timestamp_ns: int, guess: np.ndarray) -> np.ndarray:
        """Update the smoother with the step (restarting it after a numerical failure).

        Returns the previous frame's pose estimate after the update.
        """
        previous = step.previous
        # The previous frame's keys would be marginalised by this update when the gap exceeds
        # the lag (its estimate is needed just below): restamped, it stays in the window.
        if self._open[previous].stamp_s <= step.cutoff + _STAMP_MARGIN_S:
            step.keep += [_pose_key(previous)] + ([_bias_key(previous)] if self.use_imu else [])
            self._open[previous].stamp_s = step.stamp
        if self._use_accel:
            step.keep += [_GRAVITY_KEY, _ACCEL_BIAS_KEY]
        self._last_ns = timestamp_ns
        self._index = step.current
        self._finish_before(step.cutoff)
        try:
            self._update(step.factors, step.values, step.keys, tuple(step.keep))
            return self._pose_estimate(previous)
        except RuntimeError as error:  # numerical failure inside GTSAM: restart the graph
            self._finish_before(float("inf"), read=False)
            self._restart(step.current, self._body_pose @ guess)
            reason = str(error).strip().splitlines()[0]
            step.notes.append(f"back end restarted at this frame ({reason})")
            return self._body_pose

    def _status(self, step: _Step) -> FrameStatus:
        """OK with accepted vision, else DEGRADED (gyro) or LOST; notes the last fix."""
        if step.accepted:
            self._last_fix_index, self._last_fix_ns = step.current, self._last_ns
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
        self._body_pose = self._pose_estimate(self._index)
        self._remember(self._last_ns, self._index, self._body_pose)
        self._open[self._index] = _OpenFrame(
            self._index,
            self._last_ns,
            self._stamp(self._last_ns),
            delta,
            self._body_pose.copy(),
        )
        bias = None
        if self.use_imu:
            self._bias = self._bias_estimate(self._index)
            bias = self._bias.copy()
        if self._use_accel:
            self._gravity = np.asarray(self._smoother.calculateEstimateVector(_GRAVITY_KEY))
            self._accel_bias = np.asarray(self._smoother.calculateEstimateVector(_ACCEL_BIAS_KEY))
        final_poses, self._final_poses = tuple(self._final_poses), []
        covariance, motion_covariance = self._marginals(motion)
        return FusedEstimate(
            pose=self._body_pose @ self.body_from_camera,
            body_pose=self._body_pose.copy(),
            status=status,
            message=message,
            gyro_bias=bias,
            body_motion=motion,
            final_poses=final_poses,
            gravity=self._gravity.copy() if self._use_accel else None,
            accel_bias=self._accel_bias.copy() if self._use_accel else None,
            body_covariance=covariance,
            body_motion_covariance=motion_covariance,
            covariance_scale=self._calibration.value if self._calibration is not None else 1.0,
            pose_covariance_scale=self._calibration.pose_value if self._calibration else 1.0,
        )

    def _marginals(self, motion: np.ndarray | None) -> tuple[np.ndarray | None, np.ndarray | None]:
        """Covariance of the newest pose and of the motion from the previous one.

        The motion M = X_prev^-1 X_cur has the right-perturbation error
        xi = xi_cur - Ad(M^-1) xi_prev, so its covariance needs the joint marginal of both.
        None where GTSAM cannot give it (a restarted graph without the previous frame).
        """
        smoother = self._smoother
        isam = smoother if isinstance(smoother, gtsam.ISAM2) else smoother.getISAM2()
        current = _pose_key(self._index)
        try:
            if motion is None or not isam.valueExists(_pose_key(self._index - 1)):
                return np.asarray(isam.marginalCovariance(current)), None
            previous = _pose_key(self._index - 1)
            joint = isam.jointMarginalCovariance(gtsam.KeyVector([previous, current]))
        except RuntimeError:  # numerical failure inside GTSAM
            return None, None
        jacobian = np.hstack([-gtsam.Pose3(invert_pose(motion)).AdjointMap(), np.eye(6)])
        blocks = np.block(
            [
                [joint.at(previous, previous), joint.at(previous, current)],
                [joint.at(current, previous), joint.at(current, current)],
            ]
        )
        motion_covariance = jacobian @ blocks @ jacobian.T
        motion_covariance = 0.5 * (motion_covariance + motion_covariance.T)
        return np.asarray(joint.at(current, current)), motion_covariance

    # ------------------------------------------------------------------ smoothed output

    def flush(self) -> tuple[tuple[int, np.ndarray], ...]:
        """Final estimates of the frames still in the smoother (end of a run), oldest first."""
        self._finish_before(float("inf"))
        final_poses, self._final_poses = tuple(self._final_poses), []
        return final_poses

    def _finish_before(self, stamp_s: float, read: bool = True) -> None:
        """Finish the frames stamped before ``stamp_s`` (the smoother is about to drop them).

        Their estimate is read one last time (``read=False``: the last one read, after a
        numerical failure) and handed out as final.
        """
        while self._open:
            frame = next(iter(self._open.values()))
            if frame.stamp_s >= stamp_s:
                break
            del self._open[frame.index]
            if read:
                try:
                    frame.body_pose = self._pose_estimate(frame.index)
                except (IndexError, RuntimeError):  # GTSAM: unknown key / numerical failure
                    pass  # keep the latest estimate read
            self._final_poses.append((frame.timestamp_ns, frame.body_pose @ self.body_from_camera))

    def _inertial_factor(
        self, current: int, delta: SpecificForceDelta | None, cutoff: float
    ) -> tuple[gtsam.CustomFactor, np.ndarray] | None:
        """The inertial factor on (X_k-2, X_k-1, X_k) and the position it predicts for X_k.

        None without accelerometer data for either interval, when either interval is longer
        than ``inertial_max_interval_s``, or when X_k-2 is about to leave the smoother.
        """
        if delta is None or current < 2:
            return None
        first_frame = self._open.get(current - 2)
        previous_frame = self._open.get(current - 1)
        if first_frame is None or previous_frame is None or previous_frame.delta is None:
            return None
        longest = max(previous_frame.delta.duration_s, delta.duration_s)
        if longest > self.config.inertial_max_interval_s:
            return None
        if not self._in_window(current - 2, cutoff):
            return None
        assert self._imu_noise is not None
        terms = InertialTerms.of(previous_frame.delta, delta)
        sigma = max(
            inertial_factor_sigma(terms, self._imu_noise.accel_noise_density),
            self.config.inertial_min_sigma_mps,
        )
        factor = inertial_factor(
            (_pose_key(current - 2), _pose_key(current - 1), _pose_key(current)),
            _GRAVITY_KEY,
            _ACCEL_BIAS_KEY,
            terms,
            sigma,
        )
        first_pose = self._pose_estimate(current - 2)
        predicted = predict_position(
            terms, first_pose, self._body_pose, self._gravity, self._accel_bias
        )
        return factor, predicted

    def _remember(self, timestamp_ns: int, index: int, body_pose: np.ndarray) -> None:
        """Keep the pose of frames that may still be referenced: none older than the latest
        reference, since a front end's references only move forward."""
        self._frames[timestamp_ns] = (index, body_pose)
        while self._frames and next(iter(self._frames.values()))[0] < self._oldest_reference:
            self._frames.popitem(last=False)
