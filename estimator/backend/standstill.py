"""The start-up standstill (static initialisation, with the IMU).

When the samples before the first frame show the platform at rest, the first gyro bias starts
from their mean gyro, and gets the prior mean gyro +- density / sqrt(T) (with the bias walk)
once the first frame interval confirms the rest (IMU tests, and the relative pose when vision
has one). The IMU alone cannot tell rest from smooth cruising (a car at constant speed reads
like a still sensor), and the mean rate of a cruising platform is not its bias: until vision
agrees, the first bias keeps the loose prior ``gyro_bias_prior_sigma`` around that mean.
For as long as every frame interval from the start shows rest too, consecutive poses are tied
by a tight zero-motion factor. The gyro factors of those intervals then estimate the bias in
the graph exactly as the mean gyro would, with no sample used twice. The first interval that
moves ends the start-up for good.
"""

from __future__ import annotations

import gtsam
import numpy as np

from estimator.backend.imu import ImuBuffer
from estimator.backend.noise import pose_noise
from estimator.backend.rest import RestWindow, at_rest
from estimator.backend.smoother import bias_key, pose_key
from estimator.backend.step import Step
from estimator.config import BackendConfig
from estimator.types import ImuBatch, ImuNoise

__all__ = ["StartupRest"]


class StartupRest:
    """Looks for rest from the start until the first interval that moves."""

    def __init__(self, config: BackendConfig, imu_noise: ImuNoise | None, active: bool) -> None:
        self.config = config
        self.imu_noise = imu_noise
        self.starting = active  # looking for rest while True
        self.rest: RestWindow | None = None
        # (duration s, mean gyro) of the start-up rest once it has ended, for reports.
        self.summary: tuple[float, np.ndarray] | None = None
        # The bias prior (mean, sigma) of the rest before frame 0, until an interval confirms it.
        self.pending_prior: tuple[np.ndarray, float] | None = None

    def before_first_frame(self, buffer: ImuBuffer, end_ns: int) -> tuple[np.ndarray, float, str]:
        """First bias (mean, sigma, note): the mean gyro before the first frame if the IMU was at
        rest there, with the loose sigma; its tight prior waits for the first interval."""
        assert self.imu_noise is not None
        samples = buffer.between(-(2**62), end_ns)
        stamps = samples.timestamps_ns
        loose = (np.zeros(3), self.config.gyro_bias_prior_sigma, "")
        if len(stamps) < 2 or (stamps[-1] - stamps[0]) * 1e-9 < self.config.rest_min_duration_s:
            return loose
        if not at_rest(samples.gyro, samples.accel, self.imu_noise, self.config.rest_z):
            self.starting = False  # already moving: no static initialisation
            return (*loose[:2], "IMU not at rest before frame 0")
        self.rest = RestWindow.of(samples.timestamps_ns, samples.gyro, samples.accel)
        sigma = self.rest.bias_sigma(self.imu_noise)
        self.pending_prior = (self.rest.gyro_mean.copy(), sigma)
        return (
            self.rest.gyro_mean,
            self.config.gyro_bias_prior_sigma,
            f"IMU at rest for {self.rest.duration_s:.2f} s before frame 0: gyro bias prior "
            f"{np.array2string(self.rest.gyro_mean, precision=5)} +- {sigma:.1e} rad/s once "
            "the first frame interval confirms the rest",
        )

    def interval(self, buffer: ImuBuffer, start_ns: int, end_ns: int) -> ImuBatch | None:
        """The IMU samples of this interval (IMU clock) if they continue the start-up rest."""
        assert self.imu_noise is not None
        samples = buffer.between(start_ns, end_ns)
        if len(samples) < 2 or not at_rest(
            samples.gyro, samples.accel, self.imu_noise, self.config.rest_z, self.rest
        ):
            return None
        return samples

    def end(self, notes: list[str]) -> None:
        self.starting = False
        if self.rest is not None:
            duration = self.rest.duration_s
            notes.append(f"start-up standstill ended after {duration:.2f} s of rest")
            self.summary = (duration, self.rest.gyro_mean.copy())

    def add(self, step: Step, guess: np.ndarray) -> np.ndarray:
        """During the start-up rest: extend it and tie the poses by a zero-motion factor;
        the first interval that moves ends the start-up. Returns the initial guess."""
        if not step.still:
            if self.pending_prior is not None:
                step.notes.append("the rest before frame 0 was motion: its gyro bias prior dropped")
                self.pending_prior = None
            if self.starting:
                self.end(step.notes)
            return guess
        if self.pending_prior is not None:
            mean, sigma = self.pending_prior
            step.factors.add(
                gtsam.PriorFactorVector(
                    bias_key(step.previous), mean, gtsam.noiseModel.Isotropic.Sigma(3, sigma)
                )
            )
            self.pending_prior = None
        samples = step.rest_samples
        assert samples is not None
        if self.rest is None:
            self.rest = RestWindow.of(samples.timestamps_ns, samples.gyro, samples.accel)
        else:
            self.rest.extend(samples.timestamps_ns, samples.gyro, samples.accel)
        step.factors.add(
            gtsam.BetweenFactorPose3(
                pose_key(step.previous),
                pose_key(step.current),
                gtsam.Pose3(),
                pose_noise(self.config.zero_motion_sigma_rad, self.config.zero_motion_sigma_m),
            )
        )
        return np.eye(4)
