"""Rendered stereo sequences with exact ground truth, written in the EuRoC/ASL layout.

The scene is a hall (floor, ceiling, four walls) with floor-to-ceiling pillars, every plane
carrying its own procedural high-contrast texture (multi-scale noise blobs, flat patches and
small checkers, so ORB finds many distinct corners). The body flies one smooth closed loop of
a chosen length: an ellipse with a vertical wave, varying speed, and yaw/pitch/roll
oscillations on top of the heading. Position and Euler angles are closed-form functions of
time, so velocity, acceleration and angular velocity are exact derivatives, and the simulated
200 Hz IMU (white noise + random-walk bias, specific force in the body frame) is consistent
with the ground truth by construction. ``standstill_s`` lets the body wait at its start pose
first and then start the same flight from rest (a smooth time warp, ``start_after_rest``).

Each plane is drawn with one ``cv2.warpPerspective`` of its texture over the image rectangle it
covers, and a per-pixel inverse-depth test (inverse depth of a plane is affine in the pixel
coordinates) resolves occlusion; rays that meet a plane behind the camera or nearer than the
near plane are rejected by the same test, which is the near-plane clipping.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable, Iterator
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Literal, get_args

import cv2
import numpy as np
from scipy.optimize import brentq

from estimator.geometry import invert_pose, make_pose, matrix_to_quat, transform_points
from estimator.types import ImuNoise

if TYPE_CHECKING:
    from estimator.rendered.synthetic_driving import DrivingTrajectory

__all__ = [
    "BROKEN_KINDS",
    "CAMERA",
    "KITTI_CAMERA",
    "LoopTrajectory",
    "Plane",
    "SimCamera",
    "SynthOptions",
    "SyntheticSequence",
    "TrajectoryState",
    "World",
    "build_world",
    "read_broken_frames",
    "simulate_imu",
    "start_after_rest",
    "synthesize",
]

Scenario = Literal["flight", "driving"]
Layout = Literal["euroc", "kitti"]
GRAVITY = np.array([0.0, 0.0, -9.81])  # world z up
MIP_LEVELS = 5
BROKEN_KINDS = ("black", "blur", "shuffled")
BROKEN_FILE = "broken_frames.csv"


@dataclass(frozen=True)
class SimCamera:
    """An ideal (undistorted, exactly rectified) stereo pair: pinhole, right camera at +x."""

    width: int
    height: int
    f: float
    cx: float
    cy: float
    baseline: float

    def __getitem__(self, key: str) -> float:
        return getattr(self, key)

    def matrix(self) -> np.ndarray:
        return np.array([[self.f, 0.0, self.cx], [0.0, self.f, self.cy], [0.0, 0.0, 1.0]])


# EuRoC-like stereo camera, but ideal (undistorted) and exactly rectified.
CAMERA = SimCamera(width=752, height=480, f=458.0, cx=367.0, cy=248.0, baseline=0.11)
# KITTI-like (sequence 00 grey cameras): 1241x376, 718.856 px, 0.54 m baseline.
KITTI_CAMERA = SimCamera(width=1241, height=376, f=718.856, cx=607.1928, cy=185.2157, baseline=0.54)


def _euroc_cam0_T_BS() -> np.ndarray:
    """EuRoC V1 cam0 -> body extrinsics, projected onto SO(3) so it is exactly rigid."""
    rotation = np.array(
        [
            [0.0148655429818, -0.999880929698, 0.00414029679422],
            [0.999557249008, 0.0149672133247, 0.025715529948],
            [-0.0257744366974, 0.00375618835797, 0.999660727178],
        ]
    )
    u, _, vt = np.linalg.svd(rotation)
    return make_pose(u @ vt, [-0.0216401454975, -0.064676986768, 0.00981073058949])


T_BS_CAM0 = _euroc_cam0_T_BS()
T_CAM0_CAM1 = make_pose(np.eye(3), [CAMERA["baseline"], 0.0, 0.0])  # right camera at +x
T_BS_CAM1 = T_BS_CAM0 @ T_CAM0_CAM1
# Columns: the camera's x (right), y (down), z (forward) in the heading frame (x fwd, z up).
R_HEADING_CAM = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


def camera_matrix(camera: SimCamera = CAMERA) -> np.ndarray:
    return camera.matrix()


# ----------------------------------------------------------------------------- options


@dataclass
class SynthOptions:
    """What to render. Defaults give a 20 m loop in 200 frames (10 s at 20 Hz)."""

    frames: int = 200
    length_m: float = 20.0
    fps: float = 20.0
    seed: int = 0
    noise: float = 0.0  # Gaussian image noise, grey levels (sigma)
    brightness: float = 0.0  # relative amplitude of slow per-camera gain changes
    blur: float = 0.0  # exposure time as a fraction of the frame interval (motion blur)
    broken_fraction: float = 0.0  # fraction of frames made useless (black/blur/shuffled)
    imu_noise_scale: float = 1.0  # 1 = EuRoC's ADIS16448 noise, 0 = perfect IMU, zero bias
    imu_rate_hz: float = 200.0
    texture_px_per_m: float = 96.0
    # Seconds the body waits at its start pose before flying (extra frames in front of the
    # ``frames`` of the flight), as EuRoC's drones do: lets a VIO initialise its gyro bias.
    standstill_s: float = 0.0
    # "flight": EuRoC-like drone in a hall; "driving": KITTI-like car in a street
    # (estimator/rendered/synthetic_driving.py). Layout "kitti" writes KITTI's odometry folders.
    scenario: Scenario = "flight"
    layout: Layout = "euroc"

    @classmethod
    def driving(cls, **overrides: object) -> SynthOptions:
        """Driving defaults: 60 s at 10 Hz over 660 m (11 m/s), 100 Hz IMU, coarser texture."""
        values: dict[str, object] = {
            "scenario": "driving",
            "frames": 600,
            "length_m": 660.0,
            "fps": 10.0,
            "imu_rate_hz": 100.0,
            "texture_px_per_m": 24.0,
        }
        return cls(**{**values, **overrides})

    def validate(self) -> None:
        if self.scenario not in get_args(Scenario):
            raise ValueError(f"scenario must be one of {get_args(Scenario)}, got {self.scenario!r}")
        if self.layout not in get_args(Layout):
            raise ValueError(f"layout must be one of {get_args(Layout)}, got {self.layout!r}")

        if self.frames < 2:
            raise ValueError(f"frames must be >= 2, got {self.frames}")
        if not 0.5 <= self.length_m <= 1000.0:
            raise ValueError(f"length_m must be in [0.5, 1000], got {self.length_m}")
        if self.fps <= 0 or self.imu_rate_hz <= 0:
            raise ValueError("fps and imu_rate_hz must be positive")
        ratio = self.imu_rate_hz / self.fps
        if abs(ratio - round(ratio)) > 1e-9:
            raise ValueError(f"imu_rate_hz ({self.imu_rate_hz}) must be a multiple of fps")
        for name in ("noise", "brightness", "blur", "imu_noise_scale", "standstill_s"):
            if not math.isfinite(getattr(self, name)):
                raise ValueError(f"{name} must be a finite number, got {getattr(self, name)}")
            if getattr(self, name) < 0:
                raise ValueError(f"{name} must be >= 0, got {getattr(self, name)}")
        if self.brightness >= 1.0:
            raise ValueError(
                f"brightness must be < 1 (relative gain change), got {self.brightness}"
            )
        if self.blur > 1.0:
            raise ValueError(f"blur is an exposure fraction in [0, 1], got {self.blur}")
        if not 0.0 <= self.broken_fraction <= 0.5:
            raise ValueError(f"broken_fraction must be in [0, 0.5], got {self.broken_fraction}")
        if self.standstill_s > 60.0:
            raise ValueError(f"standstill_s must be <= 60, got {self.standstill_s}")
        if self.texture_px_per_m < 8:
            raise ValueError(f"texture_px_per_m must be >= 8, got {self.texture_px_per_m}")
        if self.scenario == "driving" and not 2.0 <= self.length_m / self.duration_s <= 40.0:
            raise ValueError(
                f"a drive of {self.length_m} m in {self.duration_s:.1f} s is "
                f"{self.length_m / self.duration_s:.1f} m/s; keep it within 2..40 m/s"
            )

    @property
    def duration_s(self) -> float:
        return max(self.frames - 1, 1) / self.fps if self.fps > 0 else float("nan")


# ----------------------------------------------------------------------------- trajectory


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


# ----------------------------------------------------------------------------- scene


@dataclass(eq=False)
class Plane:
    """A textured rectangle origin + s u + r v (s, r in metres), visible from the u x v side."""

    origin: np.ndarray
    u: np.ndarray  # unit, along texture columns
    v: np.ndarray  # unit, along texture rows
    width: float
    height: float
    texture: np.ndarray  # uint8 (rows along v, cols along u), values >= 1 (0 marks "outside")
    normal: np.ndarray = field(init=False)
    levels: list[np.ndarray] = field(init=False)

    def __post_init__(self) -> None:
        self.normal = np.cross(self.u, self.v)
        # Mipmap pyramid: level l holds texel (s, r) of level 0 at (s, r) / 2^l (pyrDown).
        self.levels = [self.texture]
        while len(self.levels) < MIP_LEVELS and min(self.levels[-1].shape) >= 16:
            self.levels.append(np.maximum(cv2.pyrDown(self.levels[-1]), 1))

    @property
    def corners(self) -> np.ndarray:
        o, u, v = self.origin, self.u * self.width, self.v * self.height
        return np.stack([o, o + u, o + u + v, o + v])


def make_texture(rows: int, cols: int, rng: np.random.Generator) -> np.ndarray:
    """High-contrast multi-scale texture: noise blobs, flat patches and small checkers."""
    image = np.zeros((rows, cols), dtype=np.float32)
    for scale, weight in ((2.5, 1.0), (7.0, 0.9), (20.0, 0.7), (60.0, 0.5)):
        small = rng.standard_normal(
            (int(np.ceil(rows / scale)) + 3, int(np.ceil(cols / scale)) + 3)
        ).astype(np.float32)
        big = cv2.resize(
            small,
            (int(small.shape[1] * scale), int(small.shape[0] * scale)),
            interpolation=cv2.INTER_CUBIC,
        )
        image += weight * big[:rows, :cols]
    image = np.tanh(1.2 * image / (image.std() + 1e-6))
    # Flat rectangles and 3x3 checkers with sharp edges: strong, well-localised corners.
    patches = max(1, rows * cols // 900)
    sizes = rng.integers(3, 14, size=(patches, 2))
    tops = rng.integers(0, max(1, rows - 3), size=patches)
    lefts = rng.integers(0, max(1, cols - 3), size=patches)
    shades = rng.uniform(-1.0, 1.0, size=patches)
    checker = rng.random(patches) < 0.3
    for top, left, (h, w), shade, is_checker in zip(
        tops, lefts, sizes, shades, checker, strict=True
    ):
        block = image[top : top + h, left : left + w]
        if is_checker:
            yy, xx = np.indices(block.shape)
            block[...] = np.where(((yy * 3 // h) + (xx * 3 // w)) % 2 == 0, 1.0, -1.0) * 0.9
        else:
            block[...] = shade
    return np.clip(128.0 + 110.0 * image, 1.0, 255.0).astype(np.uint8)


@dataclass
class World:
    planes: list[Plane]
    bounds: tuple[float, float, float]  # hall half-extents x, y and height
    camera: SimCamera = CAMERA

    def render(self, T_WC: np.ndarray, z_near: float = 0.05) -> tuple[np.ndarray, np.ndarray]:
        """Grey image (uint8) and inverse depth (float32, 0 = nothing) seen by a camera."""
        return render_view(self.planes, T_WC, z_near, self.camera)


def _add_plane(
    planes: list[Plane],
    origin: tuple[float, float, float],
    u: np.ndarray,
    v: np.ndarray,
    width: float,
    height: float,
    px_per_m: float,
    rng: np.random.Generator,
) -> None:
    rows = max(2, round(height * px_per_m))
    cols = max(2, round(width * px_per_m))
    planes.append(
        Plane(
            np.asarray(origin, float),
            np.asarray(u, float),
            np.asarray(v, float),
            width,
            height,
            make_texture(rows, cols, rng),
        )
    )


def _add_box(
    planes: list[Plane],
    x0: float,
    x1: float,
    y0: float,
    y1: float,
    z0: float,
    z1: float,
    px_per_m: float,
    rng: np.random.Generator,
) -> None:
    """Four outward-facing vertical faces of an axis-aligned box."""
    ex, ey, ez = np.eye(3)
    h = z1 - z0
    # Each face: (origin, u, v) with u x v pointing outwards; v runs downwards (-z).
    _add_plane(planes, (x1, y0, z1), -ex, -ez, x1 - x0, h, px_per_m, rng)  # normal -y
    _add_plane(planes, (x0, y1, z1), ex, -ez, x1 - x0, h, px_per_m, rng)  # normal +y
    _add_plane(planes, (x1, y1, z1), -ey, -ez, y1 - y0, h, px_per_m, rng)  # normal +x
    _add_plane(planes, (x0, y0, z1), ey, -ez, y1 - y0, h, px_per_m, rng)  # normal -x


def build_world(trajectory: LoopTrajectory, rng: np.random.Generator, px_per_m: float) -> World:
    """Hall around the loop plus pillars kept at least 1 m clear of the flown path."""
    margin = 2.5
    half_x, half_y = trajectory.a + margin, trajectory.b + margin
    height = 3.5
    ex, ey, ez = np.eye(3)
    planes: list[Plane] = []
    # Floor (normal +z) and ceiling (normal -z).
    _add_plane(planes, (-half_x, -half_y, 0.0), ex, ey, 2 * half_x, 2 * half_y, px_per_m, rng)
    _add_plane(planes, (-half_x, half_y, height), ex, -ey, 2 * half_x, 2 * half_y, px_per_m, rng)
    # Walls facing inwards (u x v = inward normal), texture rows running down.
    _add_plane(planes, (half_x, half_y, height), -ex, -ez, 2 * half_x, height, px_per_m, rng)
    _add_plane(planes, (-half_x, -half_y, height), ex, -ez, 2 * half_x, height, px_per_m, rng)
    _add_plane(planes, (-half_x, half_y, height), -ey, -ez, 2 * half_y, height, px_per_m, rng)
    _add_plane(planes, (half_x, -half_y, height), ey, -ez, 2 * half_y, height, px_per_m, rng)

    path = trajectory.loop_positions(720)[:, :2]
    perimeter = trajectory.path_length() / trajectory.fraction
    wanted = int(np.clip(round(0.6 * perimeter), 6, 40))
    placed: list[tuple[float, float, float, float]] = []
    for _ in range(wanted * 60):
        if len(placed) == wanted:
            break
        sx, sy = rng.uniform(0.3, 0.8, size=2)
        cx = rng.uniform(-half_x + 0.4 + sx / 2, half_x - 0.4 - sx / 2)
        cy = rng.uniform(-half_y + 0.4 + sy / 2, half_y - 0.4 - sy / 2)
        clearance = 1.0 + 0.5 * np.hypot(sx, sy)
        if np.min(np.hypot(path[:, 0] - cx, path[:, 1] - cy)) < clearance:
            continue
        if any(
            abs(cx - px) < (sx + qx) / 2 + 0.3 and abs(cy - py) < (sy + qy) / 2 + 0.3
            for px, py, qx, qy in placed
        ):
            continue
        placed.append((cx, cy, sx, sy))
        _add_box(
            planes, cx - sx / 2, cx + sx / 2, cy - sy / 2, cy + sy / 2, 0.0, height, px_per_m, rng
        )
    return World(planes, (half_x, half_y, height))


# ----------------------------------------------------------------------------- rendering


def _clip_near(points: np.ndarray, z_near: float) -> np.ndarray:
    """Sutherland-Hodgman clip of a convex polygon (camera frame) against z >= z_near."""
    result = []
    count = len(points)
    for i in range(count):
        current, following = points[i], points[(i + 1) % count]
        inside_now, inside_next = current[2] >= z_near, following[2] >= z_near
        if inside_now:
            result.append(current)
        if inside_now != inside_next:
            fraction = (z_near - current[2]) / (following[2] - current[2])
            result.append(current + fraction * (following - current))
    return np.array(result).reshape(-1, 3)


def _sample_texture(
    plane: Plane,
    homography: np.ndarray,
    plane_inv: np.ndarray,
    rx: np.ndarray,
    ry: np.ndarray,
    px_per_m: float,
    d_c: float,
    f: float,
) -> np.ndarray:
    """Texture seen through each pixel, trilinearly mipmapped (float32, 0 = off the plane).

    A pixel covers px_per_m * Z / (f sqrt(cos a)) texels (a: angle between ray and normal,
    geometric mean of the two footprint axes); sampling the pyramid level of that footprint
    instead of the full texture keeps distant surfaces free of aliasing, which would otherwise
    flicker from frame to frame as no real camera does.
    """
    # The footprint varies slowly across a plane: evaluate it every 8th pixel, then upsample.
    step = 8
    coarse_x, coarse_y = rx[::step], ry[::step]
    coarse_inv = plane_inv[::step, ::step]
    ray_norm = np.sqrt(
        (coarse_y * coarse_y)[:, None] + (coarse_x * coarse_x)[None, :] + np.float32(f * f)
    ) / np.float32(f)
    ahead = coarse_inv > 0
    if not ahead.any():
        return np.zeros(plane_inv.shape, dtype=np.float32)
    inv = np.maximum(coarse_inv, np.float32(1e-6))
    cos_incidence = np.clip(np.float32(abs(d_c)) * inv / ray_norm, 1e-3, 1.0)
    footprint = np.float32(px_per_m / f) / (inv * np.sqrt(cos_incidence))
    coarse_level = np.clip(np.log2(np.maximum(footprint, 1.0)), 0.0, len(plane.levels) - 1)
    lowest = int(np.floor(coarse_level[ahead].min()))
    highest = int(np.ceil(coarse_level[ahead].max()))
    size = (len(rx), len(ry))
    result = np.zeros(plane_inv.shape, dtype=np.float32)
    if highest == lowest == 0:
        level = None
    else:
        # Clipped to the levels drawn, so the blend weights always sum to one.
        level = np.clip(
            cv2.resize(coarse_level.astype(np.float32), size, interpolation=cv2.INTER_LINEAR),
            lowest,
            highest,
        )
    weight = np.empty_like(result)
    for index in range(lowest, highest + 1):
        warped = cv2.warpPerspective(
            plane.levels[index],
            homography @ np.diag([2.0**index, 2.0**index, 1.0]),
            size,
            flags=cv2.INTER_LINEAR,
            borderMode=cv2.BORDER_CONSTANT,
            borderValue=0,
        )
        if level is None:
            result += warped
            continue
        # Tent weight max(0, 1 - |level - index|), computed in place.
        np.subtract(level, np.float32(index), out=weight)
        np.abs(weight, out=weight)
        np.subtract(np.float32(1.0), weight, out=weight)
        np.maximum(weight, np.float32(0.0), out=weight)
        weight *= warped
        result += weight
    return result


def render_view(
    planes: list[Plane], T_WC: np.ndarray, z_near: float = 0.05, camera: SimCamera = CAMERA
) -> tuple[np.ndarray, np.ndarray]:
    """Draw every plane facing the camera over its image rectangle, nearest one wins."""
    width, height = camera.width, camera.height
    f, cx, cy = camera.f, camera.cx, camera.cy
    K = camera.matrix()
    T_CW = invert_pose(T_WC)
    rotation, translation = T_CW[:3, :3], T_CW[:3, 3]
    center = T_WC[:3, 3]
    image = np.zeros((height, width), dtype=np.uint8)
    inv_depth = np.zeros((height, width), dtype=np.float32)
    for plane in planes:
        if plane.normal @ (center - plane.origin) <= 1e-6:
            continue  # back face
        polygon = _clip_near(transform_points(T_CW, plane.corners), z_near)
        if len(polygon) < 3:
            continue
        u = f * polygon[:, 0] / polygon[:, 2] + cx
        v = f * polygon[:, 1] / polygon[:, 2] + cy
        x0, x1 = max(int(np.floor(u.min())) - 1, 0), min(int(np.ceil(u.max())) + 1, width - 1)
        y0, y1 = max(int(np.floor(v.min())) - 1, 0), min(int(np.ceil(v.max())) + 1, height - 1)
        if x0 > x1 or y0 > y1:
            continue
        ppm_u = plane.texture.shape[1] / plane.width
        ppm_v = plane.texture.shape[0] / plane.height
        # Texture pixel (s, r) -> image: K [R u / ppm, R v / ppm, R o + t] [s, r, 1].
        homography = K @ np.column_stack(
            [
                rotation @ plane.u / ppm_u,
                rotation @ plane.v / ppm_v,
                rotation @ plane.origin + translation,
            ]
        )
        homography = np.array([[1.0, 0, -x0], [0, 1.0, -y0], [0, 0, 1.0]]) @ homography
        # Plane n_c . X = d_c in the camera frame; 1/Z = n_c . K^-1 [x, y, 1] / d_c.
        normal_c = rotation @ plane.normal
        d_c = plane.normal @ plane.origin + normal_c @ translation
        rx = np.arange(x0, x1 + 1, dtype=np.float32) - np.float32(cx)
        ry = np.arange(y0, y1 + 1, dtype=np.float32) - np.float32(cy)
        plane_inv = (ry * np.float32(normal_c[1] / (f * d_c)))[:, None] + (
            rx * np.float32(normal_c[0] / (f * d_c)) + np.float32(normal_c[2] / d_c)
        )[None, :]
        texture = _sample_texture(
            plane, homography, plane_inv, rx, ry, 0.5 * (ppm_u + ppm_v), d_c, f
        )
        depth_roi = inv_depth[y0 : y1 + 1, x0 : x1 + 1]
        image_roi = image[y0 : y1 + 1, x0 : x1 + 1]
        visible = (texture > 0.5) & (plane_inv > depth_roi) & (plane_inv < 1.0 / z_near)
        texture += np.float32(0.5)  # round to nearest on the cast below
        np.copyto(image_roi, texture.astype(np.uint8), where=visible)
        np.copyto(depth_roi, plane_inv, where=visible)
    return image, inv_depth


# ----------------------------------------------------------------------------- IMU


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


# ----------------------------------------------------------------------------- image effects


def _blur_kernel(displacement: np.ndarray) -> np.ndarray | None:
    """Normalised line kernel along an image displacement (px); None when under a pixel."""
    length = float(np.hypot(*displacement))
    if length < 1.0:
        return None
    half = int(np.ceil(length / 2)) + 1
    kernel = np.zeros((2 * half + 1, 2 * half + 1), dtype=np.float32)
    direction = displacement / length
    start = np.round(half - direction * length / 2).astype(int)
    end = np.round(half + direction * length / 2).astype(int)
    cv2.line(kernel, (int(start[0]), int(start[1])), (int(end[0]), int(end[1])), 1.0, 1)
    return kernel / kernel.sum()


def _mean_flow(inv_depth: np.ndarray, T_C0_C1: np.ndarray, camera: SimCamera) -> np.ndarray:
    """Mean image displacement of a pixel grid when the camera moves by T_C0_C1."""
    f, cx, cy = camera.f, camera.cx, camera.cy
    ys, xs = np.mgrid[8 : inv_depth.shape[0] : 24, 8 : inv_depth.shape[1] : 24]
    inv = inv_depth[ys, xs]
    valid = inv > 0
    if not valid.any():
        return np.zeros(2)
    z = 1.0 / inv[valid]
    points = np.stack([(xs[valid] - cx) / f * z, (ys[valid] - cy) / f * z, z], -1)
    moved = transform_points(invert_pose(T_C0_C1), points)
    ahead = moved[:, 2] > 0.05
    if not ahead.any():
        return np.zeros(2)
    moved = moved[ahead]
    flow = np.stack(
        [
            f * moved[:, 0] / moved[:, 2] + cx - xs[valid][ahead],
            f * moved[:, 1] / moved[:, 2] + cy - ys[valid][ahead],
        ],
        -1,
    )
    return np.median(flow, axis=0)


# ----------------------------------------------------------------------------- sequence


@dataclass
class SyntheticSequence:
    """What ``synthesize`` wrote (all times in ns, poses body-in-world)."""

    root: Path
    options: SynthOptions
    frame_timestamps_ns: np.ndarray
    imu_timestamps_ns: np.ndarray
    body_poses: np.ndarray  # at the IMU timestamps
    broken: dict[int, str] = field(default_factory=dict)  # frame index -> kind
    path_length_m: float = 0.0
    world: World | None = None  # the rendered scene, for checks against the images
    trajectory: LoopTrajectory | DrivingTrajectory | None = None


START_NS = 1_600_000_000_000_000_000  # 19-digit timestamps, like EuRoC's


def _write_camera_yaml(
    path: Path, T_BS: np.ndarray, comment: str, camera: SimCamera = CAMERA, rate_hz: float = 20.0
) -> None:
    data = ", ".join(repr(float(v)) for v in T_BS.reshape(16))
    path.write_text(
        "%YAML:1.0\n"
        f"sensor_type: camera\ncomment: {comment}\n"
        f"T_BS:\n  cols: 4\n  rows: 4\n  data: [{data}]\n"
        f"rate_hz: {rate_hz:g}\nresolution: [{camera.width}, {camera.height}]\n"
        "camera_model: pinhole\n"
        f"intrinsics: [{camera.f}, {camera.f}, {camera.cx}, {camera.cy}]\n"
        "distortion_model: none\ndistortion_coefficients: []\n"
    )


def _write_imu_yaml(path: Path, noise: ImuNoise) -> None:
    path.write_text(
        "%YAML:1.0\nsensor_type: imu\ncomment: simulated IMU\n"
        "T_BS:\n  cols: 4\n  rows: 4\n"
        "  data: [1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0]\n"
        f"rate_hz: {noise.rate_hz!r}\n"
        f"gyroscope_noise_density: {noise.gyro_noise_density!r}\n"
        f"gyroscope_random_walk: {noise.gyro_random_walk!r}\n"
        f"accelerometer_noise_density: {noise.accel_noise_density!r}\n"
        f"accelerometer_random_walk: {noise.accel_random_walk!r}\n"
    )


def _write_table(path: Path, header: str, timestamps: np.ndarray, values: np.ndarray) -> None:
    """CSV with exact integer ns timestamps and full-precision (17 digit) values."""
    rows = (
        f"{t}," + ",".join(f"{v:.17g}" for v in row)
        for t, row in zip(timestamps.tolist(), values.tolist(), strict=True)
    )
    path.write_text(header + "\n" + "\n".join(rows) + "\n")


def read_broken_frames(root: Path) -> dict[int, str]:
    """Frame index -> kind of the frames ``synthesize`` broke on purpose (empty if none)."""
    path = Path(root) / BROKEN_FILE
    if not path.is_file():
        return {}
    broken = {}
    for line in path.read_text().splitlines():
        if line and not line.startswith("#"):
            _, index, kind = line.split(",")
            broken[int(index)] = kind
    return broken


def synthesize(
    out_dir: Path,
    options: SynthOptions | None = None,
    progress: Callable[[int], object] | None = None,
) -> SyntheticSequence:
    """Render a stereo + IMU sequence into ``out_dir`` (EuRoC layout under ``out_dir/mav0``).

    ``progress`` is an optional callable taking the number of frames just rendered.
    """
    options = options or SynthOptions()
    options.validate()
    out_dir = Path(out_dir)
    mav0 = out_dir / "mav0"
    for existing in (mav0, out_dir / "image_0"):
        if existing.exists():
            raise ValueError(f"{existing} already exists; choose an empty output folder")
    rng = np.random.default_rng(options.seed)
    frame_step_ns = round(1e9 / options.fps)
    imu_step_ns = round(1e9 / options.imu_rate_hz)
    per_frame = frame_step_ns // imu_step_ns
    duration = (options.frames - 1) / options.fps
    rig = _scene(options, duration, rng)
    trajectory, world = rig.trajectory, rig.world

    # IMU and ground truth on one 200 Hz grid, 0.2 s beyond both ends; frames every per_frame.
    # A standstill prepends still frames; the flight then starts (from rest) at frame ``still``.
    still = round(options.standstill_s * options.fps)
    total = options.frames + still
    margin = round(0.2 * options.imu_rate_hz)
    imu_index = np.arange(-margin, (total - 1) * per_frame + margin + 1)
    imu_ns = START_NS + imu_index * imu_step_ns
    if still:
        flight_t = (imu_index - still * per_frame) * (imu_step_ns * 1e-9)
        state = start_after_rest(trajectory, flight_t, START_RAMP_S)
    else:
        state = trajectory.state(imu_index * (imu_step_ns * 1e-9))
    noise = ImuNoise(rate_hz=options.imu_rate_hz)
    gyro, accel, gyro_bias, accel_bias = simulate_imu(state, noise, rng, options.imu_noise_scale)
    frame_rows = margin + np.arange(total) * per_frame
    frame_ns = imu_ns[frame_rows]
    body_poses = state.poses()

    if options.layout == "kitti":
        writer = _kitti_writer(out_dir, rig, frame_ns, body_poses[frame_rows])
    else:
        writer = _euroc_writer(mav0, rig, options, imu_ns, state, (gyro, accel), frame_ns)
        _write_ground_truth(mav0, imu_ns, state, gyro_bias, accel_bias)

    broken = _choose_broken(options, total, rng)
    # A shuffled frame gets the (unbroken) right image of the frame half a loop away.
    donors = {i: (i + total // 2) % total for i, kind in broken.items() if kind == "shuffled"}
    kept_right: dict[int, np.ndarray] = {}
    for index, left, right in _render_frames(
        rig, body_poses, frame_rows, per_frame, options, rng, progress
    ):
        if index in donors.values():
            kept_right[index] = right
        if broken.get(index) == "black":
            left, right = np.zeros_like(left), np.zeros_like(right)
        elif broken.get(index) == "blur":
            left, right = (cv2.GaussianBlur(im, (0, 0), 12.0) for im in (left, right))
        writer(index, left, "left")
        writer(index, right, "right")
    for index, donor in donors.items():
        writer(index, kept_right[donor], "right")
    if broken:
        lines = [f"{frame_ns[i]},{i},{kind}" for i, kind in sorted(broken.items())]
        (out_dir / BROKEN_FILE).write_text("#timestamp [ns],index,kind\n" + "\n".join(lines) + "\n")
    path_length = float(
        np.linalg.norm(np.diff(body_poses[frame_rows, :3, 3], axis=0), axis=1).sum()
    )
    scene = (
        {"loop_semi_axes_m": [trajectory.a, trajectory.b], "hall_half_extents_m": world.bounds}
        if isinstance(trajectory, LoopTrajectory)
        else {"turns": len(trajectory.turns), "mean_speed_mps": trajectory.mean_speed}
    )
    (out_dir / "synth.json").write_text(
        json.dumps(
            {
                "options": asdict(options),
                "path_length_m": path_length,
                **scene,
                "planes": len(world.planes),
            },
            indent=2,
        )
    )
    return SyntheticSequence(
        out_dir, options, frame_ns, imu_ns, body_poses, broken, path_length, world, trajectory
    )


@dataclass
class SceneRig:
    """What a scenario renders: the motion, the world and where the stereo pair sits on it."""

    trajectory: LoopTrajectory | DrivingTrajectory
    world: World
    T_BS_cam0: np.ndarray

    @property
    def camera(self) -> SimCamera:
        return self.world.camera

    @property
    def T_cam0_cam1(self) -> np.ndarray:
        return make_pose(np.eye(3), [self.camera.baseline, 0.0, 0.0])


def _scene(options: SynthOptions, duration: float, rng: np.random.Generator) -> SceneRig:
    if options.scenario == "driving":
        from estimator.rendered.synthetic_driving import (
            DRIVING_T_BS_CAM0,
            build_street,
            driving_for_length,
        )

        drive = driving_for_length(options.length_m, duration, rng)
        street = build_street(drive, rng, options.texture_px_per_m)
        return SceneRig(drive, street, DRIVING_T_BS_CAM0)
    loop = loop_for_length(options.length_m, duration)
    return SceneRig(loop, build_world(loop, rng, options.texture_px_per_m), T_BS_CAM0)


Writer = Callable[[int, np.ndarray, str], None]


def _euroc_writer(
    mav0: Path,
    rig: SceneRig,
    options: SynthOptions,
    imu_ns: np.ndarray,
    state: TrajectoryState,
    imu: tuple[np.ndarray, np.ndarray],
    frame_ns: np.ndarray,
) -> Writer:
    """Write the EuRoC folders and sensor files; returns the image writer."""
    for name in ("cam0/data", "cam1/data", "imu0", "state_groundtruth_estimate0"):
        (mav0 / name).mkdir(parents=True, exist_ok=True)
    T_BS_cam1 = rig.T_BS_cam0 @ rig.T_cam0_cam1
    for name, T_BS, side in (("cam0", rig.T_BS_cam0, "left"), ("cam1", T_BS_cam1, "right")):
        _write_camera_yaml(
            mav0 / name / "sensor.yaml", T_BS, f"simulated {side} camera", rig.camera, options.fps
        )
    noise = ImuNoise(rate_hz=options.imu_rate_hz)
    _write_imu_yaml(mav0 / "imu0" / "sensor.yaml", noise)
    (mav0 / "body.yaml").write_text("%YAML:1.0\ncomment: swarmvo synthetic sequence\n")
    _write_table(
        mav0 / "imu0" / "data.csv",
        "#timestamp [ns],w_RS_S_x [rad s^-1],w_RS_S_y [rad s^-1],w_RS_S_z [rad s^-1],"
        "a_RS_S_x [m s^-2],a_RS_S_y [m s^-2],a_RS_S_z [m s^-2]",
        imu_ns,
        np.hstack(imu),
    )
    camera_rows = "\n".join(f"{t},{t}.png" for t in frame_ns.tolist())
    for camera in ("cam0", "cam1"):
        (mav0 / camera / "data.csv").write_text("#timestamp [ns],filename\n" + camera_rows + "\n")
    folders = {"left": mav0 / "cam0" / "data", "right": mav0 / "cam1" / "data"}

    def write(index: int, image: np.ndarray, side: str) -> None:
        cv2.imwrite(str(folders[side] / f"{frame_ns[index]}.png"), image)

    return write


def _write_ground_truth(
    mav0: Path,
    imu_ns: np.ndarray,
    state: TrajectoryState,
    gyro_bias: np.ndarray,
    accel_bias: np.ndarray,
) -> None:
    _write_table(
        mav0 / "state_groundtruth_estimate0" / "data.csv",
        "#timestamp, p_RS_R_x [m], p_RS_R_y [m], p_RS_R_z [m], q_RS_w [], q_RS_x [], q_RS_y [], "
        "q_RS_z [], v_RS_R_x [m s^-1], v_RS_R_y [m s^-1], v_RS_R_z [m s^-1], "
        "b_w_RS_S_x [rad s^-1], b_w_RS_S_y [rad s^-1], b_w_RS_S_z [rad s^-1], "
        "b_a_RS_S_x [m s^-2], b_a_RS_S_y [m s^-2], b_a_RS_S_z [m s^-2]",
        imu_ns,
        np.hstack(
            [
                state.positions,
                matrix_to_quat(state.rotations),
                state.velocities,
                gyro_bias,
                accel_bias,
            ]
        ),
    )


def _kitti_writer(
    out_dir: Path, rig: SceneRig, frame_ns: np.ndarray, frame_body_poses: np.ndarray
) -> Writer:
    """KITTI odometry layout: image_0/ image_1/ NNNNNN.png, calib.txt, times.txt, poses.txt.

    Poses are left-camera poses relative to the first one (KITTI's convention); times are
    seconds since the first frame. KITTI has no IMU, so none is written.
    """
    from estimator.formats.trajectory_io import format_seconds, write_kitti

    folders = {"left": out_dir / "image_0", "right": out_dir / "image_1"}
    for folder in folders.values():
        folder.mkdir(parents=True, exist_ok=True)
    c = rig.camera
    rows = []
    for label, offset in (("P0", 0.0), ("P1", -c.f * c.baseline)):
        values = [c.f, 0.0, c.cx, offset, 0.0, c.f, c.cy, 0.0, 0.0, 0.0, 1.0, 0.0]
        rows.append(f"{label}: " + " ".join(f"{v:.12e}" for v in values))
    (out_dir / "calib.txt").write_text("\n".join(rows) + "\n")
    relative_ns = frame_ns - frame_ns[0]
    (out_dir / "times.txt").write_text("".join(format_seconds(t) + "\n" for t in relative_ns))
    cameras = frame_body_poses @ rig.T_BS_cam0
    write_kitti(out_dir / "poses.txt", invert_pose(cameras[0]) @ cameras)

    def write(index: int, image: np.ndarray, side: str) -> None:
        cv2.imwrite(str(folders[side] / f"{index:06d}.png"), image)

    return write


def _choose_broken(options: SynthOptions, total: int, rng: np.random.Generator) -> dict[int, str]:
    """Frames to break among all ``total`` (never the first two, so the odometry can start)."""
    count = round(options.broken_fraction * total)
    candidates = np.arange(2, total)
    count = min(count, len(candidates))
    if count == 0:
        return {}
    chosen = np.sort(rng.choice(candidates, size=count, replace=False))
    kinds = rng.choice(len(BROKEN_KINDS), size=count)
    return {int(i): BROKEN_KINDS[k] for i, k in zip(chosen, kinds, strict=True)}


def _render_frames(
    rig: SceneRig,
    body_poses: np.ndarray,
    frame_rows: np.ndarray,
    per_frame: int,
    options: SynthOptions,
    rng: np.random.Generator,
    progress: Callable[[int], object] | None,
) -> Iterator[tuple[int, np.ndarray, np.ndarray]]:
    """Yield (index, left, right) rendered, with gain changes, motion blur and sensor noise."""
    phases = rng.uniform(0.0, 2 * np.pi, size=4)
    world, T_BS = rig.world, rig.T_BS_cam0
    for index, row in enumerate(frame_rows):
        T_WC0 = body_poses[row] @ T_BS
        left, inv_depth = world.render(T_WC0)
        right, _ = world.render(T_WC0 @ rig.T_cam0_cam1)
        if options.blur > 0:
            # Exposure ends at the frame time: the camera moved over the blur fraction before.
            steps = options.blur * per_frame
            earlier = body_poses[max(0, round(row - steps))] @ T_BS
            flow = _mean_flow(inv_depth, invert_pose(T_WC0) @ earlier, world.camera)
            kernel = _blur_kernel(flow)
            if kernel is not None:
                left, right = (cv2.filter2D(im, -1, kernel) for im in (left, right))
        if options.brightness > 0:
            t = index / options.fps
            gains = [
                1.0 + options.brightness * np.sin(2 * np.pi * t / 3.1 + phases[0]),
                1.0
                + options.brightness
                * (
                    np.sin(2 * np.pi * t / 3.1 + phases[0]) * 0.8
                    + 0.2 * np.sin(2 * np.pi * t / 1.7 + phases[1])
                ),
            ]
            left, right = (
                cv2.convertScaleAbs(im, alpha=g) for im, g in zip((left, right), gains, strict=True)
            )
        if options.noise > 0:
            left, right = (
                np.clip(im + rng.normal(0.0, options.noise, im.shape), 0, 255).astype(np.uint8)
                for im in (left, right)
            )
        if progress is not None:
            progress(1)
        yield index, left, right
