"""The accelerometer in the graph: a three-frame inertial factor with gravity and bias variables.

Between frames 0, 1, 2 (intervals dt1, dt2) the specific force preintegrated per interval
(``SpecificForceDelta``: dp, dv in the body frame at the start of the interval) ties the
positions of three consecutive frames without any velocity variable. Eliminating v0 and v1
from p_j = p_i + v_i dt + g dt^2 / 2 + R_i dp and v_j = v_i + g dt + R_i dv gives

    (p2 - p1) / dt2 - (p1 - p0) / dt1 = R0 (dv1 - dp1 / dt1) + R1 dp2 / dt2 + g (dt1 + dt2) / 2

a velocity change (m/s) predicted by the IMU. An accelerometer bias b (body frame) removes
b dt from dv and b dt^2 / 2 from dp, i.e. adds (dt1 R0 + dt2 R1) b / 2 to the error. Why this
form: it needs no velocity variables and no initial velocity (a body that starts in motion does
not give one). Gravity g in the world frame and the bias b are variables of the graph (one
each, constant over a run): the world is the first body pose, levelled from the accelerometer
at start-up, which is only approximate when the body already moves, and the same inertial
factors that use g estimate it, so no information is used twice. What the factor gives:

* through a vision gap it carries the translation with the measured acceleration instead of a
  constant-velocity guess (on the rendered flights the body accelerates at 1-2.5 m/s^2, about
  5 mm per frame of gap at 20 Hz for constant velocity);
* on every frame it ties the trajectory's acceleration to the accelerometer, which smooths the
  vision's translation noise and, through gravity, makes roll and pitch observable.
"""

from __future__ import annotations

from dataclasses import dataclass

import gtsam
import numpy as np

from estimator.backend.imu import SpecificForceDelta

__all__ = [
    "InertialTerms",
    "inertial_factor",
    "inertial_factor_sigma",
    "predict_position",
    "velocity_change_error",
]


@dataclass(frozen=True)
class InertialTerms:
    """What the error needs from two consecutive intervals, computed once per factor."""

    dt1: float
    dt2: float
    a1: np.ndarray  # dv1 - dp1 / dt1
    a2: np.ndarray  # dp2 / dt2
    c: float  # (dt1 + dt2) / 2

    @staticmethod
    def of(first: SpecificForceDelta, second: SpecificForceDelta) -> InertialTerms:
        """From the specific force preintegrated over frames 0 -> 1 and 1 -> 2."""
        dt1, dt2 = first.duration_s, second.duration_s
        return InertialTerms(
            dt1,
            dt2,
            first.delta_velocity - first.delta_position / dt1,
            second.delta_position / dt2,
            0.5 * (dt1 + dt2),
        )


def velocity_change_error(
    terms: InertialTerms,
    pose0: np.ndarray,
    pose1: np.ndarray,
    pose2: np.ndarray,
    gravity: np.ndarray,
    accel_bias: np.ndarray,
) -> tuple[np.ndarray, tuple[np.ndarray, ...]]:
    """Error (3,) in m/s and its Jacobians: 3x6 per body pose (4x4, world), 3x3 for g and b.

    Pose3 tangent = [rotation, translation], right perturbation: p' = p + R dv and
    R' = R Exp(w), so d(R a)/dw = -R [a]x. Written for speed: GTSAM linearises every inertial
    factor of the window again on each frame.
    """
    dt1, dt2 = terms.dt1, terms.dt2
    r0, r1, r2 = pose0[:3, :3], pose1[:3, :3], pose2[:3, :3]
    a1 = terms.a1 - (0.5 * dt1) * accel_bias
    a2 = terms.a2 - (0.5 * dt2) * accel_bias
    error = (
        (pose2[:3, 3] - pose1[:3, 3]) / dt2
        - (pose1[:3, 3] - pose0[:3, 3]) / dt1
        - r0 @ a1
        - r1 @ a2
        - terms.c * gravity
    )
    d0, d1, d2 = np.empty((3, 6)), np.empty((3, 6)), np.zeros((3, 6))
    d0[:, :3] = r0 @ _skew(a1)
    d0[:, 3:] = r0 / dt1
    d1[:, :3] = r1 @ _skew(a2)
    d1[:, 3:] = r1 * -(1.0 / dt1 + 1.0 / dt2)
    d2[:, 3:] = r2 / dt2
    return error, (d0, d1, d2, -terms.c * _EYE, (0.5 * dt1) * r0 + (0.5 * dt2) * r1)


_EYE = np.eye(3)


def _skew(v: np.ndarray) -> np.ndarray:
    """``geometry.skew`` of one vector, the same matrix built in one call: the factor is
    linearised again on every frame it stays in the window (tests/test_inertial.py)."""
    x, y, z = v
    return np.array(((0.0, -z, y), (z, 0.0, -x), (-y, x, 0.0)))


def predict_position(
    terms: InertialTerms,
    pose0: np.ndarray,
    pose1: np.ndarray,
    gravity: np.ndarray,
    accel_bias: np.ndarray,
) -> np.ndarray:
    """Position of frame 2 (world) that zeroes the error: the IMU's extrapolation."""
    pose2 = np.eye(4)  # the error is linear in p2 with slope I / dt2
    error, _ = velocity_change_error(terms, pose0, pose1, pose2, gravity, accel_bias)
    return -error * terms.dt2


def inertial_factor_sigma(terms: InertialTerms, accel_noise_density: float) -> float:
    """Per-axis sigma (m/s) of the error from white accelerometer noise of density q.

    It enters dv1 - dp1/dt1 with variance q^2 dt1 / 3 and dp2/dt2 with q^2 dt2 / 3.
    """
    return float(accel_noise_density * np.sqrt((terms.dt1 + terms.dt2) / 3.0))


def inertial_factor(
    pose_keys: tuple[int, int, int],
    gravity_key: int,
    bias_key: int,
    terms: InertialTerms,
    sigma: float,
) -> gtsam.CustomFactor:
    """Factor on three consecutive Pose3 frames, world gravity and accelerometer bias."""
    noise = gtsam.noiseModel.Isotropic.Sigma(3, sigma)

    def evaluate(
        factor: gtsam.CustomFactor, values: gtsam.Values, jacobians: list | None
    ) -> np.ndarray:
        k0, k1, k2, kg, kb = factor.keys()
        error, derivatives = velocity_change_error(
            terms,
            values.atPose3(k0).matrix(),
            values.atPose3(k1).matrix(),
            values.atPose3(k2).matrix(),
            values.atVector(kg),
            values.atVector(kb),
        )
        if jacobians is not None:
            for slot, derivative in enumerate(derivatives):
                jacobians[slot] = derivative
        return error

    return gtsam.CustomFactor(noise, [*pose_keys, gravity_key, bias_key], evaluate)
