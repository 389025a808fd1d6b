"""The rendered hall: textured planes (floor, ceiling, walls, pillars) around the flight loop.

Every plane carries its own procedural high-contrast texture (multi-scale noise blobs, flat
patches and small checkers, so ORB finds many distinct corners).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import cv2
import numpy as np

from estimator.rendered.camera import CAMERA, SimCamera
from estimator.rendered.render import Plane, render_view
from estimator.rendered.trajectory import LoopTrajectory

__all__ = ["World", "add_plane", "build_world", "make_texture"]


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
    # The planes of moving objects at a time (s), in the world frame (traffic.py); None: static.
    movers: Callable[[float], list[Plane]] | None = None

    def render(
        self, T_WC: np.ndarray, z_near: float = 0.05, time_s: float = 0.0
    ) -> tuple[np.ndarray, np.ndarray]:
        """Grey image (uint8) and inverse depth (float32, 0 = nothing) seen by a camera at
        ``time_s`` (where the moving objects are then)."""
        planes = self.planes if self.movers is None else self.planes + self.movers(time_s)
        return render_view(planes, T_WC, z_near, self.camera)


def add_plane(
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
    add_plane(planes, (x1, y0, z1), -ex, -ez, x1 - x0, h, px_per_m, rng)  # normal -y
    add_plane(planes, (x0, y1, z1), ex, -ez, x1 - x0, h, px_per_m, rng)  # normal +y
    add_plane(planes, (x1, y1, z1), -ey, -ez, y1 - y0, h, px_per_m, rng)  # normal +x
    add_plane(planes, (x0, y0, z1), ey, -ez, y1 - y0, h, px_per_m, rng)  # normal -x


def build_world(
    trajectory: LoopTrajectory,
    rng: np.random.Generator,
    px_per_m: float,
    camera: SimCamera = CAMERA,
) -> World:
    """Hall around the loop plus pillars kept at least 1 m clear of the flown path, seen by
    ``camera``."""
    margin = 2.5
    half_x, half_y = trajectory.a + margin, trajectory.b + margin
    height = 3.5
    ex, ey, ez = np.eye(3)
    planes: list[Plane] = []
    # Floor (normal +z) and ceiling (normal -z).
    add_plane(planes, (-half_x, -half_y, 0.0), ex, ey, 2 * half_x, 2 * half_y, px_per_m, rng)
    add_plane(planes, (-half_x, half_y, height), ex, -ey, 2 * half_x, 2 * half_y, px_per_m, rng)
    # Walls facing inwards (u x v = inward normal), texture rows running down.
    add_plane(planes, (half_x, half_y, height), -ex, -ez, 2 * half_x, height, px_per_m, rng)
    add_plane(planes, (-half_x, -half_y, height), ex, -ez, 2 * half_x, height, px_per_m, rng)
    add_plane(planes, (-half_x, half_y, height), -ey, -ez, 2 * half_y, height, px_per_m, rng)
    add_plane(planes, (half_x, -half_y, height), ey, -ez, 2 * half_y, height, px_per_m, rng)

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
    return World(planes, (half_x, half_y, height), camera)
