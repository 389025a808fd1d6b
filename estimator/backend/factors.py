"""The gyro rotation factor on Pose3 frames, with analytic Jacobians.

GTSAM's ``AHRSFactor`` has exactly the error we want but connects Rot3 variables, while the
frames here are Pose3 (the front end measures full relative poses). Instead of a second set
of Rot3 variables tied to the poses, this factor evaluates the AHRS error directly on the
rotation part of two Pose3 keys and a gyro-bias key:

    e = Log( (dR * Exp(J_b (b - b_hat)))^T  R_i^T R_j )

with Jacobians (Pose3 tangent = [rotation, translation], right perturbation)

    de/dR_i = -Jr^-1(e) R_j^T R_i,   de/dR_j = Jr^-1(e),
    de/db   = -Jr^-1(e) E^T Jr(J_b (b - b_hat)) J_b,   E = Exp(e),

the same expressions as GTSAM's AHRSFactor (without the Coriolis term, negligible here);
the tests compare both.
"""

from __future__ import annotations

import gtsam
import numpy as np

from estimator.backend.imu import GyroPreintegration

__all__ = ["gyro_rotation_error", "gyro_rotation_factor"]



def _on_rotation(jacobian: np.ndarray) -> np.ndarray:
    """A 3x3 Jacobian w.r.t. a rotation as the 3x6 one w.r.t. the Pose3 (translation: 0)."""
    full = np.zeros((3, 6))
    full[:, :3] = jacobian
    return full


def gyro_rotation_error(
    preintegration: GyroPreintegration,
    rotation_i: np.ndarray,
    rotation_j: np.ndarray,
    bias: np.ndarray,
) -> tuple[np.ndarray, tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Rotation error (3,) and its Jacobians w.r.t. R_i, R_j (3x3 each) and the bias."""
    correction = preintegration.bias_jacobian @ (bias - preintegration.bias_hat)
    predicted = preintegration.delta_rotation @ gtsam.Rot3.Expmap(correction).matrix()
    actual = rotation_i.T @ rotation_j
    residual_rotation = predicted.T @ actual
    error = gtsam.Rot3.Logmap(gtsam.Rot3(residual_rotation))
    log_jacobian = gtsam.Rot3.LogmapDerivative(error)
    d_rotation_i = -log_jacobian @ actual.T
    d_bias = (
        -log_jacobian
        @ residual_rotation.T
        @ gtsam.Rot3.ExpmapDerivative(correction)
        @ preintegration.bias_jacobian
    )
    return error, (d_rotation_i, log_jacobian, d_bias)


def gyro_rotation_factor(
    pose_i: int, pose_j: int, bias: int, preintegration: GyroPreintegration
) -> gtsam.CustomFactor:
    """Factor on (Pose3 i, Pose3 j, Vector3 gyro bias) with the preintegration covariance."""
    noise = gtsam.noiseModel.Gaussian.Covariance(preintegration.covariance)

    def evaluate(
        factor: gtsam.CustomFactor, values: gtsam.Values, jacobians: list | None
    ) -> np.ndarray:
        key_i, key_j, key_b = factor.keys()
        error, (d_i, d_j, d_b) = gyro_rotation_error(
            preintegration,
            values.atPose3(key_i).rotation().matrix(),
            values.atPose3(key_j).rotation().matrix(),
            values.atVector(key_b),
        )
        if jacobians is not None:
            jacobians[0], jacobians[1] = _on_rotation(d_i), _on_rotation(d_j)
            jacobians[2] = d_b
        return error

    return gtsam.CustomFactor(noise, [pose_i, pose_j, bias], evaluate)
