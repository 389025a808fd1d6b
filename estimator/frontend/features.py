"""Feature detection spread over the image, and descriptor matching between candidate pairs.

Registration is only as good as the geometry of its points: corners bunched in one textured
corner give a poorly conditioned rotation. Detection therefore over-samples and then keeps the
strongest corners cell by cell (grid bucketing), round-robin over the cells, up to a budget.

Matching works on *candidate pairs* that the caller has already restricted geometrically (the
same row band for stereo, a search radius in time), so the descriptor distances computed are
only the plausible ones and the ratio / mutual checks happen within those candidates.
"""

from __future__ import annotations

from dataclasses import dataclass
from operator import attrgetter

import cv2
import numba
import numpy as np

from estimator.config import FrontendConfig
from estimator.frontend.fast_kernels import fast_corners, harris_response
from estimator.frontend.fast_threshold import AdaptiveFastThreshold
from estimator.frontend.match_kernels import as_words
from estimator.frontend.steered_brief import (
    DESCRIPTOR_BORDER,
    PATTERN,
    describe,
    orb_pattern,
    orientation,
    smoothed,
)

__all__ = [
    "FeatureDetector",
    "Features",
    "MatchSet",
    "descriptor_distances",
    "grid_select",
    "match_candidates",
]

_RESPONSE = attrgetter("response")  # cheaper per keypoint than a generator expression
# ORB's edge threshold: its corners keep 31 px to the image's edge (more than the descriptor needs).
CORNER_BORDER = max(31, DESCRIPTOR_BORDER)
# The compiled detector raises FAST's threshold to this many grey levels below the last image's cut.
FAST_CUT_MARGIN = 6


@dataclass(frozen=True)
class Features:
    """Keypoints of one image: pixel positions, descriptors and corner strength."""

    points: np.ndarray  # (N, 2) float64, (x, y) pixels
    descriptors: np.ndarray  # (N, 32) uint8 for ORB, (N, 128) float32 for SIFT
    response: np.ndarray  # (N,) detector response
    binary: bool  # True: Hamming distance, False: L2

    def __len__(self) -> int:
        return len(self.points)


@dataclass(frozen=True)
class MatchSet:
    """Accepted pairs (a[i] <-> b[i]) with their descriptor distances."""

    a: np.ndarray  # (M,) int
    b: np.ndarray  # (M,) int
    distance: np.ndarray  # (M,) float

    def __len__(self) -> int:
        return len(self.a)


def grid_select(
    points: np.ndarray,
    response: np.ndarray,
    image_size: tuple[int, int],
    grid: tuple[int, int],
    budget: int,
) -> np.ndarray:
    """Indices of at most ``budget`` points: every cell's best, then every cell's second, ...

    Round-robin by rank spreads the budget evenly where there is texture and hands the share of
    empty cells to the textured ones, instead of wasting it.
    """
    if len(points) <= budget:  # everything fits: the common case on 752x480 frames
        return np.arange(len(points), dtype=np.intp)
    width, height = image_size
    rows, cols = grid
    col = np.clip((points[:, 0] * cols / width).astype(np.intp), 0, cols - 1)
    row = np.clip((points[:, 1] * rows / height).astype(np.intp), 0, rows - 1)
    strongest = np.argsort(-response, kind="stable")
    order = _round_robin(row * cols + col, strongest, rows * cols)
    return np.sort(order[:budget])


