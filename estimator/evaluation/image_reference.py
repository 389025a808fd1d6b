"""A model-free rotation reference measured straight from the raw images.

When a camera barely moves (a robot standing still), its attitude change is visible in the
images as a near-uniform image shift, independent of stereo, triangulation or any estimator:
corners of the first image are tracked with pyramidal Lucas-Kanade (forward-backward checked),
undistorted to unit bearing vectors with the camera's own intrinsics, and the rotation that
best maps the bearings of frame i onto those of the first frame is the least-squares (Wahba)
fit on the bearings. Translation is ignored, so this holds only while translation is small
against scene depth (a 2 mm shift at 3 m tilts a bearing by 0.04 deg). It is the referee for
the standstill case, where a ground-truth attitude that comes from other sensors can disagree
with what the camera saw.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from estimator.formats.calibration import CameraModel
from estimator.geometry import wahba

__all__ = ["ImageRotation", "bearing_vectors", "image_rotations"]

_LK_WINDOW = (21, 21)
_LK_LEVELS = 3
_LK_CRITERIA = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 50, 1e-3)


@dataclass(frozen=True)
class ImageRotation:
    """Rotation of the camera at frame i relative to the first frame (R_0i), from its images."""

    rotation: np.ndarray  # (3, 3): bearing_0 ~ rotation @ bearing_i
    tracked: int  # corners that passed the forward-backward check
    residual_deg: float  # RMS angle between the rotated bearings after the fit


def bearing_vectors(pixels: np.ndarray, camera: CameraModel) -> np.ndarray:
    """Unit viewing rays (N, 3) of raw (distorted) pixel positions (N, 2)."""
    pixels = np.asarray(pixels, dtype=np.float64).reshape(-1, 1, 2)
    if camera.distortion_model == "equidistant":
        normalised = cv2.fisheye.undistortPoints(pixels, camera.K, camera.D)[:, 0]
    else:
        normalised = cv2.undistortPoints(pixels, camera.K, camera.D)[:, 0]
    rays = np.column_stack([normalised, np.ones(len(normalised))])
    return rays / np.linalg.norm(rays, axis=1, keepdims=True)


def image_rotations(
    first: np.ndarray,
    others: list[np.ndarray],
    camera: CameraModel,
    max_corners: int = 1000,
    max_round_trip_px: float = 0.1,
) -> list[ImageRotation]:
    """The attitude change of each image in ``others`` relative to ``first`` (8-bit grey)."""
    corners = cv2.goodFeaturesToTrack(first, max_corners, 0.01, 8)
    if corners is None or len(corners) < 3:
        raise ValueError("the first image has too few corners to measure a rotation")
    corners = corners.astype(np.float32)
    first_rays = bearing_vectors(corners, camera)
    results = []
    for image in others:
        tracked, status, _ = cv2.calcOpticalFlowPyrLK(
            first,
            image,
            corners,
            None,
            winSize=_LK_WINDOW,
            maxLevel=_LK_LEVELS,
            criteria=_LK_CRITERIA,
        )
        back, back_status, _ = cv2.calcOpticalFlowPyrLK(
            image,
            first,
            tracked,
            None,
            winSize=_LK_WINDOW,
            maxLevel=_LK_LEVELS,
            criteria=_LK_CRITERIA,
        )
        round_trip = np.linalg.norm((back - corners)[:, 0], axis=1)
        good = (status[:, 0] == 1) & (back_status[:, 0] == 1) & (round_trip < max_round_trip_px)
        if good.sum() < 3:
            raise ValueError("fewer than 3 corners tracked: the views do not overlap")
        rays = bearing_vectors(tracked[good], camera)
        rotation = wahba(rays, first_rays[good])
        angles = np.arccos(np.clip(np.sum((rays @ rotation.T) * first_rays[good], axis=1), -1, 1))
        results.append(
            ImageRotation(
                rotation=rotation,
                tracked=int(good.sum()),
                residual_deg=float(np.degrees(np.sqrt(np.mean(angles**2)))),
            )
        )
    return results
