"""IMU preintegration, sample buffering and gravity alignment for the back end.

The gyro gives the rotation between frames; the accelerometer sets the initial roll and pitch
and, preintegrated into a velocity and a position increment per frame interval
(``preintegrate_specific_force``), feeds the inertial factor of ``inertial.py``. Between two
frames the gyro samples are preintegrated with GTSAM's
``PreintegratedAhrsMeasurements`` (which also propagates the 3x3 covariance); the Jacobian of
the preintegrated rotation with respect to the gyro bias is propagated alongside with the same
recursion GTSAM uses internally (its Python binding does not expose it), so the rotation
factor can correct for a changing bias estimate without re-integrating.
"""

from __future__ import annotations

from dataclasses import dataclass

import gtsam
import numpy as np

from estimator.imu_sampling import sample_segments
from estimator.types import ImuBatch, ImuNoise

__all__ = [
    "GRAVITY",
    "GyroPreintegration",
    "ImuBuffer",
    "SpecificForceDelta",
    "gravity_aligned_rotation",
    "preintegrate_gyro",
    "preintegrate_specific_force",
    "rotation_params",
]

GRAVITY = 9.81  # m/s^2, magnitude only: the world z axis points up (against gravity)

Segments = tuple[np.ndarray, np.ndarray]  # (K, 3) mean value per piece, (K,) durations in s


@dataclass(frozen=True)
class GyroPreintegration:
    """The gyro between two frames, summarised in the body frame of the first one."""

    delta_rotation: np.ndarray  # (3, 3) R_i^T R_j predicted with bias = bias_hat
    bias_jacobian: np.ndarray  # (3, 3) d Log(delta_rotation) / d bias, first order
    covariance: np.ndarray  # (3, 3) of the rotation error (tangent space)
    bias_hat: np.ndarray  # (3,) gyro bias subtracted during integration
    duration_s: float


def rotation_params(noise: ImuNoise, noise_scale: float = 1.0) -> gtsam.PreintegratedRotationParams:
    """GTSAM preintegration parameters from the continuous-time gyro noise density.

    GTSAM wants the continuous-time covariance (rad^2/s); it divides by dt per sample, which
    yields the discrete sigma density * sqrt(rate) of the sensor sheet.
    """
    if noise.gyro_noise_density <= 0.0 or noise_scale <= 0.0:
        raise ValueError("gyro noise density and its scale must be positive")
    params = gtsam.PreintegratedRotationParams()
    params.setGyroscopeCovariance(np.eye(3) * (noise.gyro_noise_density * noise_scale) ** 2)
    return params


def preintegrate_gyro(
    timestamps_ns: np.ndarray,
    gyro: np.ndarray,
    start_ns: int,
    end_ns: int,
    params: gtsam.PreintegratedRotationParams,
    bias_hat: np.ndarray | None = None,
    segments: Segments | None = None,
) -> GyroPreintegration:
    """Preintegrate the gyro over [start_ns, end_ns] with bias ``bias_hat`` removed.

    ``segments``: the gyro's ``sample_segments`` over the interval when the caller has them
    already (the accelerometer's preintegration uses the same ones).
    """
    bias_hat = np.zeros(3) if bias_hat is None else np.asarray(bias_hat, dtype=float)
    if segments is None:
        segments = sample_segments(timestamps_ns, gyro, start_ns, end_ns)
    rates, durations = segments
    pim = gtsam.PreintegratedAhrsMeasurements(params, bias_hat)
    bias_jacobian = np.zeros((3, 3))
    # One C++ call per IMU sample (~10 per frame); the 3x3 recursion mirrors GTSAM's
    # PreintegratedRotation::update: D <- dR^T D - Jr(w dt) dt.
    for rate, duration in zip(rates, durations, strict=True):
        pim.integrateMeasurement(rate, duration)
        increment = (rate - bias_hat) * duration
        step = gtsam.Rot3.Expmap(increment).matrix()
        bias_jacobian = step.T @ bias_jacobian - gtsam.Rot3.ExpmapDerivative(increment) * duration
    return GyroPreintegration(
        delta_rotation=pim.deltaRij().matrix(),
        bias_jacobian=bias_jacobian,
        covariance=np.array(pim.preintMeasCov()),
        bias_hat=bias_hat.copy(),
        duration_s=float(pim.deltaTij()),
    )


