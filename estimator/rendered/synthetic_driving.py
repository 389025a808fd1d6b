"""The rendered driving scenario: a road vehicle with a KITTI-like stereo rig in a street.

The vehicle follows a road of straights and smooth turns (heading a sum of quintic
"smootherstep" turns along the arc length, so curvature is continuous) at a speed that varies
between about 0.75 and 1.25 times its mean. Arc length, speed and acceleration are closed-form
functions of time; the road's x-y position is the integral of the heading, tabulated on a
1 cm grid and interpolated with its exact derivative (cubic Hermite), so positions agree with
the closed-form velocity to micrometres. Small pitch and roll oscillations (suspension) ride on
top. The IMU sits in the body frame (x forward, y left, z up), 0.93 m above the road; the left
camera looks forward 1.65 m above the road.

The street: ground tiles along the road, building blocks on both sides with their fronts 6 to
12 m from the centreline (side streets between some), parked cars and poles 3 to 4.5 m from it,
and towers 60 to 250 m away, so the structure seen spans 3 m to well beyond 80 m.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy.integrate import cumulative_trapezoid
from scipy.interpolate import CubicHermiteSpline
from scipy.spatial import cKDTree

from estimator.geometry import make_pose
from estimator.rendered.camera import KITTI_CAMERA, R_HEADING_CAM, SimCamera
from estimator.rendered.render import Plane
from estimator.rendered.trajectory import TrajectoryState, euler_attitude
from estimator.rendered.world import World, add_plane

__all__ = [
    "DRIVING_CAMERA",
    "DRIVING_T_BS_CAM0",
    "DrivingTrajectory",
    "add_upright_box",
    "build_street",
    "driving_for_length",
]

DRIVING_CAMERA: SimCamera = KITTI_CAMERA
IMU_HEIGHT_M = 0.93
CAMERA_HEIGHT_M = 1.65
# Left camera 1.0 m ahead of the IMU, the pair centred on the vehicle's axis.
DRIVING_T_BS_CAM0 = make_pose(
    R_HEADING_CAM, [1.0, 0.5 * DRIVING_CAMERA.baseline, CAMERA_HEIGHT_M - IMU_HEIGHT_M]
)
TABLE_STEP_M = 0.01
ROAD_CLEARANCE_M = 4.5  # buildings keep at least this far from the centreline
KERB_CLEARANCE_M = 2.6  # parked cars and poles


def _smootherstep(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """6x^5 - 15x^4 + 10x^3 on [0, 1] (0 before, 1 after) and its derivative."""
    x = np.clip(x, 0.0, 1.0)
    return x**3 * (10.0 - 15.0 * x + 6.0 * x * x), 30.0 * x * x * (1.0 - x) ** 2


@dataclass
class DrivingTrajectory:
    """A drive along a road of smooth turns, with closed-form speed and attitude.

    ``turns`` are (start arc length m, length m, heading change rad); the speed is
    v(t) = mean_speed (1 + speed_wave sin(2 pi t / speed_period_s + speed_phase)).
    """

    turns: list[tuple[float, float, float]]
    mean_speed: float
    duration: float
    speed_wave: float = 0.25
    speed_period_s: float = 23.0
    speed_phase: float = 0.0
    pitch_amp: float = math.radians(0.6)
    roll_amp: float = math.radians(0.5)
    pitch_hz: float = 0.43
    roll_hz: float = 0.29
    _table: CubicHermiteSpline = field(init=False, repr=False)

    def __post_init__(self) -> None:
        # Cover the drive plus margins before the start and after the end (IMU padding).
        lowest = -5.0 * self.mean_speed - 10.0
        highest = self.arc_length(np.array([self.duration + 5.0]))[0] + 10.0
        s = np.arange(lowest, highest + TABLE_STEP_M, TABLE_STEP_M)
        heading, _ = self.heading(s)
        dx, dy = np.cos(heading), np.sin(heading)
        start = np.searchsorted(s, 0.0)
        x, y = (cumulative_trapezoid(d, s, initial=0.0) for d in (dx, dy))
        xy = np.column_stack([x - x[start], y - y[start]])
        self._table = CubicHermiteSpline(s, xy, np.column_stack([dx, dy]))

    def heading(self, s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Road heading (rad) and curvature (1/m) at arc lengths ``s``."""
        s = np.asarray(s, dtype=float)
        heading, curvature = np.zeros_like(s), np.zeros_like(s)
        for start, length, angle in self.turns:
            value, slope = _smootherstep((s - start) / length)
            heading += angle * value
            curvature += angle / length * slope
        return heading, curvature

    def _speed_terms(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        w = 2.0 * np.pi / self.speed_period_s
        q, phase, v0 = self.speed_wave, self.speed_phase, self.mean_speed
        s = v0 * (t - q / w * (np.cos(w * t + phase) - np.cos(phase)))
        v = v0 * (1.0 + q * np.sin(w * t + phase))
        a = v0 * q * w * np.cos(w * t + phase)
        return s, v, a

    def arc_length(self, t: np.ndarray) -> np.ndarray:
        return self._speed_terms(np.asarray(t, dtype=float))[0]

    def road(self, s: np.ndarray) -> np.ndarray:
        """(N, 2) centreline positions at arc lengths ``s``."""
        return self._table(np.asarray(s, dtype=float))

    def path_length(self) -> float:
        return float(self.arc_length(np.array([self.duration]))[0])

    def state(self, t: np.ndarray) -> TrajectoryState:
        t = np.asarray(t, dtype=float)
        s, speed, accel = self._speed_terms(t)
        yaw, curvature = self.heading(s)
        tangent = np.column_stack([np.cos(yaw), np.sin(yaw), np.zeros_like(yaw)])
        normal = np.column_stack([-np.sin(yaw), np.cos(yaw), np.zeros_like(yaw)])
        xy = self.road(s)
        positions = np.column_stack([xy, np.full(len(t), IMU_HEIGHT_M)])
        velocities = tangent * speed[:, None]
        accelerations = tangent * accel[:, None] + normal * (speed**2 * curvature)[:, None]
        pw, rw = 2.0 * np.pi * self.pitch_hz, 2.0 * np.pi * self.roll_hz
        pitch = self.pitch_amp * np.sin(pw * t + 0.4)
        pitch_dot = self.pitch_amp * pw * np.cos(pw * t + 0.4)
        roll = self.roll_amp * np.sin(rw * t + 1.3)
        roll_dot = self.roll_amp * rw * np.cos(rw * t + 1.3)
        rotation, omega = euler_attitude(yaw, speed * curvature, pitch, pitch_dot, roll, roll_dot)
        return TrajectoryState(positions, rotation, velocities, accelerations, omega)


def driving_for_length(
    length_m: float, duration: float, rng: np.random.Generator
) -> DrivingTrajectory:
    """A drive of ``length_m`` in ``duration`` s: a straight start, then turns and straights."""
    turns: list[tuple[float, float, float]] = []
    s = rng.uniform(25.0, 45.0)
    while s < length_m + 200.0:
        angle = math.radians(rng.uniform(25.0, 90.0)) * rng.choice([-1.0, 1.0])
        radius = rng.uniform(40.0, 90.0)
        # The smootherstep's peak slope is 15/8: this length makes ``radius`` the tightest.
        length = 1.875 * abs(angle) * radius
        turns.append((s, length, angle))
        s += length + rng.uniform(40.0, 120.0)
    phase = rng.uniform(0.0, 2.0 * np.pi)
    # Mean speed such that the arc length at ``duration`` is exactly ``length_m``.
    unit = DrivingTrajectory([], 1.0, duration, speed_phase=phase).arc_length(np.array([duration]))
    return DrivingTrajectory(turns, length_m / float(unit[0]), duration, speed_phase=phase)


# ----------------------------------------------------------------------------- street


def add_upright_box(
    planes: list[Plane],
    center: np.ndarray,
    heading: float,
    size: tuple[float, float, float],
    px_per_m: float,
    rng: np.random.Generator,
) -> None:
    """Four outward vertical faces of a box (length along ``heading``, depth, height)."""
    length, depth, height = size
    along = np.array([math.cos(heading), math.sin(heading), 0.0])
    across = np.array([-along[1], along[0], 0.0])
    down = np.array([0.0, 0.0, -1.0])
    half_l, half_d = 0.5 * length * along, 0.5 * depth * across
    top = np.array([center[0], center[1], height])
    # (top corner, direction along the face): u = n x z makes u x v (v down) the outward n.
    faces = (
        (top + half_l - half_d, -along, length),  # n = -across
        (top + half_l + half_d, -across, depth),  # n = +along
        (top - half_l + half_d, along, length),  # n = +across
        (top - half_l - half_d, across, depth),  # n = -along
    )
    for origin, u, width in faces:
        add_plane(planes, tuple(origin), u, down, width, height, px_per_m, rng)


def _footprint(center: np.ndarray, heading: float, length: float, depth: float) -> np.ndarray:
    """Points along the outline of a box's footprint (for clearance checks)."""
    along = np.array([math.cos(heading), math.sin(heading)])
    across = np.array([-along[1], along[0]])
    a, b = np.meshgrid(np.linspace(-0.5, 0.5, 9), np.array([-0.5, 0.5]))
    edges = np.concatenate(
        [np.column_stack([a.ravel(), b.ravel()]), np.column_stack([b.ravel(), a.ravel()])]
    )
    return center + edges[:, :1] * length * along + edges[:, 1:] * depth * across


@dataclass
class _Street:
    """The road sampled every metre, for placing things beside it and keeping them off it."""

    samples: np.ndarray  # arc length (m)
    road: np.ndarray  # (N, 2) centre line
    headings: np.ndarray  # (N,) rad
    tree: cKDTree
    s_end: float

    def clear(self, points: np.ndarray, distance: float) -> bool:
        """True when every point is at least ``distance`` from the centre line."""
        return bool(np.all(self.tree.query(points)[0] >= distance))

    def at(self, s: float) -> tuple[int, float, np.ndarray]:
        """Sample index, heading and left normal of the road at arc length ``s``."""
        index = min(int(np.searchsorted(self.samples, s)), len(self.samples) - 1)
        heading = float(self.headings[index])
        return index, heading, np.array([-math.sin(heading), math.cos(heading)])


def _add_ground(
    planes: list[Plane], street: _Street, rng: np.random.Generator, px_per_m: float
) -> tuple[np.ndarray, np.ndarray]:
    """16 m ground tiles within 40 m of the road; returns the corners of the area."""
    tile = 16.0
    lo, hi = street.road.min(axis=0) - 40.0, street.road.max(axis=0) + 40.0
    gx, gy = np.meshgrid(np.arange(lo[0], hi[0], tile), np.arange(lo[1], hi[1], tile))
    corners = np.column_stack([gx.ravel(), gy.ravel()])
    near = street.tree.query(corners + 0.5 * tile)[0] < 40.0
    ex, ey = np.eye(3)[0], np.eye(3)[1]
    for x, y in corners[near]:
        add_plane(planes, (x, y, 0.0), ex, ey, tile, tile, px_per_m, rng)
    return lo, hi


def _add_buildings(
    planes: list[Plane], street: _Street, rng: np.random.Generator, px_per_m: float
) -> None:
    """Building blocks on both sides, with the odd side street."""
    for side in (-1.0, 1.0):
        s = float(rng.uniform(-30.0, -10.0))
        while s < street.s_end:
            length = rng.uniform(8.0, 25.0)
            depth, height = rng.uniform(8.0, 15.0), rng.uniform(5.0, 18.0)
            offset = rng.uniform(6.0, 12.0) + 0.5 * depth
            index, heading, normal = street.at(s + 0.5 * length)
            center = street.road[index] + side * offset * normal
            if street.clear(_footprint(center, heading, length, depth), ROAD_CLEARANCE_M):
                add_upright_box(planes, center, heading, (length, depth, height), px_per_m, rng)
            gap = rng.uniform(15.0, 25.0) if rng.random() < 0.15 else rng.uniform(1.0, 6.0)
            s += length + gap


def _add_kerbside(
    planes: list[Plane], street: _Street, rng: np.random.Generator, px_per_m: float
) -> None:
    """Parked cars and poles by the kerb."""
    s = float(rng.uniform(0.0, 10.0))
    while s < street.s_end:
        index, heading, normal = street.at(s)
        side = rng.choice([-1.0, 1.0])
        if rng.random() < 0.6:
            size = (rng.uniform(3.8, 4.8), rng.uniform(1.7, 1.9), rng.uniform(1.4, 1.7))
        else:
            size = (0.3, 0.3, rng.uniform(3.0, 5.0))
        offset = rng.uniform(3.0, 4.5) + 0.5 * size[1]
        center = street.road[index] + side * offset * normal
        if street.clear(_footprint(center, heading, size[0], size[1]), KERB_CLEARANCE_M):
            add_upright_box(planes, center, heading, size, 2.0 * px_per_m, rng)
        s += rng.uniform(8.0, 30.0)


def _add_towers(
    planes: list[Plane], street: _Street, rng: np.random.Generator, px_per_m: float
) -> None:
    """Towers far from the road: what the view ahead ends on."""
    wanted = max(6, int(street.s_end / 40.0))
    for _ in range(wanted * 20):
        if wanted == 0:
            break
        index = int(rng.integers(len(street.samples)))
        angle = rng.uniform(0.0, 2.0 * np.pi)
        center = street.road[index] + rng.uniform(60.0, 250.0) * np.array(
            [math.cos(angle), math.sin(angle)]
        )
        width, height = rng.uniform(20.0, 40.0), rng.uniform(20.0, 60.0)
        if not street.clear(_footprint(center, angle, width, width), 50.0):
            continue
        add_upright_box(planes, center, angle, (width, width, height), 0.25 * px_per_m, rng)
        wanted -= 1


def build_street(
    trajectory: DrivingTrajectory,
    rng: np.random.Generator,
    px_per_m: float,
    camera: SimCamera = DRIVING_CAMERA,
) -> World:
    """Ground tiles, building blocks, parked cars, poles and far towers along the road, seen
    by ``camera``.

    The steps draw from ``rng`` in this order; changing it changes every rendered street.
    """
    s_end = trajectory.path_length() + 60.0
    samples = np.arange(-40.0, s_end, 1.0)
    road = trajectory.road(samples)
    headings, _ = trajectory.heading(samples)
    street = _Street(samples, road, headings, cKDTree(road), s_end)
    planes: list[Plane] = []
    lo, hi = _add_ground(planes, street, rng, px_per_m)
    _add_buildings(planes, street, rng, px_per_m)
    _add_kerbside(planes, street, rng, px_per_m)
    _add_towers(planes, street, rng, px_per_m)
    extent = float(np.abs(np.concatenate([lo, hi])).max()) + 250.0
    return World(planes, (extent, extent, 60.0), camera)
