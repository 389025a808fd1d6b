"""The rendered flight's motion: a closed loop in closed form, and the IMU it makes.

Position and Euler angles are closed-form functions of time, so velocity, acceleration and
angular velocity are exact derivatives and the simulated IMU (white noise + random-walk bias,
specific force in the body frame) agrees with the ground truth by construction.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import brentq

from estimator.rendered.camera import R_HEADING_CAM, T_BS_CAM0
from estimator.types import ImuNoise

GRAVITY = np.array([0.0, 0.0, -9.81])  # world z up


@dataclass
class TrajectoryState:
    """Body states at times t (all arrays have leading dimension len(t))."""

    positions: np.ndarray  # (T, 3) world
    rotations: np.ndarray  # (T, 3, 3) R_WB
    velocities: np.ndarray  # (T, 3) world
    accelerations: np.ndarray  # (T, 3) world
    angular_velocities: np.ndarray  # (T, 3) body frame

    def poses(self) -> np.ndarray:
        result = np.tile(np.eye(4), (len(self.positions), 1, 1))
        result[:, :3, :3] = self.rotations
        result[:, :3, 3] = self.positions
        return result


@dataclass
class LoopTrajectory:
    """A smooth flight along (part of) an elliptic loop, with closed-form derivatives.

    theta(t) = 2 pi fraction (tau - speed_wave sin(2 pi tau) / (2 pi)), tau = t / duration, so
    the speed varies smoothly and ``fraction`` of the loop is flown in ``duration``;
    p(theta) = (a cos theta, b sin theta, height + wave sin 3 theta). The heading frame follows
    the horizontal tangent, plus sinusoidal yaw/pitch/roll (ZYX Euler angles).
    """

    a: float
    b: float
    duration: float
    fraction: float = 1.0
    height: float = 1.4
    wave: float = 0.25
    speed_wave: float = 0.25
    yaw_amp: float = np.radians(12.0)
    pitch_amp: float = np.radians(6.0)
    roll_amp: float = np.radians(8.0)
    yaw_hz: float = 0.23
    pitch_hz: float = 0.31
    roll_hz: float = 0.17

    def _theta(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        w = 2.0 * np.pi / self.duration
        phase = w * t
        theta = self.fraction * (phase - self.speed_wave * np.sin(phase))
        theta_dot = self.fraction * w * (1.0 - self.speed_wave * np.cos(phase))
        theta_ddot = self.fraction * w * w * self.speed_wave * np.sin(phase)
        return theta, theta_dot, theta_ddot

    def _curve(self, theta: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """p, dp/dtheta, d2p/dtheta2."""
        a, b, h = self.a, self.b, self.wave
        c, s, c3, s3 = np.cos(theta), np.sin(theta), np.cos(3 * theta), np.sin(3 * theta)
        p = np.stack([a * c, b * s, self.height + h * s3], -1)
        dp = np.stack([-a * s, b * c, 3 * h * c3], -1)
        ddp = np.stack([-a * c, -b * s, -9 * h * s3], -1)
        return p, dp, ddp

    def loop_positions(self, samples: int = 2000) -> np.ndarray:
        """Points around the whole loop (the scene keeps clear of all of it)."""
        return self._curve(np.linspace(0.0, 2.0 * np.pi, samples))[0]

    def path_length(self, samples: int = 20000) -> float:
        """Length of the flown part of the loop."""
        theta = np.linspace(0.0, 2.0 * np.pi * self.fraction, samples + 1)
        p, _, _ = self._curve(theta)
        return float(np.linalg.norm(np.diff(p, axis=0), axis=1).sum())

    def state(self, t: np.ndarray) -> TrajectoryState:
        t = np.asarray(t, dtype=float)
        theta, theta_dot, theta_ddot = self._theta(t)
        p, dp, ddp = self._curve(theta)
        velocity = dp * theta_dot[:, None]
        acceleration = ddp * theta_dot[:, None] ** 2 + dp * theta_ddot[:, None]

        # Heading along the horizontal tangent, d/dt atan2(y', x') by the quotient rule.
        xp, yp, xpp, ypp = dp[:, 0], dp[:, 1], ddp[:, 0], ddp[:, 1]
        tangent_yaw = np.arctan2(yp, xp)
        tangent_yaw_dot = (xp * ypp - yp * xpp) / (xp**2 + yp**2) * theta_dot
        yaw_w, pitch_w, roll_w = (2 * np.pi * f for f in (self.yaw_hz, self.pitch_hz, self.roll_hz))
        yaw = tangent_yaw + self.yaw_amp * np.sin(yaw_w * t)
        yaw_dot = tangent_yaw_dot + self.yaw_amp * yaw_w * np.cos(yaw_w * t)
        pitch = self.pitch_amp * np.sin(pitch_w * t + 0.7)
        pitch_dot = self.pitch_amp * pitch_w * np.cos(pitch_w * t + 0.7)
        roll = self.roll_amp * np.sin(roll_w * t + 1.9)
        roll_dot = self.roll_amp * roll_w * np.cos(roll_w * t + 1.9)
        heading, omega_heading = euler_attitude(yaw, yaw_dot, pitch, pitch_dot, roll, roll_dot)
        # Body = heading frame rotated so the left camera (T_BS) looks along the heading x.
        m = R_HEADING_CAM @ T_BS_CAM0[:3, :3].T
        return TrajectoryState(p, heading @ m, velocity, acceleration, omega_heading @ m)


# Time to reach the flight's speed after a standstill (smooth start, bounded acceleration).
START_RAMP_S = 1.0


def start_after_rest(trajectory: LoopTrajectory, t: np.ndarray, ramp_s: float) -> TrajectoryState:
    """The flight started from rest at t = 0: standing still before, speeding up over ``ramp_s``.

    A time warp s(t) with s' = smoothstep(t / ramp_s) (0 before, 1 after the ramp) and s''
    continuous, so the warped states keep exact derivatives: v = v(s) s',
    a = a(s) s'^2 + v(s) s'', omega = omega(s) s'. Jumping straight to the loop's start speed
    would be an infinite acceleration, which no IMU can measure.
    """
    t = np.asarray(t, dtype=float)
    x = np.clip(t / ramp_s, 0.0, 1.0)
    s = np.where(t < ramp_s, ramp_s * (x**3 - 0.5 * x**4), t - 0.5 * ramp_s)
    ds = 3.0 * x**2 - 2.0 * x**3
    dds = 6.0 * x * (1.0 - x) / ramp_s
    base = trajectory.state(s)
    return TrajectoryState(
        base.positions,
        base.rotations,
        base.velocities * ds[:, None],
        base.accelerations * ds[:, None] ** 2 + base.velocities * dds[:, None],
        base.angular_velocities * ds[:, None],
    )


def euler_attitude(
    yaw: np.ndarray,
    yaw_dot: np.ndarray,
    pitch: np.ndarray,
    pitch_dot: np.ndarray,
    roll: np.ndarray,
    roll_dot: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """R = Rz(yaw) Ry(pitch) Rx(roll) and its angular velocity in its own (rotating) frame."""
    rotation = _rz(yaw) @ _ry(pitch) @ _rx(roll)
    omega = np.stack(
        [
            roll_dot - yaw_dot * np.sin(pitch),
            pitch_dot * np.cos(roll) + yaw_dot * np.cos(pitch) * np.sin(roll),
            -pitch_dot * np.sin(roll) + yaw_dot * np.cos(pitch) * np.cos(roll),
        ],
        -1,
    )
    return rotation, omega


def _rx(angle: np.ndarray) -> np.ndarray:
    c, s, o, z = np.cos(angle), np.sin(angle), np.ones_like(angle), np.zeros_like(angle)
    return np.stack(
        [np.stack([o, z, z], -1), np.stack([z, c, -s], -1), np.stack([z, s, c], -1)], -2
    )


def _ry(angle: np.ndarray) -> np.ndarray:
    c, s, o, z = np.cos(angle), np.sin(angle), np.ones_like(angle), np.zeros_like(angle)
    return np.stack(
        [np.stack([c, z, s], -1), np.stack([z, o, z], -1), np.stack([-s, z, c], -1)], -2
    )


def _rz(angle: np.ndarray) -> np.ndarray:
    c, s, o, z = np.cos(angle), np.sin(angle), np.ones_like(angle), np.zeros_like(angle)
    return np.stack(
        [np.stack([c, -s, z], -1), np.stack([s, c, z], -1), np.stack([z, z, o], -1)], -2
    )


def loop_for_length(
    length_m: float, duration: float, min_perimeter_m: float = 16.0
) -> LoopTrajectory:
    """A flight of path length ``length_m`` along a loop of at least ``min_perimeter_m``.

    Short sequences fly part of a room-sized loop instead of a tiny fast circle, so speed and
    turn rate stay EuRoC-like (about 2 m/s and 40 deg/s for 0.1 m per frame at 20 Hz).
    """

    def make(a: float, fraction: float = 1.0) -> LoopTrajectory:
        return LoopTrajectory(
            a=a, b=0.6 * a, duration=duration, fraction=fraction, wave=0.25 * min(1.0, a / 4.0)
        )

    perimeter = max(length_m, min_perimeter_m)
    a = brentq(lambda a: make(a).path_length() - perimeter, 1e-3, 1e4, xtol=1e-10)
    if length_m >= perimeter:
        return make(a)
    fraction = brentq(lambda f: make(a, f).path_length() - length_m, 1e-9, 1.0, xtol=1e-12)
    return make(a, fraction)


def simulate_imu(
    state: TrajectoryState,
    noise: ImuNoise,
    rng: np.random.Generator,
    scale: float = 1.0,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(gyro, accel, gyro_bias, accel_bias) measured at the given states.

    Discrete white-noise sigma = density * sqrt(rate); biases start at a small random value
    and follow a random walk with sigma = random_walk * sqrt(dt) per step. ``scale`` = 0 gives
    a perfect IMU with zero bias.
    """
    count = len(state.positions)
    dt = 1.0 / noise.rate_hz
    gyro_bias = scale * (
        rng.normal(0.0, 2e-3, 3)
        + np.cumsum(rng.normal(0.0, noise.gyro_random_walk * np.sqrt(dt), (count, 3)), axis=0)
    )
    accel_bias = scale * (
        rng.normal(0.0, 2e-2, 3)
        + np.cumsum(rng.normal(0.0, noise.accel_random_walk * np.sqrt(dt), (count, 3)), axis=0)
    )
    gyro_sigma = scale * noise.gyro_noise_density * np.sqrt(noise.rate_hz)
    accel_sigma = scale * noise.accel_noise_density * np.sqrt(noise.rate_hz)
    specific_force = np.einsum("kji,kj->ki", state.rotations, state.accelerations - GRAVITY)
    gyro = state.angular_velocities + gyro_bias + rng.normal(0.0, 1.0, (count, 3)) * gyro_sigma
    accel = specific_force + accel_bias + rng.normal(0.0, 1.0, (count, 3)) * accel_sigma
    return gyro, accel, gyro_bias, accel_bias
