"""What the back end takes of one measurement's inliers to place them as stereo landmarks.

Plain arrays (no GTSAM), so the front end can build them without loading the back end.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["StereoCamera", "StereoObservations", "project_stereo", "stereo_pixels"]


@dataclass(frozen=True)
class StereoCamera:
    """The rectified rig: shared intrinsics (fx = fy), baseline, and where it sits on the left
    camera (``camera_from_rect``: the rectifying rotation, inverted, as a 4x4 pose)."""

    fx: float
    cx: float
    cy: float
    baseline: float
    camera_from_rect: np.ndarray


@dataclass(frozen=True)
class StereoObservations:
    """The inliers of one measurement as rectified stereo pixels (u_left, u_right, v) in the
    reference and the current frame, with the point indices that name them in each frame."""

    reference_ns: int
    reference_ids: np.ndarray  # (N,) point indices in the reference frame's stereo points
    current_ids: np.ndarray  # (N,) point indices in the current frame's stereo points
    reference_pixels: np.ndarray  # (N, 3)
    current_pixels: np.ndarray  # (N, 3)
    reference_points: np.ndarray  # (N, 3) rectified reference camera (initial landmarks)
    camera: StereoCamera
    sigmas_px: tuple[float, float, float]  # the session's noise of u, v and disparity
    # The noise grows with the flow between the two images: sigma x (1 + gain x flow) /
    # (1 + gain x typical_flow), the level being the one at the recent frames' typical flow.
    flow_gain: float = 0.0
    typical_flow_px: float = 0.0

    def __post_init__(self) -> None:
        count = len(self.reference_ids)
        shapes = {
            "current_ids": (self.current_ids.shape, (count,)),
            "reference_pixels": (self.reference_pixels.shape, (count, 3)),
            "current_pixels": (self.current_pixels.shape, (count, 3)),
            "reference_points": (self.reference_points.shape, (count, 3)),
        }
        for name, (shape, expected) in shapes.items():
            if shape != expected:
                raise ValueError(f"{name} has shape {shape}, expected {expected}")

    def __len__(self) -> int:
        return len(self.reference_ids)

    def flow_scale(self) -> np.ndarray:
        """(N,) factor of each pair's pixel noise for its flow between the two frames."""
        moved = np.hypot(*(self.current_pixels - self.reference_pixels)[:, [0, 2]].T)
        typical = 1.0 + self.flow_gain * self.typical_flow_px
        return (1.0 + self.flow_gain * moved) / typical


def project_stereo(points: np.ndarray, camera: StereoCamera) -> np.ndarray:
    """(u_left, u_right, v) of rectified-camera points (N, 3): the inverse of triangulation."""
    depth = points[:, 2]
    u = camera.fx * points[:, 0] / depth + camera.cx
    v = camera.fx * points[:, 1] / depth + camera.cy
    return np.column_stack([u, u - camera.fx * camera.baseline / depth, v])


def stereo_pixels(pixels: np.ndarray, disparity: np.ndarray) -> np.ndarray:
    """(u_left, u_right, v) from left pixels (u, v) and disparities (u_right = u_left - d)."""
    return np.column_stack([pixels[:, 0], pixels[:, 0] - disparity, pixels[:, 1]])
