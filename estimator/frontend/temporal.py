"""Matching stereo points through time: the 3D-3D correspondences the registration solves.

The reference frame (the keyframe, or the previous frame) and the current frame each carry
triangulated points with left-image descriptors. A reference point may only pair with current
points near where it is expected to appear: its own pixel, or, better, its projection under a
predicted motion. Among those candidates the ratio and mutual checks pick at most one partner.

How near is "near" depends on the point (with ``frontend.min_search_radius_px`` set): an error
of the predicted rotation moves every pixel alike (f radians, more towards the image edges),
an error of the predicted translation moves a point by f t / Z. On a drive a point 3 m away
may be 40 px from its prediction while one at 80 m is within 2 px; one wide window for all
gives the far points dozens of wrong candidates and the matcher the work of comparing them.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from estimator.config import FrontendConfig
from estimator.formats.calibration import Rectification
from estimator.frontend.features import MatchSet, descriptor_distances, match_candidates
from estimator.frontend.match_kernels import as_words, window_matches
from estimator.frontend.patch_warp import local_affine, warped_templates
from estimator.frontend.stereo import StereoPoints, triangulate
from estimator.geometry import transform_points
from estimator.order_statistics import median

__all__ = [
    "Correspondences",
    "PredictionUncertainty",
    "match_temporal",
    "project",
    "refine_pixels",
    "search_radii",
]

# A refined position further than this from the descriptor match is a different corner.
_MAX_REFINE_SHIFT_PX = 1.5
# A KLT track must come back to where it started within this (forward-backward check).
_KLT_ROUND_TRIP_PX = 0.5
# A per-point window spans this many standard deviations of its predicted pixel.
WINDOW_SIGMAS = 3.0
# Matches this far out in their windows (median) show a prediction error beyond the windows.
WINDOW_MISS_FRACTION = 0.5


@dataclass(frozen=True)
class PredictionUncertainty:
    """One standard deviation of a predicted relative pose's error: rotation angle (rad) and
    translation (m); the search windows follow from it."""

    rotation_rad: float
    translation_m: float


@dataclass(frozen=True)
class Correspondences:
    """Paired points: reference_points[i] (previous P) <-> current_points[i] (current Q)."""

    reference_index: np.ndarray  # (M,) into the reference StereoPoints
    current_index: np.ndarray  # (M,) into the current StereoPoints
    reference_points: np.ndarray  # (M, 3)
    current_points: np.ndarray  # (M, 3)

    def __len__(self) -> int:
        return len(self.reference_index)


def project(points: np.ndarray, fx: float, cx: float, cy: float) -> np.ndarray:
    """Rectified pixels of camera-frame points (NaN behind the camera)."""
    depth = np.where(points[:, 2] > 1e-6, points[:, 2], np.nan)
    return np.column_stack([fx * points[:, 0] / depth + cx, fx * points[:, 1] / depth + cy])


def search_radii(
    moved: np.ndarray,
    expected: np.ndarray,
    uncertainty: PredictionUncertainty | None,
    config: FrontendConfig,
    rectification: Rectification,
) -> np.ndarray:
    """Search radius (px) of each reference point: ``WINDOW_SIGMAS`` times the spread of its
    predicted pixel ``expected`` (its point ``moved`` into the predicted current camera).

    A rotation error dtheta moves a pixel at distance r from the principal point by about
    f (1 + r^2 / f^2) dtheta; a translation error dt moves it by up to sqrt(f^2 + r^2) dt / Z.
    The radius is kept within [``min_search_radius_px``, ``search_radius_px``]; without an
    uncertainty (the prediction is poor) every point gets ``search_radius_px``.
    """
    wide, floor = float(config.search_radius_px), config.min_search_radius_px
    if uncertainty is None or floor is None or wide <= 0:
        return np.full(len(expected), wide)
    rect = rectification
    focal = float(rect.fx)
    offset = np.hypot(expected[:, 0] - rect.cx, expected[:, 1] - rect.cy) / focal
    depth = np.maximum(moved[:, 2], 1e-6)
    rotation_px = focal * (1.0 + offset**2) * uncertainty.rotation_rad
    translation_px = focal * np.sqrt(1.0 + offset**2) * uncertainty.translation_m / depth
    radii = WINDOW_SIGMAS * np.hypot(rotation_px, translation_px)
    return np.clip(np.nan_to_num(radii, nan=wide), min(float(floor), wide), wide)


def _candidate_pairs(
    expected: np.ndarray, observed: np.ndarray, radii: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """(i, j) with observed[j] within ``radii[i]`` pixels of expected[i] (all pairs if 0)."""
    radius = float(radii.max()) if len(radii) else 0.0
    if radius <= 0:
        ia, ib = np.meshgrid(np.arange(len(expected)), np.arange(len(observed)), indexing="ij")
        return ia.ravel(), ib.ravel()
    finite = np.flatnonzero(np.isfinite(expected).all(axis=1))
    if len(finite) == 0 or len(observed) == 0:
        empty = np.zeros(0, dtype=np.intp)
        return empty, empty
    # Imported here: SciPy (about 50 MB per process) serves only the SIFT and KLT paths.
    from scipy.spatial import cKDTree

    pairs = cKDTree(expected[finite]).sparse_distance_matrix(
        cKDTree(observed), radius, output_type="ndarray"
    )
    ia = finite[pairs["i"]]
    inside = pairs["v"] <= radii[ia]
    return ia[inside], pairs["j"][inside].astype(np.intp)


def _window_matches(
    expected: np.ndarray,
    reference: StereoPoints,
    current: StereoPoints,
    radii: np.ndarray,
    ratio: float,
    max_distance: float,
) -> MatchSet:
    """:func:`_candidate_pairs` + Hamming distances + mutual ratio test in one compiled pass.

    Candidates of reference point i are the current points within ``radii[i]`` of its expected
    pixel; where two reference points are equally near one current point, the one with the
    smaller index keeps it.
    """
    finite = np.flatnonzero(np.isfinite(expected).all(axis=1))
    if len(finite) == 0 or len(current) == 0:
        empty = np.zeros(0, dtype=np.intp)
        return MatchSet(empty, empty, np.zeros(0))
    order = np.argsort(current.pixels[:, 1], kind="stable")
    rows = current.pixels[order, 1]
    centres = np.ascontiguousarray(expected[finite])
    windows = np.ascontiguousarray(radii[finite], dtype=float)
    low = np.searchsorted(rows, centres[:, 1] - windows, side="left")
    high = np.searchsorted(rows, centres[:, 1] + windows, side="right")
    a, b, distance = window_matches(
        centres, np.ascontiguousarray(current.pixels), as_words(reference.descriptors[finite]),
        as_words(current.descriptors), order, low, high, windows, float(ratio),
        float(max_distance),
    )  # fmt: skip
    return MatchSet(finite[a], b, distance)


def _windows_missed(
    expected: np.ndarray,
    current: StereoPoints,
    matches: MatchSet,
    radii: np.ndarray,
    config: FrontendConfig,
) -> bool:
    """Narrow windows that did not hold the motion: too few matches, or matches that lie, at
    the median, further from their predicted pixels than ``WINDOW_MISS_FRACTION`` of their
    windows (3-sigma windows of a right prediction hold them near the centre; the points
    whose motion went beyond their windows are then missing)."""
    if len(matches) < config.keyframe_min_inliers:
        return True
    offsets = np.linalg.norm(current.pixels[matches.b] - expected[matches.a], axis=1)
    return median(offsets / radii[matches.a]) > WINDOW_MISS_FRACTION


def _descriptor_matches(
    expected: np.ndarray,
    reference: StereoPoints,
    current: StereoPoints,
    radii: np.ndarray,
    config: FrontendConfig,
) -> MatchSet:
    """Ratio-tested mutual descriptor matches within each reference point's window."""
    max_distance = config.max_hamming if reference.binary else config.max_sift_distance
    if reference.binary and config.search_radius_px > 0:
        return _window_matches(
            expected, reference, current, radii, config.temporal_ratio, max_distance
        )
    ia, ib = _candidate_pairs(expected, current.pixels, radii)
    distance = descriptor_distances(
        reference.descriptors, current.descriptors, ia, ib, reference.binary
    )
    return match_candidates(
        ia, ib, distance, ratio=config.temporal_ratio, max_distance=max_distance
    )


