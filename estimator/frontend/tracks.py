"""A track-based front end: corners are followed by Lucas-Kanade instead of re-detected.

Detecting and describing both images every frame is the front end's largest cost. Here the
left image keeps persistent tracks with ids: each frame they are followed by pyramidal LK from
the previous frame (started at their positions predicted by the constant-velocity motion and
their depth) and tracked back (forward-backward check). New corners (FAST, kept one per cell of
``track_min_distance_px`` and spread over the ``grid_rows`` x ``grid_cols`` grid) are added
only where the tracks have thinned out, away from the live ones.

Stereo for every track is LK from the left to the right rectified image along the row, started
at the track's previous disparity (a new track's first disparity comes from a zero-mean SAD
search over the disparity range), tracked back to the left image, and kept on the same row and
within the disparity and depth limits. The output is the detecting front end's: triangulated
:class:`StereoPoints` (with the track ids), so registration, refinement and the back end stay
as they are; the pairs against any reference frame (keyframe or not) are the tracks both
frames share (:func:`match_tracks`).
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field

import cv2
import numpy as np

from estimator.config import FrontendConfig
from estimator.formats.calibration import Rectification
from estimator.frontend.features import grid_select
from estimator.frontend.match_kernels import zero_mean_sad
from estimator.frontend.stereo import StereoPoints, triangulate
from estimator.frontend.temporal import Correspondences, project, refine_pixels
from estimator.geometry import transform_points

__all__ = ["KeyframeView", "TrackedPoints", "Tracker", "match_tracks"]

# A track must come back within this of where it started (forward-backward check), pixels.
_ROUND_TRIP_PX = 0.5
# Tracks closer than this to the image border are dropped (LK's window leaves the image).
_BORDER_PX = 8
# A new track's SAD disparity must beat every other disparity (beyond +-2 px) by this factor.
_UNIQUENESS = 0.9
# At most this many frames in a row are left out for their LK residual; then the residual
# level is taken as the scene's new normal (a light switched on, a textured wall).
_MAX_UNLIKE_FRAMES = 2
_LK_CRITERIA = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 10, 0.03)


@dataclass(frozen=True)
class TrackedPoints(StereoPoints):
    """Stereo points of one frame with the id of the track behind each."""

    ids: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))  # (N,) unique


@dataclass(frozen=True)
class KeyframeView:
    """What the tracker needs of the keyframe to find its lost tracks again: its points
    (with their track ids), its rectified left image and the predicted motion from it to the
    current frame (4x4, rectified)."""

    points: StereoPoints
    image: np.ndarray
    current_from_keyframe: np.ndarray


class Tracker:
    """Persistent left-image tracks of one session and their stereo points, frame by frame.

    Call :meth:`follow` with the rectified left image (and the predicted motion), then
    :meth:`stereo` with the rectified right image; each frame's points are the tracks that
    have a stereo match.
    """

    def __init__(self, config: FrontendConfig, rectification: Rectification) -> None:
        self.config = config
        self.rectification = rectification
        self._fast = cv2.FastFeatureDetector_create(
            threshold=config.fast_threshold, nonmaxSuppression=True
        )
        self._image: np.ndarray | None = None  # previous rectified left image
        self._pixels = np.zeros((0, 2), np.float32)  # live tracks, left image
        self._ids = np.zeros(0, np.int64)
        self._disparity = np.zeros(0)  # NaN: no stereo match yet
        self._points = np.zeros((0, 3))  # NaN rows: no stereo match
        self._next_id = 0
        self._before: tuple | None = None  # the state before the last follow
        self._errors: deque[float] = deque(maxlen=10)  # recent frames' median LK residual
        self._unlike = 0  # frames in a row not followed for their residual
        size = 2 * config.track_window + 1
        self._lk = {"winSize": (size, size), "criteria": _LK_CRITERIA}

    def __len__(self) -> int:
        return len(self._ids)

    @property
    def live(self) -> tuple[np.ndarray, np.ndarray]:
        """Ids and left-image pixels of the live tracks (with or without a stereo match)."""
        return self._ids.copy(), self._pixels.astype(float)

    # ------------------------------------------------------------------ left image, in time

    def follow(
        self,
        image: np.ndarray,
        current_from_previous: np.ndarray | None = None,
        keyframe: KeyframeView | None = None,
    ) -> None:
        """Move the tracks into ``image`` (the next rectified left image), drop the lost ones,
        find the ``keyframe``'s lost tracks again when most are gone, and start new ones where
        they thinned out. ``current_from_previous`` (4x4, rectified) predicts where tracks with
        a depth appear."""
        self._before = (self._image, self._pixels.copy(), self._ids.copy(),
                        self._disparity.copy(), self._points.copy())  # fmt: skip
        followed = True
        if self._image is not None and len(self._ids):
            followed = self._track_into(image, current_from_previous)
        self._image = image
        if not followed:
            return
        if keyframe is not None and isinstance(keyframe.points, TrackedPoints):
            self._recover(image, keyframe)
        if len(self._ids) < self.config.track_refill_ratio * self.config.max_tracks:
            self._add_corners(image)

    def forget_frame(self) -> None:
        """The tracks as they were before the last :meth:`follow`: a frame that gave no
        vision estimate (black, blurred) is not one to follow them through."""
        if self._before is not None:
            self._image, self._pixels, self._ids, self._disparity, self._points = self._before
            self._before = None

    def _recover(self, image: np.ndarray, keyframe: KeyframeView) -> None:
        """The keyframe's tracks that are no longer live, tracked by LK straight from the
        keyframe's image (started where the predicted motion puts their points) when fewer
        than ``track_recover_ratio`` of them are live: after a black or blurred frame every
        track is lost, and new ones share nothing with the keyframe."""
        points = keyframe.points
        assert isinstance(points, TrackedPoints)
        lost = ~np.isin(points.ids, self._ids)
        if not lost.any() or (~lost).sum() >= self.config.track_recover_ratio * len(lost):
            return
        moved = transform_points(keyframe.current_from_keyframe, points.points[lost])
        rect = self.rectification
        guess = project(moved, rect.fx, rect.cx, rect.cy)
        usable = np.isfinite(guess).all(axis=1) & (moved[:, 2] > 0)
        if not usable.any():
            return
        start = points.pixels[lost][usable].astype(np.float32)
        tracked, found, _ = self._both_ways(keyframe.image, image, start, guess[usable])
        if not found.any():
            return
        moved = moved[usable][found]
        f_b = rect.fx * rect.baseline
        self._pixels = np.ascontiguousarray(np.vstack([self._pixels, tracked[found]]))
        self._ids = np.concatenate([self._ids, points.ids[lost][usable][found]])
        self._disparity = np.concatenate([self._disparity, f_b / moved[:, 2]])
        self._points = np.vstack([self._points, moved])

    def _track_into(self, image: np.ndarray, current_from_previous: np.ndarray | None) -> bool:
        """The live tracks followed into ``image``; False when the frame is unlike the recent
        ones (``_like_recent``) and every track was left out."""
        assert self._image is not None
        start = self._pixels
        guess = start.copy()
        if current_from_previous is not None:
            known = np.isfinite(self._points[:, 2])
            moved = transform_points(current_from_previous, self._points[known])
            rect = self.rectification
            predicted = project(moved, rect.fx, rect.cx, rect.cy)
            usable = np.isfinite(predicted).all(axis=1)
            rows = np.flatnonzero(known)[usable]
            guess[rows] = predicted[usable]
        tracked, keep, error = self._both_ways(self._image, image, start, guess)
        if not self._like_recent(error[keep]):
            keep[:] = False
        self._pixels = np.ascontiguousarray(tracked[keep])
        self._ids = self._ids[keep]
        self._disparity = self._disparity[keep]
        self._points = self._points[keep]
        return bool(keep.any())

    def _like_recent(self, error: np.ndarray) -> bool:
        """Whether the tracks' median LK residual in time is within ``track_blur_ratio`` of
        the recent frames' (then it joins them). A motion-blurred frame or a flash leaves
        residuals several times larger (MH_01: 1.4-6 grey levels, 15-28 with a 25 px streak),
        and its tracks would follow the streaks."""
        if not len(error):
            return True
        median = float(np.median(error))
        ratio = self.config.track_blur_ratio
        if ratio > 0 and len(self._errors) >= 3 and median > ratio * np.median(self._errors):
            self._unlike += 1
            if self._unlike <= _MAX_UNLIKE_FRAMES:
                return False
            self._errors.clear()  # the scene's level changed: this is the new normal
        self._unlike = 0
        self._errors.append(median)
        return True

    def _both_ways(
        self, source: np.ndarray, target: np.ndarray, start: np.ndarray, guess: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``start`` (pixels of ``source``) tracked into ``target`` from ``guess`` by pyramidal
        LK and back: the tracked pixels, which returned within ``_ROUND_TRIP_PX`` and stay
        inside the image, and LK's residual of each (mean absolute grey-level difference)."""
        levels = self.config.track_levels
        tracked, forward, error = cv2.calcOpticalFlowPyrLK(
            source, target, start, guess.astype(np.float32), maxLevel=levels,
            flags=cv2.OPTFLOW_USE_INITIAL_FLOW, **self._lk,
        )  # fmt: skip
        back, backward, _ = cv2.calcOpticalFlowPyrLK(
            target, source, tracked, start.copy(), maxLevel=levels,
            flags=cv2.OPTFLOW_USE_INITIAL_FLOW, **self._lk,
        )  # fmt: skip
        kept = (
            (forward.ravel() == 1)
            & (backward.ravel() == 1)
            & (np.linalg.norm(back - start, axis=1) < _ROUND_TRIP_PX)
            & self._inside(tracked, target.shape)
        )
        return tracked, kept, error.ravel()

    @staticmethod
    def _inside(pixels: np.ndarray, shape: tuple[int, ...]) -> np.ndarray:
        height, width = shape[:2]
        u, v = pixels[:, 0], pixels[:, 1]
        return (
            (u >= _BORDER_PX) & (u < width - _BORDER_PX)
            & (v >= _BORDER_PX) & (v < height - _BORDER_PX)
        )  # fmt: skip

    def _add_corners(self, image: np.ndarray) -> None:
        """FAST corners away from the live tracks, one per cell of the minimum distance,
        spread over the grid, up to ``max_tracks`` tracks in all."""
        config = self.config
        spacing = config.track_min_distance_px
        mask = np.zeros(image.shape, np.uint8)
        mask[_BORDER_PX:-_BORDER_PX, _BORDER_PX:-_BORDER_PX] = 255
        radius = max(round(spacing), 1)
        for u, v in np.rint(self._pixels).astype(int):
            cv2.circle(mask, (int(u), int(v)), radius, 0, -1)
        keypoints = self._fast.detect(image, mask)
        if not keypoints:
            return
        points = np.array([k.pt for k in keypoints], np.float32)
        response = np.array([k.response for k in keypoints])
        # One corner per spacing x spacing cell (the strongest): FAST corners clump.
        strongest = np.argsort(-response, kind="stable")
        cell_cols = int(image.shape[1] // spacing) + 1
        cells = (points[strongest, 1] // spacing).astype(np.int64) * cell_cols + (
            points[strongest, 0] // spacing
        ).astype(np.int64)
        _, first = np.unique(cells, return_index=True)
        chosen = strongest[np.sort(first)]
        budget = config.max_tracks - len(self._ids)
        if budget <= 0:
            return
        size = (image.shape[1], image.shape[0])
        chosen = chosen[
            grid_select(points[chosen], response[chosen], size, (config.grid_rows,
                        config.grid_cols), budget)
        ]  # fmt: skip
        count = len(chosen)
        self._pixels = np.ascontiguousarray(np.vstack([self._pixels, points[chosen]]))
        self._ids = np.concatenate([self._ids, self._next_id + np.arange(count)])
        self._next_id += count
        self._disparity = np.concatenate([self._disparity, np.full(count, np.nan)])
        self._points = np.vstack([self._points, np.full((count, 3), np.nan)])

    # ------------------------------------------------------------------ stereo

    def stereo(self, right: np.ndarray) -> TrackedPoints:
        """Stereo points of the tracks in the current frame (``right``: rectified right image
        of the frame :meth:`follow` last saw)."""
        left = self._image
        if left is None or not len(self._ids):
            return _empty()
        config = self.config
        disparity = self._disparity.copy()
        fresh = np.flatnonzero(~np.isfinite(disparity))
        if len(fresh):
            disparity[fresh] = self._search_disparity(left, right, self._pixels[fresh])
        has_guess = np.isfinite(disparity)
        rows = np.flatnonzero(has_guess)
        start = self._pixels[rows]
        guess = start.copy()
        guess[:, 0] -= disparity[rows].astype(np.float32)
        matched, forward, _ = cv2.calcOpticalFlowPyrLK(
            left, right, start, guess, maxLevel=0, flags=cv2.OPTFLOW_USE_INITIAL_FLOW,
            **self._lk,
        )  # fmt: skip
        back, backward, _ = cv2.calcOpticalFlowPyrLK(
            right, left, matched, start.copy(), maxLevel=0,
            flags=cv2.OPTFLOW_USE_INITIAL_FLOW, **self._lk,
        )  # fmt: skip
        measured = start[:, 0].astype(float) - matched[:, 0]
        good = (
            (forward.ravel() == 1)
            & (backward.ravel() == 1)
            & (np.linalg.norm(back - start, axis=1) < _ROUND_TRIP_PX)
            & (np.abs(matched[:, 1] - start[:, 1]) <= config.stereo_row_tolerance_px)
            & (measured >= config.min_disparity_px)
            & (measured <= config.max_disparity_px)
        )
        points = triangulate(start[good].astype(float), measured[good], self.rectification)
        in_range = (points[:, 2] >= config.min_depth_m) & (points[:, 2] <= config.max_depth_m)
        kept = rows[good][in_range]
        self._disparity[kept] = measured[good][in_range]
        self._points[kept] = points[in_range]
        # A new track without a stereo match is dropped (searching it again every frame costs
        # more than a new corner); an older one keeps its last disparity as the next guess.
        matched = np.zeros(len(self._ids), dtype=bool)
        matched[kept] = True
        stays = matched | np.isfinite(self._disparity)
        self._pixels = np.ascontiguousarray(self._pixels[stays])
        self._ids, self._disparity = self._ids[stays], self._disparity[stays]
        self._points, matched = self._points[stays], matched[stays]
        f_b = self.rectification.fx * self.rectification.baseline
        depth = self._points[matched, 2]
        return TrackedPoints(
            pixels=self._pixels[matched].astype(float),
            disparity=self._disparity[matched],
            points=self._points[matched],
            depth_sigma=depth**2 * config.disparity_sigma_px / f_b,
            descriptors=np.zeros((len(depth), 0), np.uint8),
            binary=True,
            ids=self._ids[matched],
        )

    def _search_disparity(
        self, left: np.ndarray, right: np.ndarray, pixels: np.ndarray
    ) -> np.ndarray:
        """Whole-pixel disparities of new tracks: zero-mean SAD of a patch along the row over
        the disparity range, NaN where the best is not clearly better than the rest."""
        config = self.config
        half = config.subpixel_window
        low = int(np.floor(config.min_disparity_px))
        high = int(np.ceil(config.max_disparity_px))
        pad = high + half + 1
        padded = [
            cv2.copyMakeBorder(image, half, half, pad, pad, cv2.BORDER_REPLICATE)
            for image in (left, right)
        ]
        u = np.rint(pixels[:, 0]).astype(np.intp) + pad
        v = np.rint(pixels[:, 1]).astype(np.intp) + half
        shifts = np.arange(-high, -low + 1)  # right x = u + shift = u - disparity
        cost = zero_mean_sad(padded[0], padded[1], u, v, u, half, shifts)
        # Disparities that would reach past the right image's left edge are not candidates.
        disparities = -shifts
        cost[disparities[None, :] > (u - pad)[:, None]] = np.inf
        best = np.argmin(cost, axis=1)
        rows = np.arange(len(best))
        best_cost = cost[rows, best]
        far = np.abs(np.arange(len(shifts))[None, :] - best[:, None]) > 2
        runner_up = np.where(far, cost, np.inf).min(axis=1)
        unique = np.isfinite(best_cost) & (best_cost < _UNIQUENESS * runner_up)
        return np.where(unique, disparities[best].astype(float), np.nan)


def _empty() -> TrackedPoints:
    base = StereoPoints.empty()
    return TrackedPoints(
        base.pixels, base.disparity, base.points, base.depth_sigma,
        np.zeros((0, 0), np.uint8), True, ids=np.zeros(0, np.int64),
    )  # fmt: skip


def match_tracks(
    reference: StereoPoints,
    current: StereoPoints,
    config: FrontendConfig,
    rectification: Rectification,
    images: tuple[np.ndarray, np.ndarray] | None = None,
) -> Correspondences:
    """Pairs of the tracks both frames share. With ``images`` (reference, current rectified
    left) and ``config.temporal_refine`` the current pixel is aligned with the reference
    patch by LK and re-triangulated there: tracks followed frame by frame drift a little,
    the keyframe's patch does not."""
    if not isinstance(reference, TrackedPoints) or not isinstance(current, TrackedPoints):
        raise ValueError("track matching needs the points of the track front end")
    _, reference_index, current_index = np.intersect1d(
        reference.ids, current.ids, assume_unique=True, return_indices=True
    )
    current_points = current.points[current_index]
    if images is not None and config.temporal_refine and len(reference_index):
        pixels, found = refine_pixels(
            images[0], images[1], reference.pixels[reference_index],
            current.pixels[current_index], config.temporal_refine_window,
        )  # fmt: skip
        reference_index, current_index = reference_index[found], current_index[found]
        current_points = triangulate(pixels[found], current.disparity[current_index], rectification)
    return Correspondences(
        reference_index=reference_index.astype(np.intp),
        current_index=current_index.astype(np.intp),
        reference_points=reference.points[reference_index],
        current_points=current_points,
    )
