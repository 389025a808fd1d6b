"""Stereo matching along rectified rows and triangulation with a per-point depth uncertainty.

After rectification a 3D point lies on the same image row in both cameras, at a positive
disparity d = x_left - x_right, and its depth is Z = f b / d. Matching therefore only compares
descriptors of right keypoints inside a narrow row band and the allowed disparity range, which
keeps the comparisons few and the false matches rare. Keypoints sit on the pixel grid (coarser
on higher pyramid levels), so the disparity is refined by a zero-mean SAD patch search along the
row with an equiangular fit through the best three costs (like ORB-SLAM's stereo matching, which
fits a parabola), or by Lucas-Kanade. A disparity noise of sigma_d pixels gives
sigma_Z = Z^2 sigma_d / (f b).

The full 3x3 covariance of a point (:func:`point_covariances`) propagates pixel noise
(sigma_u, sigma_v) and disparity noise sigma_d through the triangulation Jacobian. Lateral
uncertainty grows like Z sigma_u / f, depth uncertainty like Z^2 sigma_d / (f b): for a 11 cm
baseline at a few metres the point is tens of times less certain along its viewing ray than
across it, which a single scalar sigma per point cannot express.
"""

from __future__ import annotations

from dataclasses import dataclass, fields, replace

import cv2
import numpy as np

from estimator.config import FrontendConfig
from estimator.formats.calibration import Rectification
from estimator.frontend.features import (
    Features,
    MatchSet,
    descriptor_distances,
    match_candidates,
)
from estimator.frontend.match_kernels import as_words, band_matches, zero_mean_sad

__all__ = [
    "StereoMatcher",
    "StereoPoints",
    "point_covariances",
    "row_band_pairs",
    "shift_disparities",
    "triangulate",
    "triangulation_jacobian",
]

# Disparity refinement searches this many pixels either side of the descriptor match.
_REFINE_RADIUS = 1


@dataclass(frozen=True)
class StereoPoints:
    """Triangulated stereo matches of one frame, in the rectified left camera frame."""

    pixels: np.ndarray  # (N, 2) rectified left pixel (u, v) behind each point
    disparity: np.ndarray  # (N,) pixels
    points: np.ndarray  # (N, 3) metres, rectified left camera
    depth_sigma: np.ndarray  # (N,) metres
    descriptors: np.ndarray  # (N, D) left descriptors
    binary: bool
    # (N,) right keypoint's row minus the left's (pixels; None: not matched by rows), which a
    # late right shutter moves with the image's vertical motion (shutter_offset.py)
    row_offset: np.ndarray | None = None
    # The rig's constant disparity offset already taken out of ``disparity`` (pixels; the
    # matched disparity is ``disparity + disparity_offset_px``; disparity_offset.py)
    disparity_offset_px: float = 0.0

    def __len__(self) -> int:
        return len(self.points)

    def select(self, keep: np.ndarray) -> StereoPoints:
        """The points where ``keep`` (every per-point array of this class or a subclass)."""
        count = len(self)
        chosen = {
            item.name: value[keep]
            for item in fields(self)
            if isinstance(value := getattr(self, item.name), np.ndarray) and len(value) == count
        }
        return replace(self, **chosen)

    @staticmethod
    def empty(binary: bool = True) -> StereoPoints:
        width, dtype = (32, np.uint8) if binary else (128, np.float32)
        return StereoPoints(
            np.zeros((0, 2)), np.zeros(0), np.zeros((0, 3)), np.zeros(0),
            np.zeros((0, width), dtype), binary,
        )  # fmt: skip