def match_temporal(
    reference: StereoPoints,
    current: StereoPoints,
    config: FrontendConfig,
    rectification: Rectification,
    predicted_current_from_reference: np.ndarray | None = None,
    images: tuple[np.ndarray, np.ndarray] | None = None,
    uncertainty: PredictionUncertainty | None = None,
) -> Correspondences:
    """3D-3D correspondences between a reference frame's and the current frame's points.

    ``predicted_current_from_reference`` (4x4, rectified frames) moves reference points into
    the predicted current camera; their projections centre the search windows. Without it the
    window is centred on the reference pixel (small-motion assumption). ``uncertainty`` (of the
    prediction; None when it is poor) sizes each point's window (see :func:`search_radii`).
    With ``images``
    (reference, current rectified left images) and ``config.temporal_refine`` the current
    pixels are refined to sub-pixel precision (see :func:`refine_pixels`).
    ``config.temporal_matcher = "klt"`` tracks the reference pixels instead of comparing
    descriptors (see :func:`track_klt`; needs ``images``).
    """
    rect = rectification
    if predicted_current_from_reference is None:
        expected, moved = reference.pixels, reference.points
    else:
        moved = transform_points(predicted_current_from_reference, reference.points)
        expected = project(moved, rect.fx, rect.cx, rect.cy)
    if config.temporal_matcher == "klt":
        if images is None:
            raise ValueError("the KLT temporal matcher needs the reference and current images")
        return track_klt(reference, current, expected, images, config, rect)
    radii = search_radii(moved, expected, uncertainty, config, rect)
    matches = _descriptor_matches(expected, reference, current, radii, config)
    wide = np.full(len(expected), float(config.search_radius_px))
    narrowed = not np.array_equal(radii, wide)
    if narrowed and _windows_missed(expected, current, matches, radii, config):
        # The prediction is off by more than its windows allow (a motion it did not
        # foresee, e.g. the start of a turn): search wide.
        matches = _descriptor_matches(expected, reference, current, wide, config)
    reference_index, current_index = matches.a, matches.b
    current_points = current.points[current_index]
    if images is not None and config.temporal_refine and len(matches):
        affine = None
        if config.temporal_refine_warp and predicted_current_from_reference is not None:
            affine = local_affine(
                reference.pixels[reference_index], reference.points[reference_index],
                predicted_current_from_reference, rect,
            )  # fmt: skip
        pixels, found = refine_pixels(
            images[0],
            images[1],
            reference.pixels[reference_index],
            current.pixels[current_index],
            config.temporal_refine_window,
            affine,
        )
        reference_index, current_index = reference_index[found], current_index[found]
        current_points = triangulate(pixels[found], current.disparity[current_index], rect)
    return Correspondences(
        reference_index=reference_index,
        current_index=current_index,
        reference_points=reference.points[reference_index],
        current_points=current_points,
    )