@dataclass(frozen=True)
class SpecificForceDelta:
    """The accelerometer between two frames, in the body frame of the first one.

    With gravity g in the world and the first frame's rotation R_i, velocity v_i:
    p_j = p_i + v_i dt + g dt^2 / 2 + R_i delta_position and v_j = v_i + g dt + R_i
    delta_velocity (the specific force rotated by the gyro, integrated once and twice).
    """

    delta_position: np.ndarray  # (3,) m
    delta_velocity: np.ndarray  # (3,) m/s
    duration_s: float


# Gravity is left out of GTSAM's integration (the caller handles it in its own world frame),
# and the covariance it propagates is not used: the inertial factor has its own noise model.
_SPECIFIC_FORCE_PARAMS = gtsam.PreintegrationParams(np.zeros(3))
_SPECIFIC_FORCE_PARAMS.setAccelerometerCovariance(np.eye(3))
_SPECIFIC_FORCE_PARAMS.setGyroscopeCovariance(np.eye(3))
_SPECIFIC_FORCE_PARAMS.setIntegrationCovariance(np.eye(3))


def preintegrate_specific_force(
    timestamps_ns: np.ndarray,
    gyro: np.ndarray,
    accel: np.ndarray,
    start_ns: int,
    end_ns: int,
    gyro_bias: np.ndarray | None = None,
    accel_bias: np.ndarray | None = None,
    gyro_segments: Segments | None = None,
) -> SpecificForceDelta:
    """Velocity and position increments of the specific force over [start_ns, end_ns].

    GTSAM's ``PreintegratedImuMeasurements`` does the integration (gravity zero, biases
    removed); both signals are cut at the frame times like the gyro (``sample_segments``;
    ``gyro_segments``: the gyro's, when the caller has them already).
    """
    if gyro_segments is None:
        gyro_segments = sample_segments(timestamps_ns, gyro, start_ns, end_ns)
    rates, durations = gyro_segments
    forces, _ = sample_segments(timestamps_ns, accel, start_ns, end_ns)
    bias = gtsam.imuBias.ConstantBias(
        np.zeros(3) if accel_bias is None else np.asarray(accel_bias, dtype=float),
        np.zeros(3) if gyro_bias is None else np.asarray(gyro_bias, dtype=float),
    )
    pim = gtsam.PreintegratedImuMeasurements(_SPECIFIC_FORCE_PARAMS, bias)
    for force, rate, duration in zip(forces, rates, durations, strict=True):
        pim.integrateMeasurement(force, rate, duration)
    return SpecificForceDelta(
        delta_position=np.asarray(pim.deltaPij(), dtype=float).copy(),
        delta_velocity=np.asarray(pim.deltaVij(), dtype=float).copy(),
        duration_s=float(pim.deltaTij()),
    )


def gravity_aligned_rotation(accel: np.ndarray) -> np.ndarray:
    """World-from-body rotation with roll/pitch from the mean specific force and yaw = 0.

    At rest the accelerometer measures the reaction to gravity, R_wb^T (0, 0, g): the body's
    view of world "up". With R_wb = Rz(0) Ry(pitch) Rx(roll), R_wb^T e_z =
    (-sin p, sin r cos p, cos r cos p), hence roll = atan2(f_y, f_z) and
    pitch = atan2(-f_x, hypot(f_y, f_z)). Yaw is unobservable from gravity and set to 0.
    """
    accel = np.asarray(accel, dtype=float).reshape(-1, 3)
    if len(accel) == 0:
        raise ValueError("gravity alignment needs at least one accelerometer sample")
    if not np.all(np.isfinite(accel)):
        raise ValueError("accelerometer samples contain NaN or inf")
    mean = accel.mean(axis=0)
    norm = float(np.linalg.norm(mean))
    if not 0.5 * GRAVITY < norm < 1.5 * GRAVITY:
        raise ValueError(
            f"mean specific force {norm:.2f} m/s^2 is far from gravity ({GRAVITY} m/s^2): "
            "the window is not static enough (or not in m/s^2) to align with gravity"
        )
    roll = np.arctan2(mean[1], mean[2])
    pitch = np.arctan2(-mean[0], np.hypot(mean[1], mean[2]))
    return gtsam.Rot3.Ypr(0.0, pitch, roll).matrix()