def row_band_pairs(
    left: np.ndarray,
    right: np.ndarray,
    row_tolerance: float,
    disparity_range: tuple[float, float],
) -> tuple[np.ndarray, np.ndarray]:
    """All (i, j) with |y_l - y_r| <= tol and min <= x_l - x_r <= max, without an N x M table.

    Right points are sorted by row once; each left point's band is a contiguous slice found by
    binary search, and the slices are expanded into index pairs with one ``np.repeat``.
    """
    if len(left) == 0 or len(right) == 0:
        empty = np.zeros(0, dtype=np.intp)
        return empty, empty
    order = np.argsort(right[:, 1], kind="stable")
    rows = right[order, 1]
    low = np.searchsorted(rows, left[:, 1] - row_tolerance, side="left")
    high = np.searchsorted(rows, left[:, 1] + row_tolerance, side="right")
    counts = high - low
    ia = np.repeat(np.arange(len(left)), counts)
    offsets = np.arange(counts.sum()) - np.repeat(np.cumsum(counts) - counts, counts)
    ib = order[np.repeat(low, counts) + offsets]
    disparity = left[ia, 0] - right[ib, 0]
    inside = (disparity >= disparity_range[0]) & (disparity <= disparity_range[1])
    return ia[inside], ib[inside]


def _binary_band_matches(
    left: Features,
    right: Features,
    row_tolerance: float,
    disparity_range: tuple[float, float],
    ratio: float,
    max_distance: float,
) -> MatchSet:
    """:func:`row_band_pairs` + Hamming distances + mutual ratio test in one compiled pass."""
    if len(left) == 0 or len(right) == 0:
        empty = np.zeros(0, dtype=np.intp)
        return MatchSet(empty, empty, np.zeros(0))
    order = np.argsort(right.points[:, 1], kind="stable")
    rows = right.points[order, 1]
    low = np.searchsorted(rows, left.points[:, 1] - row_tolerance, side="left")
    high = np.searchsorted(rows, left.points[:, 1] + row_tolerance, side="right")
    a, b, distance = band_matches(
        np.ascontiguousarray(left.points[:, 0]), np.ascontiguousarray(right.points[:, 0]),
        as_words(left.descriptors), as_words(right.descriptors), order, low, high,
        (float(disparity_range[0]), float(disparity_range[1])), float(ratio), float(max_distance),
    )  # fmt: skip
    return MatchSet(a, b, distance)


def shift_disparities(
    points: StereoPoints,
    shift: np.ndarray | float,
    rectification: Rectification,
    floor_px: float | None = None,
) -> StereoPoints:
    """``points`` with ``shift`` (pixels, per point or one for all) added to each disparity and
    re-triangulated (their depth sigmas scaled with the depth); a disparity that would not stay
    positive drops its point, or with ``floor_px`` becomes that."""
    disparity = points.disparity + shift
    if floor_px is not None:
        disparity = np.maximum(disparity, floor_px)
    keep = disparity > 0
    kept = points if keep.all() else points.select(keep)
    disparity = disparity[keep]
    moved = triangulate(kept.pixels, disparity, rectification)
    depth_ratio = moved[:, 2] / kept.points[:, 2]
    return replace(
        kept, disparity=disparity, points=moved, depth_sigma=kept.depth_sigma * depth_ratio**2
    )


def triangulate(
    pixels: np.ndarray, disparity: np.ndarray, rectification: Rectification
) -> np.ndarray:
    """Rectified-left-camera points from pixels and disparities (Z = f b / d)."""
    f, b = rectification.fx, rectification.baseline
    depth = f * b / disparity
    x = (pixels[:, 0] - rectification.cx) * depth / f
    y = (pixels[:, 1] - rectification.cy) * depth / f
    return np.column_stack([x, y, depth])


def triangulation_jacobian(
    pixels: np.ndarray, disparity: np.ndarray, rectification: Rectification
) -> np.ndarray:
    """d(X, Y, Z) / d(u, v, d) of :func:`triangulate`, (N, 3, 3).

    X = (u - cx) b / d, Y = (v - cy) b / d, Z = f b / d: u and v move the point across the
    ray (b / d = Z / f per pixel), d moves it along the ray (-point / d per pixel).
    """
    b = rectification.baseline
    disparity = np.asarray(disparity, dtype=float)
    across = b / disparity
    points = triangulate(np.asarray(pixels, dtype=float), disparity, rectification)
    jacobian = np.zeros((len(disparity), 3, 3))
    jacobian[:, 0, 0] = across
    jacobian[:, 1, 1] = across
    jacobian[:, :, 2] = -points / disparity[:, None]
    return jacobian


