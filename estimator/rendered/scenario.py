"""Simulated inputs for the back end: a smooth trajectory, its IMU and front-end relative poses.

The back end can be exercised without images: the relative poses a front end would report
are the true ones plus noise drawn from the same model the back end assumes (residual RMS r
over n inliers -> translation ~ r/sqrt(n), rotation ~ r/(sqrt(n) * spread)), and a chosen
fraction of frames either fails (``None``) or carries a gross error, as broken images or
wrong matches would cause. The gyro is the exact body angular rate of the trajectory plus
white noise and a slowly walking bias; the accelerometer is the exact specific force plus
noise. World z is up; gravity is -9.81 m/s^2 along it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from estimator.backend.imu import GRAVITY
from estimator.geometry import invert_pose, kabsch, make_pose
from estimator.types import ImuBatch, ImuNoise

__all__ = [
    "CAMERA_MOUNT",
    "PERFECT_IMU",
    "FrontendMeasurement",
    "Scenario",
    "aligned_ate",
    "chain",
    "simulate_frontend",
    "smooth_trajectory",
]

# A camera mounted like EuRoC's cam0: rotated ~90 deg about z and offset by a few cm
# (body_from_camera, slightly off the axes so that no term of the extrinsic vanishes).
CAMERA_MOUNT = make_pose(
    Rotation.from_euler("xyz", [0.02, -0.01, 1.55]).as_matrix(), [-0.02, -0.06, 0.01]
)
# Noise-free IMU (use with ``initial_bias=(0, 0, 0)`` for an exact one).
PERFECT_IMU = ImuNoise(gyro_noise_density=0.0, gyro_random_walk=0.0, accel_noise_density=0.0)

# Sum-of-sines trajectory: amplitude (m or rad), angular frequency (rad/s), phase (rad).
_POSITION = np.array(
    [
        [[3.0, 0.31, 0.0], [0.4, 1.3, 0.5]],  # x
        [[2.0, 0.43, 1.0], [0.3, 1.1, 2.0]],  # y
        [[0.5, 0.52, 0.3], [0.1, 1.7, 1.0]],  # z
    ]
)
_ATTITUDE = np.array(
    [
        [[0.6, 0.21, 0.0], [0.25, 1.4, 0.7]],  # yaw (plus a steady 0.25 rad/s turn)
        [[0.2, 0.73, 0.2], [0.05, 2.3, 1.1]],  # pitch
        [[0.25, 0.91, 0.3], [0.06, 2.9, 0.4]],  # roll
    ]
)
_YAW_RATE = 0.25


def _sines(table: np.ndarray, t: np.ndarray, derivative: int = 0) -> np.ndarray:
    """Evaluate sum_i A_i sin(w_i t + p_i) (or its 2nd derivative) per row -> (len(t), rows)."""
    amplitude, omega, phase = table[..., 0], table[..., 1], table[..., 2]
    arg = omega[None] * t[:, None, None] + phase[None]
    if derivative == 0:
        return (amplitude[None] * np.sin(arg)).sum(axis=-1)
    if derivative == 2:
        return (-amplitude[None] * omega[None] ** 2 * np.sin(arg)).sum(axis=-1)
    raise ValueError("derivative must be 0 or 2")


def _rotations(t: np.ndarray) -> Rotation:
    angles = _sines(_ATTITUDE, t)
    angles[:, 0] += _YAW_RATE * t
    return Rotation.from_euler("ZYX", angles)


@dataclass(frozen=True)
class Scenario:
    """Ground truth and IMU of one simulated run."""

    timestamps_ns: np.ndarray  # (N,) frame times
    body_poses: np.ndarray  # (N, 4, 4) body in world
    imu: ImuBatch  # starts before the first frame (gravity alignment window)
    gyro_bias: np.ndarray  # (M, 3) true bias at each IMU sample


@dataclass(frozen=True)
class FrontendMeasurement:
    """What a front end would hand the back end for one frame."""

    relative_pose: np.ndarray | None  # camera T_prev_cur, None when vision failed
    residuals: np.ndarray | None  # inlier residual norms (m)
    inlier_count: int
    kind: str  # "good", "failed" or "gross"


def smooth_trajectory(
    frames: int,
    seed: int,
    frame_rate_hz: float = 20.0,
    imu_rate_hz: float = 200.0,
    noise: ImuNoise | None = None,
    initial_bias: tuple[float, float, float] = (0.01, -0.02, 0.015),
    lead_in_s: float = 0.2,
) -> Scenario:
    """A smooth 3D trajectory with exact poses and a simulated IMU (seeded)."""
    if frames < 2:
        raise ValueError(f"need at least 2 frames, got {frames}")
    noise = noise or ImuNoise(rate_hz=imu_rate_hz)
    rng = np.random.default_rng(seed)
    frame_t = np.arange(frames) / frame_rate_hz
    step = 1.0 / imu_rate_hz
    imu_t = np.arange(-lead_in_s, frame_t[-1] + step / 2, step)

    rotations = _rotations(frame_t)
    poses = np.stack(
        [
            make_pose(r, p)
            for r, p in zip(rotations.as_matrix(), _sines(_POSITION, frame_t), strict=True)
        ]
    )

    # Body angular rate by a central difference of the attitude (error O(h^2), h = 0.1 ms).
    h = 1e-4
    rate = (_rotations(imu_t - h).inv() * _rotations(imu_t + h)).as_rotvec() / (2.0 * h)
    walk = rng.normal(0.0, noise.gyro_random_walk * np.sqrt(step), size=(len(imu_t), 3))
    bias = np.asarray(initial_bias, dtype=float) + np.cumsum(walk, axis=0)
    gyro_sigma = noise.gyro_noise_density * np.sqrt(imu_rate_hz)
    gyro = rate + bias + rng.normal(0.0, gyro_sigma, size=rate.shape)

    # Specific force f = R^T (a - g), with g = (0, 0, -9.81).
    world_accel = _sines(_POSITION, imu_t, derivative=2) + np.array([0.0, 0.0, GRAVITY])
    accel = _rotations(imu_t).inv().apply(world_accel)
    accel += rng.normal(0.0, noise.accel_noise_density * np.sqrt(imu_rate_hz), size=accel.shape)

    to_ns = lambda seconds: np.round(seconds * 1e9).astype(np.int64)  # noqa: E731
    return Scenario(
        timestamps_ns=to_ns(frame_t),
        body_poses=poses,
        imu=ImuBatch(to_ns(imu_t), gyro, accel),
        gyro_bias=bias,
    )


def _exp_se3(twist: np.ndarray) -> np.ndarray:
    """Small rigid perturbation: rotation vector twist[:3], translation twist[3:]."""
    return make_pose(Rotation.from_rotvec(twist[:3]).as_matrix(), twist[3:])


def simulate_frontend(
    body_poses: np.ndarray,
    body_from_camera: np.ndarray,
    seed: int,
    broken_fraction: float = 0.0,
    point_sigma_m: float = 0.03,
    point_spread_m: float = 1.5,
    inlier_range: tuple[int, int] = (60, 250),
    gross_rotation_deg: tuple[float, float] = (8.0, 25.0),
    gross_translation_m: tuple[float, float] = (0.2, 0.8),
) -> list[FrontendMeasurement]:
    """Noisy camera relative poses for frames 1..N-1 (index 0 is the first frame: no motion).

    Half of the broken frames fail (None), half carry a gross rotation and translation error
    with the residuals of a good fit, as a confident wrong registration would.
    """
    if not 0.0 <= broken_fraction <= 1.0:
        raise ValueError(f"broken_fraction must be in [0, 1], got {broken_fraction}")
    rng = np.random.default_rng(seed)
    count = len(body_poses)
    camera_poses = body_poses @ body_from_camera
    truth = invert_pose(camera_poses[:-1]) @ camera_poses[1:]
    inliers = rng.integers(inlier_range[0], inlier_range[1] + 1, size=count - 1)
    broken = rng.random(count - 1) < broken_fraction
    gross = broken & (rng.random(count - 1) < 0.5)
    measurements = [FrontendMeasurement(np.eye(4), None, 0, "first")]
    for k in range(count - 1):
        n = int(inliers[k])
        residuals = np.linalg.norm(rng.normal(0.0, point_sigma_m, size=(n, 3)), axis=1)
        sigma_t = point_sigma_m / np.sqrt(n)
        sigma_r = sigma_t / point_spread_m
        twist = np.concatenate([rng.normal(0, sigma_r, 3), rng.normal(0, sigma_t, 3)])
        if broken[k] and not gross[k]:
            measurements.append(FrontendMeasurement(None, None, 0, "failed"))
            continue
        kind = "good"
        if gross[k]:
            axis = rng.normal(size=3)
            angle = np.radians(rng.uniform(*gross_rotation_deg))
            direction = rng.normal(size=3)
            length = rng.uniform(*gross_translation_m)
            twist[:3] += angle * axis / np.linalg.norm(axis)
            twist[3:] += length * direction / np.linalg.norm(direction)
            kind = "gross"
        measurements.append(FrontendMeasurement(truth[k] @ _exp_se3(twist), residuals, n, kind))
    return measurements


def chain(relative_poses: list[np.ndarray | None], hold: bool = True) -> np.ndarray:
    """Front-end-only trajectory: compose relative poses; a failed frame repeats the previous
    motion (constant velocity) or, with ``hold``, keeps the pose."""
    poses = [np.eye(4)]
    last = np.eye(4)
    for relative in relative_poses[1:]:
        if relative is None:
            relative = np.eye(4) if hold else last
        last = relative
        poses.append(poses[-1] @ relative)
    return np.stack(poses)


def aligned_ate(estimate: np.ndarray, truth: np.ndarray) -> float:
    """Translation RMSE (m) of (N, 4, 4) poses after the best rigid alignment of positions."""
    rotation, translation = kabsch(estimate[:, :3, 3], truth[:, :3, 3])
    moved = estimate[:, :3, 3] @ rotation.T + translation
    return float(np.sqrt(np.mean(np.sum((moved - truth[:, :3, 3]) ** 2, axis=1))))
