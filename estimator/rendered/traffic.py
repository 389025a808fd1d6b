"""Moving vehicles on the rendered road: what a real drive has and a static street has not.

A real street moves: oncoming cars, cars in the next lane, and a car ahead that keeps its
distance, whose points barely move in the image and agree with a camera that stands still.
Each vehicle here is a textured box (a car, or a truck one time in five) that keeps to a lane
beside the road's centreline and moves along it at its own speed; the lead vehicle drives in
the ego's lane a fixed gap ahead. ``Traffic.planes_at`` gives the boxes' planes at a time, which
``World.render`` draws with the street (``World.movers``).

The vehicles are drawn from their own random stream, so a street rendered with traffic is the
same street as without it.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import StrEnum

import numpy as np

from estimator.rendered.render import Plane
from estimator.rendered.synthetic_driving import DrivingTrajectory, add_upright_box

__all__ = ["LANE_OFFSET_M", "Traffic", "Vehicle", "VehicleKind", "build_traffic"]

LANE_OFFSET_M = 2.0  # the next lanes' centres from the road's centreline (the ego's lane)
LEAD_GAP_M = (15.0, 30.0)  # the lead vehicle's centre ahead of the ego's body
ONCOMING_SPEED_MPS = (8.0, 14.0)
SAME_WAY_SPEED_MPS = (6.0, 16.0)


class VehicleKind(StrEnum):
    LEAD = "lead"  # the ego's lane, a fixed gap ahead
    ONCOMING = "oncoming"  # the left lane, towards the ego
    SAME_WAY = "same-way"  # the right lane, the ego's direction at its own speed


@dataclass(frozen=True)
class Vehicle:
    """A box on the road: its planes in its own frame (x forward, y left, z up, on the ground)."""

    kind: VehicleKind
    planes: tuple[Plane, ...]
    lane_offset_m: float  # to the left of the centreline
    start_s: float  # arc length at time 0 (the lead: its gap ahead of the ego)
    speed_mps: float  # along the road, negative towards its start (the lead: the ego's mean)

    def arc_length(self, road: DrivingTrajectory, time_s: float) -> float:
        if self.kind is VehicleKind.LEAD:
            return float(road.arc_length(np.array([time_s]))[0]) + self.start_s
        return self.start_s + self.speed_mps * time_s


@dataclass(frozen=True)
class Traffic:
    """The vehicles on ``road``; ``planes_at`` gives their planes at a time."""

    road: DrivingTrajectory
    vehicles: tuple[Vehicle, ...]

    def poses_at(self, time_s: float) -> np.ndarray:
        """(N, 4, 4) world poses of the vehicles at ``time_s``: on the road, turned with it (an
        oncoming vehicle facing the other way)."""
        s = np.array([vehicle.arc_length(self.road, time_s) for vehicle in self.vehicles])
        heading, _ = self.road.heading(s)
        left = np.column_stack([-np.sin(heading), np.cos(heading)])
        offsets = np.array([vehicle.lane_offset_m for vehicle in self.vehicles])
        oncoming = np.array([vehicle.speed_mps < 0 for vehicle in self.vehicles])
        yaw = heading + np.where(oncoming, np.pi, 0.0)
        cos, sin = np.cos(yaw), np.sin(yaw)
        poses = np.zeros((len(s), 4, 4))
        poses[:, 0, 0], poses[:, 0, 1], poses[:, 1, 0], poses[:, 1, 1] = cos, -sin, sin, cos
        poses[:, 2, 2] = poses[:, 3, 3] = 1.0
        poses[:, :2, 3] = self.road.road(s) + offsets[:, None] * left
        return poses

    def planes_at(self, time_s: float) -> list[Plane]:
        poses = self.poses_at(time_s)
        return [
            plane.moved(pose)
            for vehicle, pose in zip(self.vehicles, poses, strict=True)
            for plane in vehicle.planes
        ]


def _box(rng: np.random.Generator, px_per_m: float) -> tuple[Plane, ...]:
    """A car (or one time in five a truck) centred on the origin, length along x."""
    if rng.random() < 0.2:
        size = (rng.uniform(8.0, 12.0), rng.uniform(2.4, 2.5), rng.uniform(3.0, 3.6))
    else:
        size = (rng.uniform(3.8, 4.8), rng.uniform(1.7, 1.9), rng.uniform(1.4, 1.7))
    planes: list[Plane] = []
    add_upright_box(planes, np.zeros(2), 0.0, size, px_per_m, rng)
    return tuple(planes)


def build_traffic(
    road: DrivingTrajectory, per_100m: float, rng: np.random.Generator, px_per_m: float
) -> Traffic:
    """A lead vehicle and ``per_100m`` vehicles per 100 m of road, half of them oncoming,
    spread along the drive; textures at ``px_per_m`` (as the parked cars'). ``per_100m`` is
    checked by ``SynthOptions.validate``."""
    length = road.path_length()
    gap = rng.uniform(*LEAD_GAP_M)
    vehicles = [Vehicle(VehicleKind.LEAD, _box(rng, px_per_m), 0.0, gap, road.mean_speed)]
    for _ in range(round(per_100m * length / 100.0)):
        start = rng.uniform(-20.0, length + 60.0)
        if rng.random() < 0.5:
            speed, kind, offset = -rng.uniform(*ONCOMING_SPEED_MPS), VehicleKind.ONCOMING, 1.0
        else:
            speed, kind, offset = rng.uniform(*SAME_WAY_SPEED_MPS), VehicleKind.SAME_WAY, -1.0
        vehicles.append(Vehicle(kind, _box(rng, px_per_m), offset * LANE_OFFSET_M, start, speed))
    return Traffic(road, tuple(vehicles))