def track_klt(
    reference: StereoPoints,
    current: StereoPoints,
    expected: np.ndarray,
    images: tuple[np.ndarray, np.ndarray],
    config: FrontendConfig,
    rectification: Rectification,
) -> Correspondences:
    """Correspondences by pyramidal Lucas-Kanade tracking instead of descriptors.

    Reference pixels are tracked into the current image (started at their predicted positions)
    and back again; a track is kept when it returns within 0.5 px. A tracked pixel takes the
    disparity of the nearest current stereo point within ``klt_association_px`` (each current
    point serves one track, the closest), and is triangulated at its tracked position.
    """
    size = 2 * config.klt_window + 1
    lk = {
        "winSize": (size, size),
        "maxLevel": config.klt_levels,
        "criteria": (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 30, 0.01),
    }
    usable = np.flatnonzero(np.isfinite(expected).all(axis=1))
    empty = np.zeros(0, dtype=np.intp)
    if len(usable) == 0 or len(current) == 0:
        return Correspondences(empty, empty, np.zeros((0, 3)), np.zeros((0, 3)))
    start = reference.pixels[usable].astype(np.float32)
    guess = expected[usable].astype(np.float32)
    tracked, forward, _ = cv2.calcOpticalFlowPyrLK(
        images[0], images[1], start, guess.copy(), flags=cv2.OPTFLOW_USE_INITIAL_FLOW, **lk
    )
    back, backward, _ = cv2.calcOpticalFlowPyrLK(
        images[1], images[0], tracked, start.copy(), flags=cv2.OPTFLOW_USE_INITIAL_FLOW, **lk
    )
    good = (
        (forward.ravel() == 1)
        & (backward.ravel() == 1)
        & (np.linalg.norm(back - start, axis=1) < _KLT_ROUND_TRIP_PX)
    )
    from scipy.spatial import cKDTree  # only this path needs SciPy (see _candidate_pairs)

    distance, nearest = cKDTree(current.pixels).query(
        tracked.astype(float), distance_upper_bound=config.klt_association_px
    )
    good &= np.isfinite(distance)
    # One track per current point: the closest one wins.
    order = np.flatnonzero(good)[np.argsort(distance[good], kind="stable")]
    _, first = np.unique(nearest[order], return_index=True)
    keep = np.sort(order[first])
    reference_index = usable[keep]
    current_index = nearest[keep].astype(np.intp)
    pixels = tracked[keep].astype(float)
    return Correspondences(
        reference_index=reference_index,
        current_index=current_index,
        reference_points=reference.points[reference_index],
        current_points=triangulate(pixels, current.disparity[current_index], rectification),
    )


