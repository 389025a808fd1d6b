"""The ideal stereo camera of the rendered sequences and how a view of the world is drawn.

Each plane is drawn with one ``cv2.warpPerspective`` of its texture over the image rectangle it
covers, and a per-pixel inverse-depth test (inverse depth of a plane is affine in the pixel
coordinates) resolves occlusion; rays that meet a plane behind the camera or nearer than the
near plane are rejected by the same test, which is the near-plane clipping. Motion blur
follows the mean image flow between two views.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass, field

import cv2
import numpy as np

from estimator.geometry import invert_pose, transform_points
from estimator.rendered.camera import CAMERA, SimCamera

MIP_LEVELS = 5


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

    def moved(self, pose: np.ndarray) -> Plane:
        """This plane carried by the rigid ``pose`` (4x4), sharing its texture and mipmaps: a
        moving object is re-posed every frame without rebuilding its pyramid."""
        moved = copy.copy(self)
        rotation = pose[:3, :3]
        moved.origin = rotation @ self.origin + pose[:3, 3]
        moved.u, moved.v = rotation @ self.u, rotation @ self.v
        moved.normal = rotation @ self.normal
        return moved

    @property
    def corners(self) -> np.ndarray:
        o, u, v = self.origin, self.u * self.width, self.v * self.height
        return np.stack([o, o + u, o + u + v, o + v])


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
    levels = _footprint_levels(plane, plane_inv, rx, ry, px_per_m, d_c, f)
    if levels is None:
        return np.zeros(plane_inv.shape, dtype=np.float32)
    coarse_level, lowest, highest = levels
    size = (len(rx), len(ry))
    if highest == lowest == 0:
        level = None
    else:
        # Clipped to the levels drawn, so the blend weights always sum to one.
        level = np.clip(
            cv2.resize(coarse_level.astype(np.float32), size, interpolation=cv2.INTER_LINEAR),
            lowest,
            highest,
        )
    indices = range(lowest, highest + 1)
    return _blend_levels(plane, homography, size, level, indices, plane_inv.shape)


def _footprint_levels(
    plane: Plane,
    plane_inv: np.ndarray,
    rx: np.ndarray,
    ry: np.ndarray,
    px_per_m: float,
    d_c: float,
    f: float,
) -> tuple[np.ndarray, int, int] | None:
    """Pyramid level of each pixel's footprint on a coarse grid, and the range of levels needed.

    Returns (level every 8th pixel, lowest, highest), or None when the plane lies wholly
    behind the camera. The footprint varies slowly across a plane, so evaluating it every 8th
    pixel and upsampling is enough.
    """
    step = 8
    coarse_x, coarse_y = rx[::step], ry[::step]
    coarse_inv = plane_inv[::step, ::step]
    ray_norm = np.sqrt(
        (coarse_y * coarse_y)[:, None] + (coarse_x * coarse_x)[None, :] + np.float32(f * f)
    ) / np.float32(f)
    ahead = coarse_inv > 0
    if not ahead.any():
        return None
    inv = np.maximum(coarse_inv, np.float32(1e-6))
    cos_incidence = np.clip(np.float32(abs(d_c)) * inv / ray_norm, 1e-3, 1.0)
    footprint = np.float32(px_per_m / f) / (inv * np.sqrt(cos_incidence))
    coarse_level = np.clip(np.log2(np.maximum(footprint, 1.0)), 0.0, len(plane.levels) - 1)
    lowest = int(np.floor(coarse_level[ahead].min()))
    highest = int(np.ceil(coarse_level[ahead].max()))
    return coarse_level, lowest, highest


def _blend_levels(
    plane: Plane,
    homography: np.ndarray,
    size: tuple[int, int],
    level: np.ndarray | None,
    indices: range,
    shape: tuple[int, ...],
) -> np.ndarray:
    """Warp each pyramid level in ``indices`` and blend them with tent weights around ``level``.

    ``level`` None means every pixel samples level 0, which then needs no weights at all
    (the common case for near surfaces, kept cheap).
    """
    result = np.zeros(shape, dtype=np.float32)
    weight = np.empty_like(result)
    for index in indices:
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


def blur_kernel(displacement: np.ndarray) -> np.ndarray | None:
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


def mean_flow(inv_depth: np.ndarray, T_C0_C1: np.ndarray, camera: SimCamera) -> np.ndarray:
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
