"""The priors a graph starts from: the first pose (which defines the world), the gyro bias and,
with the accelerometer, world gravity and the accelerometer bias. Used at the first frame and
when the smoother restarts after a numerical failure."""

from __future__ import annotations

from dataclasses import dataclass

import gtsam
import numpy as np

from estimator.backend.smoother import ACCEL_BIAS_KEY, GRAVITY_KEY, bias_key, pose_key

__all__ = ["ORIGIN_SIGMA", "Anchor", "InertialPrior"]

# The anchoring pose is pinned with a tight prior.
ORIGIN_SIGMA = 1e-6


@dataclass(frozen=True)
class InertialPrior:
    """Gravity and accelerometer bias priors (means at the latest estimates)."""

    gravity: np.ndarray
    gravity_sigma: float
    accel_bias: np.ndarray
    accel_bias_sigma: float


@dataclass(frozen=True)
class Anchor:
    """Factors and values that pin frame ``index`` at ``body_pose`` and its biases."""

    index: int
    body_pose: np.ndarray
    gyro_bias: tuple[np.ndarray, float] | None = None  # (mean, sigma) with the IMU
    inertial: InertialPrior | None = None  # with the accelerometer

    def graph(self) -> tuple[gtsam.NonlinearFactorGraph, gtsam.Values, list[int]]:
        factors = gtsam.NonlinearFactorGraph()
        values = gtsam.Values()
        keys = [pose_key(self.index)]
        origin = gtsam.Pose3(self.body_pose)
        factors.add(
            gtsam.PriorFactorPose3(
                pose_key(self.index), origin, gtsam.noiseModel.Isotropic.Sigma(6, ORIGIN_SIGMA)
            )
        )
        values.insert(pose_key(self.index), origin)
        priors: list[tuple[int, np.ndarray, float]] = []
        if self.gyro_bias is not None:
            priors.append((bias_key(self.index), *self.gyro_bias))
        if self.inertial is not None:
            inertial = self.inertial
            priors.append((GRAVITY_KEY, inertial.gravity, inertial.gravity_sigma))
            priors.append((ACCEL_BIAS_KEY, inertial.accel_bias, inertial.accel_bias_sigma))
        for key, mean, sigma in priors:
            factors.add(
                gtsam.PriorFactorVector(key, mean, gtsam.noiseModel.Isotropic.Sigma(3, sigma))
            )
            values.insert(key, mean)
            keys.append(key)
        return factors, values, keys