def refine_pixels(
    reference_image: np.ndarray,
    current_image: np.ndarray,
    reference_pixels: np.ndarray,
    current_pixels: np.ndarray,
    half_window: int,
    affine: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Sub-pixel positions in the current image of the reference pixels (Lucas-Kanade).

    Keypoints sit on the integer grid (or coarser on higher pyramid levels), so a scene that
    moves by a fraction of a pixel shows up as 0 or 1 pixel jumps: metres of noise at the
    scale of a standstill. LK, started at the descriptor match, aligns the reference patch in
    the current image continuously. Returns the refined pixels and a mask of those that
    converged within 1.5 px of the match; the disparity measured at the match is reused (it
    varies smoothly over such a shift). With ``affine`` ((N, 2, 2), see
    :func:`~estimator.frontend.patch_warp.local_affine`) each reference patch is first warped
    into the current view.
    """
    size = 2 * half_window + 1
    start = current_pixels.astype(np.float32)
    source_image, source_pixels = reference_image, reference_pixels.astype(np.float32)
    if affine is not None:
        warped = warped_templates(
            reference_image, reference_pixels, affine, half_window, current_image.shape[:2]
        )
        if warped is not None:
            source_image, source_pixels = warped
    refined, status, _ = cv2.calcOpticalFlowPyrLK(
        source_image,
        current_image,
        source_pixels,
        start.copy(),
        winSize=(size, size),
        maxLevel=0,
        criteria=(cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 20, 0.01),
        flags=cv2.OPTFLOW_USE_INITIAL_FLOW,
    )
    found = (status.ravel() == 1) & (np.linalg.norm(refined - start, axis=1) < _MAX_REFINE_SHIFT_PX)
    return refined.astype(float), found