class ImuBuffer:
    """Recent IMU samples, so an interval shifted by the camera-IMU time offset can be cut.

    Frames deliver "the samples since the previous frame" in camera time; with a non-zero
    offset the interval in IMU time straddles two deliveries, so samples are kept until no
    future interval can need them.
    """

    def __init__(self) -> None:
        self.timestamps_ns = np.zeros(0, dtype=np.int64)
        self.gyro = np.zeros((0, 3))
        self.accel = np.zeros((0, 3))

    def __len__(self) -> int:
        return len(self.timestamps_ns)

    def extend(self, batch: ImuBatch) -> None:
        """Append samples newer than what is stored (repeats and older ones are dropped)."""
        stamps = np.asarray(batch.timestamps_ns, dtype=np.int64)
        gyro = np.asarray(batch.gyro, dtype=float).reshape(-1, 3)
        accel = np.asarray(batch.accel, dtype=float).reshape(-1, 3)
        if not (len(stamps) == len(gyro) == len(accel)):
            raise ValueError(
                f"IMU batch sizes differ: {len(stamps)} stamps, {len(gyro)} gyro, "
                f"{len(accel)} accel"
            )
        if len(stamps) > 1 and np.any(np.diff(stamps) <= 0):
            raise ValueError("IMU timestamps must be strictly increasing")
        if not (np.all(np.isfinite(gyro)) and np.all(np.isfinite(accel))):
            raise ValueError("IMU samples contain NaN or inf")
        if len(self.timestamps_ns):
            keep = stamps > self.timestamps_ns[-1]
            stamps, gyro, accel = stamps[keep], gyro[keep], accel[keep]
        self.timestamps_ns = np.concatenate([self.timestamps_ns, stamps])
        self.gyro = np.concatenate([self.gyro, gyro])
        self.accel = np.concatenate([self.accel, accel])

    def covers(self, start_ns: int, end_ns: int, max_gap_ns: int) -> bool:
        """Whether samples reach within ``max_gap_ns`` of both ends and have no larger hole."""
        inside = self.timestamps_ns[
            (self.timestamps_ns >= start_ns - max_gap_ns)
            & (self.timestamps_ns <= end_ns + max_gap_ns)
        ]
        if len(inside) == 0:
            return False
        edges = np.concatenate([[start_ns], inside, [end_ns]])
        edges = np.clip(edges, start_ns, end_ns)
        return bool(np.max(np.diff(edges)) <= max_gap_ns)

    def between(self, start_ns: int, end_ns: int) -> ImuBatch:
        """The samples in (start, end]: each sample counted once."""
        return ImuBatch(self.timestamps_ns, self.gyro, self.accel).between(start_ns, end_ns)

    def window(self, start_ns: int, end_ns: int) -> ImuBatch:
        """Samples spanning [start, end]: one sample either side for interpolation."""
        stamps = self.timestamps_ns
        first = max(int(np.searchsorted(stamps, start_ns, side="right")) - 1, 0)
        last = min(int(np.searchsorted(stamps, end_ns, side="left")) + 1, len(stamps))
        return ImuBatch(stamps[first:last], self.gyro[first:last], self.accel[first:last])

    def drop_before(self, time_ns: int) -> None:
        """Forget samples older than the last one at or before ``time_ns``."""
        first = max(int(np.searchsorted(self.timestamps_ns, time_ns, side="right")) - 1, 0)
        self.timestamps_ns = self.timestamps_ns[first:]
        self.gyro = self.gyro[first:]
        self.accel = self.accel[first:]
