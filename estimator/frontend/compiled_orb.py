"""ORB on one pyramid level as compiled kernels with array output (the default detector).

ORB's selection, step for step: FAST-9 corners, the ``2 n`` best by FAST score, the ``n`` best of
those by Harris, the grid's share of them; then, for the kept corners only, the angle and the 256
tests (n = ``max_features`` x ``detection_oversampling``). With ORB's own tests
(``steered_brief.orb_pattern``) the features are OpenCV's ORB's to the bit; with the seeded ones
this is ``fast-brief``. No ``KeyPoint`` object is made: for ~2 000 candidates per EuRoC image
they cost about as much as finding them (docs/performance.md).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from estimator.config import FrontendConfig
from estimator.frontend.fast_kernels import fast_corners, harris_response
from estimator.frontend.features import Features, empty_features, strongest_first
from estimator.frontend.steered_brief import DESCRIPTOR_BORDER, describe, orientation, smoothed

__all__ = ["CORNER_BORDER", "CompiledOrb", "best_indices"]

# ORB's edge threshold: its corners keep 31 px to the image's edge (more than the descriptor needs).
CORNER_BORDER = max(31, DESCRIPTOR_BORDER)
# FAST's threshold is raised to this many grey levels below the last image's cut.
FAST_CUT_MARGIN = 6

Select = Callable[[np.ndarray, np.ndarray, tuple], np.ndarray]


class CompiledOrb:
    """One detector's state across images: the raised FAST threshold of the last left image."""

    def __init__(self, config: FrontendConfig, pattern: np.ndarray, select: Select) -> None:
        """``pattern``: the (256, 4) test pairs; ``select``: the grid selection (indices of the
        kept points, given points, responses and the image shape)."""
        self.config = config
        self.pattern = pattern
        self._select = select
        self._candidates = int(np.ceil(config.max_features * config.detection_oversampling))
        # The last left image's 2 n-th best FAST score, when it had a surplus.
        self._last_cut: int | None = None
        self.threshold = config.fast_threshold  # the FAST threshold of the last image

    def detect(self, image: np.ndarray, same_scene: bool = False) -> Features:
        """ORB's selection on arrays: FAST-9 corners, the ``2 n`` best by FAST score, the
        ``n`` best of those by Harris, the grid's share of them; angles and descriptors only
        for the corners kept (n = ``max_features`` x ``detection_oversampling``)."""
        xs, ys, score = self._fast_corners(image, same_scene)
        if len(xs) > 2 * self._candidates:  # never on EuRoC: < 4 000 corners (performance.md)
            best = best_indices(score, 2 * self._candidates)
            xs, ys = xs[best], ys[best]
        response = harris_response(image, xs, ys)
        if len(xs) > self._candidates:
            best = best_indices(response, self._candidates)
            xs, ys, response = xs[best], ys[best], response[best]
        if len(xs) == 0:
            return empty_features(True)
        points = np.column_stack((xs, ys)).astype(float)
        keep = self._select(points, response, image.shape)
        keep = keep[strongest_first(points[keep], response[keep])]
        xs, ys, points, response = xs[keep], ys[keep], points[keep], response[keep]
        angle = orientation(image, xs, ys)
        descriptors = describe(smoothed(image), xs, ys, angle, self.pattern)
        return Features(points, descriptors, response, True)

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
            self.threshold = base if self._last_cut is None else max(
                base, min(self._last_cut - FAST_CUT_MARGIN, 254)
            )  # fmt: skip
        threshold = self.threshold
        xs, ys, score = fast_corners(image, threshold, CORNER_BORDER)
        wanted = 2 * self._candidates
        if threshold > base and len(xs) < wanted:
            xs, ys, score = fast_corners(image, base, CORNER_BORDER)
        if not same_scene:
            surplus = len(xs) >= wanted
            self._last_cut = int(np.partition(score, -wanted)[-wanted]) if surplus else None
        return xs, ys, score


def best_indices(values: np.ndarray, count: int) -> np.ndarray:
    """Indices (ascending) of the ``count`` largest values, and of any tied with the last."""
    if len(values) <= count:
        return np.arange(len(values))
    cut = np.partition(values, len(values) - count)[len(values) - count]
    return np.flatnonzero(values >= cut)