def point_covariances(
    points: np.ndarray,
    rectification: Rectification,
    sigma_u: float,
    sigma_v: float,
    sigma_d: float,
    disparity_gain: float = 0.0,
    typical_disparity: float = 0.0,
) -> np.ndarray:
    """(N, 3, 3) covariances of triangulated points from pixel and disparity noise (pixels).

    J diag(sigma_u^2, sigma_v^2, sigma_d'^2) J^T with J of :func:`triangulation_jacobian`,
    written out: (Z / f)^2 diag(sigma_u^2, sigma_v^2, 0) across the ray plus
    (sigma_d' / d)^2 p p^T along it, where sigma_d' = sigma_d (1 + g d) / (1 + g d_typical)
    with g = ``disparity_gain`` (``sigma_d`` holds at ``typical_disparity``): a near point's two
    views differ more, so its disparity is less certain. It needs only the
    points (d = f b / Z), so points re-triangulated after a sub-pixel refinement need no
    extra bookkeeping.
    """
    points = np.asarray(points, dtype=float)
    f, b = rectification.fx, rectification.baseline
    depth = points[:, 2]
    sigma_d = sigma_d / (1.0 + disparity_gain * typical_disparity)
    along = (sigma_d * (depth + disparity_gain * (f * b)) / (f * b)) ** 2
    covariance = points[:, :, None] * (points[:, None, :] * along[:, None, None])
    across = (depth / f) ** 2
    covariance[:, 0, 0] += across * sigma_u**2
    covariance[:, 1, 1] += across * sigma_v**2
    return covariance