@numba.njit(cache=True, nogil=True)
def _round_robin(cell: np.ndarray, strongest: np.ndarray, cells: int) -> np.ndarray:
    """Points ordered by their strength rank within their cell, then by strength.

    ``strongest`` lists the points strongest first (ties by index); two counting passes over
    it give the order of a lexsort by (rank in cell, strength) in linear time.
    """
    count = np.zeros(cells, dtype=np.int64)
    rank = np.empty(len(cell), dtype=np.int64)
    for point in strongest:
        rank[point] = count[cell[point]]
        count[cell[point]] += 1
    start = np.zeros(count.max() + 1, dtype=np.int64)
    for point in strongest:
        if rank[point] + 1 < len(start):
            start[rank[point] + 1] += 1
    for level in range(1, len(start)):
        start[level] += start[level - 1]
    order = np.empty(len(cell), dtype=np.int64)
    for point in strongest:
        order[start[rank[point]]] = point
        start[rank[point]] += 1
    return order


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
        # The compiled kernels' test pairs, when they run (one level: orb_levels and
        # orb_scale_factor are the pyramid's alone).
        self._pattern: np.ndarray | None = None
        if config.detector == "fast-brief":
            self._pattern = PATTERN
        elif config.detector == "orb" and config.orb_levels == 1 and not opencv_orb:
            self._pattern = orb_pattern()
        self._detector: cv2.Feature2D | None = None
        if config.detector == "orb" and self._pattern is None:
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
        # Compiled: the last left image's 2 n-th best FAST score, when it had a surplus.
        self._last_cut: int | None = None
        self._raised_threshold = config.fast_threshold
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
        return self._pattern is not None

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
        if self._pattern is not None:
            return self._compiled(image, self._pattern, same_scene)
        keypoints = self._orb_corners(image, same_scene)
        if not keypoints:
            return self._empty()
        points = cv2.KeyPoint_convert(keypoints).astype(float)
        response = np.fromiter(map(_RESPONSE, keypoints), float, len(keypoints))
        raster = np.lexsort((points[:, 0], points[:, 1]))
        # The grid sees the corners in raster order, as the compiled detector's; ORB describes
        # them in its own order (grouped by pyramid level).
        keep = np.sort(raster[self._select(points[raster], response[raster], image.shape)])
        keypoints = [keypoints[i] for i in keep]
        return _strongest_first(self._describe(image, keypoints, points[keep], response[keep]))

    def _fast_corners(
        self, image: np.ndarray, same_scene: bool
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """FAST corners for the ``2 n`` best, at a threshold raised to just below the last
        image's ``2 n``-th best score when there was a surplus (a wide street image: 16 000
        corners for 4 800).

        The same corners as at the configured threshold whenever at least ``2 n`` remain: a
        corner's score is the highest threshold it passes, and a neighbour under the raised
        threshold scored below the corner anyway, so the suppression keeps what it kept.
        Fewer than ``2 n`` means the guess was too high: the image is detected again at the
        configured threshold. ``same_scene`` (the right image of the pair) reuses the guess.
        """
        base = self.config.fast_threshold
        if not self.config.adaptive_fast_threshold:
            return fast_corners(image, base, CORNER_BORDER)
        if not same_scene:
            self._raised_threshold = base if self._last_cut is None else max(
                base, min(self._last_cut - FAST_CUT_MARGIN, 254)
            )  # fmt: skip
        threshold = self._raised_threshold
        xs, ys, score = fast_corners(image, threshold, CORNER_BORDER)
        wanted = 2 * self._candidates
        if threshold > base and len(xs) < wanted:
            xs, ys, score = fast_corners(image, base, CORNER_BORDER)
        if not same_scene:
            surplus = len(xs) >= wanted
            self._last_cut = int(np.partition(score, -wanted)[-wanted]) if surplus else None
        return xs, ys, score

    def _compiled(self, image: np.ndarray, pattern: np.ndarray, same_scene: bool) -> Features:
        """ORB's selection on arrays: FAST-9 corners, the ``2 n`` best by FAST score, the
        ``n`` best of those by Harris, the grid's share of them; angles and descriptors only
        for the corners kept (n = ``max_features`` x ``detection_oversampling``)."""
        xs, ys, score = self._fast_corners(image, same_scene)
        if len(xs) > 2 * self._candidates:  # never on EuRoC: < 4 000 corners (performance.md)
            best = _best(score, 2 * self._candidates)
            xs, ys = xs[best], ys[best]
        response = harris_response(image, xs, ys)
        if len(xs) > self._candidates:
            best = _best(response, self._candidates)
            xs, ys, response = xs[best], ys[best], response[best]
        if len(xs) == 0:
            return self._empty()
        points = np.column_stack((xs, ys)).astype(float)
        keep = self._select(points, response, image.shape)
        # Kept in raster order: a stable sort by strength leaves equal ones by row, column.
        keep = keep[np.argsort(-response[keep], kind="stable")]
        xs, ys, points, response = xs[keep], ys[keep], points[keep], response[keep]
        angle = orientation(image, xs, ys)
        descriptors = describe(smoothed(image), xs, ys, angle, pattern)
        return Features(points, descriptors, response, True)

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
        if threshold > self.fast_threshold.base and len(keypoints) < self._candidates:
            self._detector.setFastThreshold(self.fast_threshold.base)
            keypoints = self._detector.detect(image, None)
            self.fast_threshold.last = self.fast_threshold.base
        return keypoints

    def _describe(
        self, image: np.ndarray, keypoints: list, points: np.ndarray, response: np.ndarray
    ) -> Features:
        """ORB descriptors of the chosen keypoints (``points`` and ``response`` match them)."""
        described, descriptors = self._detector.compute(image, keypoints)
        if descriptors is None or len(described) == 0:
            return self._empty()
        if len(described) != len(keypoints):  # dropped near the border: match by position
            kept = _described_index(points, cv2.KeyPoint_convert(described))
            points, response = points[kept], response[kept]
        return Features(points, descriptors, response, self.binary)

    def _detect_and_compute(self, image: np.ndarray) -> Features:
        keypoints, descriptors = self._detector.detectAndCompute(image, None)
        if not keypoints or descriptors is None:
            return self._empty()
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

    def _empty(self) -> Features:
        width = 32 if self.binary else 128
        dtype = np.uint8 if self.binary else np.float32
        return Features(np.zeros((0, 2)), np.zeros((0, width), dtype), np.zeros(0), self.binary)


def _strongest_first(features: Features) -> Features:
    """The features by decreasing corner response, equal responses by row, then column: an
    order that does not depend on the implementation and puts no part of the image first."""
    points = features.points
    order = np.lexsort((points[:, 0], points[:, 1], -features.response))
    return Features(
        points[order], features.descriptors[order], features.response[order], features.binary
    )


def _best(values: np.ndarray, count: int) -> np.ndarray:
    """Indices (ascending) of the ``count`` largest values, and of any tied with the last."""
    if len(values) <= count:
        return np.arange(len(values))
    cut = np.partition(values, len(values) - count)[len(values) - count]
    return np.flatnonzero(values >= cut)


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


def descriptor_distances(
    a: np.ndarray, b: np.ndarray, ia: np.ndarray, ib: np.ndarray, binary: bool
) -> np.ndarray:
    """Distance between descriptors a[ia] and b[ib], pair by pair (Hamming or L2)."""
    # np.take gathers whole rows much faster than fancy indexing of a 2-D array.
    if binary:
        # 64-bit words: 4 popcounts per 256-bit ORB descriptor instead of 32.
        xor = np.bitwise_xor(np.take(as_words(a), ia, axis=0), np.take(as_words(b), ib, axis=0))
        counts = np.bitwise_count(xor)
        total = counts[:, 0].astype(float)
        for word in range(1, counts.shape[1]):  # a few words; a sum over axis 1 is slower
            total += counts[:, word]
        return total
    difference = np.take(a, ia, axis=0).astype(np.float32) - np.take(b, ib, axis=0)
    return np.sqrt(np.einsum("ij,ij->i", difference, difference)).astype(float)


def _best_per_group(group: np.ndarray, distance: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Row index of each group's smallest distance, and that group's second-smallest distance.

    Scatter-min reductions (``np.minimum.at``) instead of a sort: linear in the number of
    candidate pairs. Ties go to the lowest row. Returns one entry per group that occurs.
    """
    size = int(group.max()) + 1  # groups are point indices: dense tables, no sorting
    rows = np.arange(len(group))
    best_distance = np.full(size, np.inf)
    np.minimum.at(best_distance, group, distance)
    is_best = distance == best_distance[group]
    best_row = np.full(size, len(group))
    np.minimum.at(best_row, group[is_best], rows[is_best])
    present = best_row < len(group)
    best_row = best_row[present]
    others = np.ones(len(group), dtype=bool)
    others[best_row] = False
    second = np.full(size, np.inf)
    np.minimum.at(second, group[others], distance[others])
    return best_row, second[present]


def match_candidates(
    ia: np.ndarray,
    ib: np.ndarray,
    distance: np.ndarray,
    *,
    ratio: float,
    max_distance: float,
    mutual: bool = True,
) -> MatchSet:
    """Pick one partner per ``a`` among candidate pairs (ia, ib, distance).

    A pair is accepted when it is a's nearest candidate, clearly better than a's second one
    (Lowe's ratio test), within ``max_distance`` and, with ``mutual``, also b's nearest.
    """
    if len(ia) == 0:
        empty = np.zeros(0, dtype=np.intp)
        return MatchSet(empty, empty, np.zeros(0))
    best_of_a, second = _best_per_group(ia, distance)
    accept = (distance[best_of_a] <= max_distance) & (distance[best_of_a] < ratio * second)
    chosen = best_of_a[accept]
    if mutual:
        best_of_b, _ = _best_per_group(ib, distance)
        owner = np.full(int(ib.max()) + 1, -1, dtype=np.intp)
        owner[ib[best_of_b]] = ia[best_of_b]
        chosen = chosen[owner[ib[chosen]] == ia[chosen]]
    return MatchSet(ia[chosen].astype(np.intp), ib[chosen].astype(np.intp), distance[chosen])
