"""The IMU's part of each frame: gyro rotation factor, bias random walk and inertial factor.

* the gyro preintegrated over the frame interval (shifted by the camera-IMU time offset) as a
  rotation factor on (X_k-1, X_k, B_k-1) (``factors.py``) and a bias random walk B_k-1 -> B_k;
* with the accelerometer, the inertial factor on (X_k-2, X_k-1, X_k, G, A): their velocity
  change against the preintegrated specific force, with world gravity G and accelerometer
  bias A as variables of the graph (``inertial.py``); it carries the translation through
  vision gaps.
"""

from __future__ import annotations

from dataclasses import replace

import gtsam
import numpy as np

from estimator.backend.factors import gyro_rotation_factor
from estimator.backend.imu import (
    GyroPreintegration,
    ImuBuffer,
    SpecificForceDelta,
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
from estimator.backend.smoother import ACCEL_BIAS_KEY, GRAVITY_KEY, bias_key, pose_key
from estimator.backend.step import Step
from estimator.backend.window import FrameWindow
from estimator.config import BackendConfig
from estimator.imu_sampling import sample_segments
from estimator.types import ImuNoise

__all__ = ["ImuTerms"]


class ImuTerms:
    """The IMU samples not yet used and the noise they are weighed with."""

    def __init__(self, config: BackendConfig, imu_noise: ImuNoise, use_accel: bool) -> None:
        self.config = config
        scale = config.imu_noise_scale
        self.noise = replace(
            imu_noise,
            gyro_noise_density=imu_noise.gyro_noise_density * scale,
            accel_noise_density=imu_noise.accel_noise_density * scale,
            gyro_random_walk=imu_noise.gyro_random_walk * scale,
            accel_random_walk=imu_noise.accel_random_walk * scale,
        )
        self.params = rotation_params(imu_noise, scale)
        self.bias_sigma_density = (
            config.gyro_random_walk
            if config.gyro_random_walk is not None
            else imu_noise.gyro_random_walk * scale
        )
        self.use_accel = use_accel
        self.buffer = ImuBuffer()
        self.offset_ns = round(config.imu_time_offset_s * 1e9)
        self.max_gap_ns = round(config.imu_max_gap_s * 1e9)

    def preintegrate(
        self, start_ns: int, end_ns: int, bias: np.ndarray
    ) -> tuple[GyroPreintegration | None, SpecificForceDelta | None]:
        """Gyro (and, when used, accelerometer) preintegrated over one frame interval."""
        start_ns += self.offset_ns
        end_ns += self.offset_ns
        if not self.buffer.covers(start_ns, end_ns, self.max_gap_ns):
            return None, None
        samples = self.buffer.window(start_ns, end_ns)
        stamps = samples.timestamps_ns
        segments = sample_segments(stamps, samples.gyro, start_ns, end_ns)  # cut once for both
        preintegration = preintegrate_gyro(
            stamps, samples.gyro, start_ns, end_ns, self.params, bias, segments
        )
        delta = None
        if self.use_accel:
            delta = preintegrate_specific_force(
                stamps, samples.gyro, samples.accel, start_ns, end_ns, bias,
                gyro_segments=segments,
            )  # fmt: skip
        self.buffer.drop_before(end_ns)
        return preintegration, delta

    def add_factors(self, step: Step, start_ns: int, end_ns: int, bias: np.ndarray) -> None:
        """Gyro rotation factor over the interval and the bias random walk into this frame."""
        previous, current = step.previous, step.current
        step.preintegration, step.delta = self.preintegrate(start_ns, end_ns, bias)
        if step.preintegration is not None:
            step.factors.add(
                gyro_rotation_factor(
                    pose_key(previous), pose_key(current), bias_key(previous), step.preintegration
                )
            )
        else:
            step.notes.append("no gyro for this interval")
        walk = self.bias_sigma_density * np.sqrt(step.dt)
        step.factors.add(
            gtsam.BetweenFactorVector(
                bias_key(previous),
                bias_key(current),
                np.zeros(3),
                gtsam.noiseModel.Isotropic.Sigma(3, walk),
            )
        )
        step.values.insert(bias_key(current), bias)
        step.keys.append(bias_key(current))

    def inertial_factor(
        self,
        step: Step,
        window: FrameWindow,
        body_pose: np.ndarray,
        gravity: np.ndarray,
        accel_bias: np.ndarray,
    ) -> tuple[gtsam.CustomFactor, np.ndarray] | None:
        """The inertial factor on (X_k-2, X_k-1, X_k) and the position it predicts for X_k.

        None without accelerometer data for either interval, when either interval is longer
        than ``inertial_max_interval_s``, or when X_k-2 is about to leave the smoother.
        """
        current, delta = step.current, step.delta
        if delta is None or current < 2:
            return None
        first_frame = window.open.get(current - 2)
        previous_frame = window.open.get(current - 1)
        if first_frame is None or previous_frame is None or previous_frame.delta is None:
            return None
        longest = max(previous_frame.delta.duration_s, delta.duration_s)
        if longest > self.config.inertial_max_interval_s:
            return None
        if not window.in_window(current - 2, step.cutoff):
            return None
        terms = InertialTerms.of(previous_frame.delta, delta)
        sigma = max(
            inertial_factor_sigma(terms, self.noise.accel_noise_density),
            self.config.inertial_min_sigma_mps,
        )
        factor = inertial_factor(
            (pose_key(current - 2), pose_key(current - 1), pose_key(current)),
            GRAVITY_KEY,
            ACCEL_BIAS_KEY,
            terms,
            sigma,
        )
        first_pose = window.smoother.pose(current - 2)
        predicted = predict_position(terms, first_pose, body_pose, gravity, accel_bias)
        return factor, predicted
