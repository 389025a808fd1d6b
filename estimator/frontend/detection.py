"""The feature detector: ORB (compiled on one level, OpenCV's on a pyramid) or SIFT, with the
corners bucketed over a grid and handed out strongest first."""

from __future__ import annotations

from operator import attrgetter

import cv2
import numpy as np

from estimator.config import FrontendConfig
from estimator.frontend.compiled_orb import CompiledOrb
from estimator.frontend.fast_threshold import AdaptiveFastThreshold
from estimator.frontend.features import Features, empty_features, grid_select, strongest_first
from estimator.frontend.steered_brief import PATTERN, orb_pattern

__all__ = ["FeatureDetector"]

_RESPONSE = attrgetter("response")  # cheaper per keypoint than a generator expression


class FeatureDetector:
    """ORB corners with descriptors (default), or SIFT's, bucketed over a grid.

    ORB on one pyramid level (the default) runs as compiled kernels with array output: the
    same corners, angles, responses and descriptors as OpenCV's ORB, to the bit, for about
    a third less CPU (docs/performance.md). ``fast-brief`` is the same with this project's
    own test pairs. OpenCV's ORB runs for pyramids, or when its tests cannot be reproduced.
    """

    def __init__(self, config: FrontendConfig, opencv_orb: bool = False) -> None:
        """``opencv_orb``: run OpenCV's ORB even where the compiled kernels reproduce it (the
        reference for tests and benchmarks)."""
        self.config = config
        candidates = int(np.ceil(config.max_features * config.detection_oversampling))
        # The compiled kernels, with their test pairs, where they run (one level: orb_levels
        # and orb_scale_factor are the pyramid's alone).
        pattern: np.ndarray | None = None
        if config.detector == "fast-brief":
            pattern = PATTERN
        elif config.detector == "orb" and config.orb_levels == 1 and not opencv_orb:
            pattern = orb_pattern()
        self.compiled_orb = None if pattern is None else CompiledOrb(config, pattern, self._select)
        self._detector: cv2.Feature2D | None = None
        if config.detector == "orb" and pattern is None:
            self._detector = cv2.ORB_create(
                nfeatures=candidates,
                scaleFactor=config.orb_scale_factor,
                nlevels=config.orb_levels,
                fastThreshold=config.fast_threshold,
            )
        elif config.detector == "sift":
            self._detector = cv2.SIFT_create(nfeatures=candidates)
        self.binary = config.detector != "sift"
        self._candidates = candidates
        # OpenCV's ORB on one level looks at the 2 x candidates best FAST corners
        # (fast_threshold.py).
        self.fast_threshold: AdaptiveFastThreshold | None = None
        orb = config.detector == "orb" and self._detector is not None
        if orb and config.orb_levels == 1 and config.adaptive_fast_threshold:
            self.fast_threshold = AdaptiveFastThreshold(
                config.fast_threshold, 2 * candidates, self._detector.getEdgeThreshold()
            )

    @property
    def compiled(self) -> bool:
        """Whether the compiled kernels detect (rather than OpenCV's ORB or SIFT)."""
        return self.compiled_orb is not None

    def detect(self, image: np.ndarray, same_scene: bool = False) -> Features:
        """Keypoints and descriptors of one 8-bit grey image.

        ORB corners are detected first and bucketed, and descriptors are computed only for
        the kept ones: describing the over-sampled candidates that the grid drops is work
        thrown away (docs/performance.md). Points and descriptors are identical to those of a
        joint detect-and-compute call. ORB's corners come strongest first (ties by row, then
        column) from either implementation, not in the order OpenCV's selection happens to
        leave them, so that both give the same features; the tie rules of the matching
        further on then favour the stronger corner (docs/frontend.md). ``same_scene``: the
        other image of the pair just detected, whose adaptive FAST threshold is reused.
        """
        if not self.binary:  # SIFT's compute rebuilds its scale space: one call is cheaper
            return self._detect_and_compute(image)
        if self.compiled_orb is not None:
            return self.compiled_orb.detect(image, same_scene)
        keypoints = self._orb_corners(image, same_scene)
        if not keypoints:
            return empty_features(self.binary)
        points = cv2.KeyPoint_convert(keypoints).astype(float)
        response = np.fromiter(map(_RESPONSE, keypoints), float, len(keypoints))
        raster = np.lexsort((points[:, 0], points[:, 1]))
        # The grid sees the corners in raster order, as the compiled detector's; ORB describes
        # them in its own order (grouped by pyramid level).
        keep = np.sort(raster[self._select(points[raster], response[raster], image.shape)])
        keypoints = [keypoints[i] for i in keep]
        return _strongest_first(self._describe(image, keypoints, points[keep], response[keep]))

    def _orb_corners(self, image: np.ndarray, same_scene: bool = False) -> list:
        """ORB's corners, found at the adaptive FAST threshold when there is one.

        Fewer corners than ORB asks for at a raised threshold mean the estimate was wrong
        (then the configured threshold's corners are taken, the same as without adapting).
        """
        if self.fast_threshold is None:
            return self._detector.detect(image, None)
        adaptive = self.fast_threshold
        threshold = adaptive.reuse() if same_scene else adaptive.choose(image)
        self._detector.setFastThreshold(threshold)
        keypoints = self._detector.detect(image, None)
        if threshold > adaptive.base and len(keypoints) < self._candidates:
            self._detector.setFastThreshold(adaptive.base)
            keypoints = self._detector.detect(image, None)
            adaptive.last = adaptive.base
        return keypoints

    def _describe(
        self, image: np.ndarray, keypoints: list, points: np.ndarray, response: np.ndarray
    ) -> Features:
        """ORB descriptors of the chosen keypoints (``points`` and ``response`` match them)."""
        described, descriptors = self._detector.compute(image, keypoints)
        if descriptors is None or len(described) == 0:
            return empty_features(self.binary)
        if len(described) != len(keypoints):  # dropped near the border: match by position
            kept = _described_index(points, cv2.KeyPoint_convert(described))
            points, response = points[kept], response[kept]
        return Features(points, descriptors, response, self.binary)

    def _detect_and_compute(self, image: np.ndarray) -> Features:
        keypoints, descriptors = self._detector.detectAndCompute(image, None)
        if not keypoints or descriptors is None:
            return empty_features(self.binary)
        points = cv2.KeyPoint_convert(keypoints).astype(float)
        response = np.fromiter(map(_RESPONSE, keypoints), float, len(keypoints))
        keep = self._select(points, response, image.shape)
        return Features(points[keep], descriptors[keep], response[keep], self.binary)

    def _select(self, points: np.ndarray, response: np.ndarray, shape: tuple) -> np.ndarray:
        height, width = shape[:2]
        return grid_select(
            points,
            response,
            (width, height),
            (self.config.grid_rows, self.config.grid_cols),
            self.config.max_features,
        )


def _strongest_first(features: Features) -> Features:
    """The features in ``strongest_first`` order (OpenCV's ORB leaves them in its own)."""
    order = strongest_first(features.points, features.response)
    return Features(
        features.points[order], features.descriptors[order], features.response[order],
        features.binary,
    )  # fmt: skip


def _described_index(points: np.ndarray, described: np.ndarray) -> np.ndarray:
    """Index into ``points`` of each described keypoint (``compute`` keeps the order)."""
    index = np.empty(len(described), dtype=np.intp)
    position = 0
    for k, point in enumerate(described):
        while not np.allclose(points[position], point):
            position += 1
        index[k] = position
        position += 1
    return index