class StereoMatcher:
    """Match left to right keypoints of a rectified pair and triangulate them."""

    def __init__(self, config: FrontendConfig, rectification: Rectification) -> None:
        if config.min_disparity_px >= config.max_disparity_px:
            raise ValueError(
                f"min_disparity_px ({config.min_disparity_px}) must be below "
                f"max_disparity_px ({config.max_disparity_px})"
            )
        if config.min_depth_m >= config.max_depth_m:
            raise ValueError(
                f"min_depth_m ({config.min_depth_m}) must be below max_depth_m "
                f"({config.max_depth_m})"
            )
        self.config = config
        self.rectification = rectification

    def match(
        self,
        left: Features,
        right: Features,
        left_image: np.ndarray,
        right_image: np.ndarray,
    ) -> StereoPoints:
        """Stereo points of one rectified frame (descriptors are the left keypoints')."""
        config = self.config
        max_distance = config.max_hamming if left.binary else config.max_sift_distance
        disparity_range = (config.min_disparity_px, config.max_disparity_px)
        if left.binary:
            matches = _binary_band_matches(
                left, right, config.stereo_row_tolerance_px, disparity_range,
                config.stereo_ratio, max_distance,
            )  # fmt: skip
        else:
            ia, ib = row_band_pairs(
                left.points, right.points, config.stereo_row_tolerance_px, disparity_range
            )
            distance = descriptor_distances(
                left.descriptors, right.descriptors, ia, ib, left.binary
            )
            matches = match_candidates(
                ia, ib, distance, ratio=config.stereo_ratio, max_distance=max_distance
            )
        pixels = left.points[matches.a]
        disparity = pixels[:, 0] - right.points[matches.b, 0]
        row_offset = right.points[matches.b, 1] - pixels[:, 1]
        keep = np.ones(len(matches), dtype=bool)
        if config.subpixel == "sad" and len(matches):
            pixels, disparity, keep = self._refine(
                pixels, right.points[matches.b, 0], left_image, right_image
            )
        elif config.subpixel == "lk" and len(matches):
            disparity, keep = self._refine_lk(
                pixels, right.points[matches.b], left_image, right_image
            )
        keep &= disparity >= config.min_disparity_px
        points = triangulate(pixels[keep], disparity[keep], self.rectification)
        f_b = self.rectification.fx * self.rectification.baseline
        depth_sigma = points[:, 2] ** 2 * config.disparity_sigma_px / f_b
        in_range = (points[:, 2] >= config.min_depth_m) & (points[:, 2] <= config.max_depth_m)
        return StereoPoints(
            pixels=pixels[keep][in_range],
            disparity=disparity[keep][in_range],
            points=points[in_range],
            depth_sigma=depth_sigma[in_range],
            descriptors=left.descriptors[matches.a[keep][in_range]],
            binary=left.binary,
            row_offset=row_offset[keep][in_range],
        )

    def _refine_lk(
        self,
        pixels: np.ndarray,
        right_pixels: np.ndarray,
        left_image: np.ndarray,
        right_image: np.ndarray,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Sub-pixel disparities by aligning each left patch in the right image (Lucas-Kanade).

        Started at the descriptor match; kept when it converges on the same row band and
        within 1.5 px of that match.
        """
        size = 2 * self.config.subpixel_window + 1
        start = np.column_stack([right_pixels[:, 0], pixels[:, 1]]).astype(np.float32)
        refined, status, _ = cv2.calcOpticalFlowPyrLK(
            left_image,
            right_image,
            pixels.astype(np.float32),
            start.copy(),
            winSize=(size, size),
            maxLevel=0,
            criteria=(cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 20, 0.01),
            flags=cv2.OPTFLOW_USE_INITIAL_FLOW,
        )
        shift = refined - start
        keep = (
            (status.ravel() == 1)
            & (np.abs(shift[:, 0]) < 1.5)
            & (
                np.abs(refined[:, 1] - pixels[:, 1])
                <= max(self.config.stereo_row_tolerance_px, 0.5)
            )
        )
        return pixels[:, 0] - refined[:, 0].astype(float), keep

    def _refine(
        self,
        pixels: np.ndarray,
        right_x: np.ndarray,
        left_image: np.ndarray,
        right_image: np.ndarray,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Sub-pixel disparities by zero-mean SAD along the row; drops matches with no minimum.

        The left patch is centred on the rounded left keypoint, which then becomes the point's
        pixel; the right patch slides +-1 px around the descriptor match.
        """
        w = self.config.subpixel_window
        radius = _REFINE_RADIUS
        height, width = left_image.shape
        u = np.rint(pixels[:, 0]).astype(np.intp)
        v = np.rint(pixels[:, 1]).astype(np.intp)
        ur = np.rint(right_x).astype(np.intp)
        margin = w + radius + 1
        inside = (
            (u >= w) & (u < width - w) & (v >= w) & (v < height - w)
            & (ur >= margin) & (ur < width - margin)
        )  # fmt: skip
        u_in, v_in, ur_in = u[inside], v[inside], ur[inside]
        shifts = np.arange(-radius - 1, radius + 2)  # one extra either side for the fit
        cost = zero_mean_sad(
            np.ascontiguousarray(left_image), np.ascontiguousarray(right_image),
            u_in, v_in, ur_in, w, shifts,
        )  # fmt: skip
        best = np.argmin(cost[:, 1:-1], axis=1) + 1  # the minimum must have two neighbours
        rows_index = np.arange(len(best))
        c_minus, c_zero, c_plus = (cost[rows_index, best + k] for k in (-1, 0, 1))
        # Equiangular (V-shaped) fit: SAD grows linearly away from the optimum, and a parabola
        # through a V pulls the estimate towards whole pixels (Shimizu & Okutomi 2005).
        rise = np.maximum(c_minus, c_plus) - c_zero
        valid = rise > 0
        delta = np.zeros(len(best))
        delta[valid] = 0.5 * (c_minus[valid] - c_plus[valid]) / rise[valid]
        valid &= np.abs(delta) <= 0.5
        refined_right = ur_in + shifts[best] + delta
        keep = np.zeros(len(pixels), dtype=bool)
        keep[np.flatnonzero(inside)[valid]] = True
        new_pixels = np.column_stack([u, v]).astype(float)
        disparity = np.zeros(len(pixels))
        disparity[inside] = u_in - refined_right
        return new_pixels, disparity, keep
