"""Adaptive FAST threshold: the corners ORB keeps, without the corners it throws away.

ORB on one pyramid level runs FAST at its threshold over the image, drops the corners within
its edge threshold of the border, keeps the ``2 n`` with the best FAST score, scores those with
Harris and keeps the ``n`` best. A corner's FAST score does not depend on the threshold, and
neither does the non-maximum suppression among the corners above it (a stronger neighbour is
above any threshold the corner passes). So every threshold that still leaves ``2 n`` corners
gives exactly the same kept corners, and a higher one is cheaper: on a 1241 x 376 street image
FAST finds about 16 000 corners at 12 grey levels for the 4 800 that ORB looks at
(docs/performance.md).

The count at a higher threshold is estimated on the image itself, from FAST on thin strips of
rows (one row in 16): the strip corners' scores give the count above any threshold at once.
The strips run at a sampling threshold a little below the previous image's choice, so that
they return few corners (each costs a Python object). The threshold chosen is the highest whose
estimate keeps ``COUNT_MARGIN`` above ``2 n``; when the strips do not show that many corners
the configured threshold is used, and nothing changes. An image with too few corners even at
the configured threshold (every EuRoC image) is detected at it, and so are the next few,
unsampled.
"""

from __future__ import annotations

import math
from operator import attrgetter

import cv2
import numpy as np

__all__ = ["COUNT_MARGIN", "SAMPLED_ROW_FRACTION", "AdaptiveFastThreshold"]

SAMPLED_ROW_FRACTION = 1 / 16  # rows of the image whose FAST corners are counted
STRIP_ROWS = 4  # rows per strip: many thin strips follow the texture down the image
# The estimate must exceed ORB's 2 n by this factor: 1.25 is about four standard deviations
# of the estimate at the drive's 4 800 corners (a few hundred of them counted in the strips).
COUNT_MARGIN = 1.25
SAMPLING_STEP_DOWN = 4  # sampling threshold = previous choice minus this (grey levels)
# Images too sparse to raise the threshold (every EuRoC one) are sampled only this often.
RECHECK_EVERY = 10
_FAST_RADIUS = 3  # FAST's circle: no corner within 3 px of an image's border
_NMS_RADIUS = 1  # non-maximum suppression compares the 8 neighbours
_RESPONSE = attrgetter("response")


class AdaptiveFastThreshold:
    """FAST threshold per image for an ORB detector that looks at ``wanted`` corners.

    ``base`` is the configured threshold (the lowest used), ``edge`` ORB's edge threshold.
    The state (the last choice) makes the next image's sampling cheaper, not its result.
    """

    def __init__(self, base: int, wanted: int, edge: int) -> None:
        self.base = int(base)
        self.wanted = int(wanted)
        self.edge = int(edge)
        self.last = self.base
        self._sparse_images = 0  # images left to detect at the base threshold unsampled
        self._fast = cv2.FastFeatureDetector_create(self.base, True)

    def choose(self, image: np.ndarray) -> int:
        """The highest threshold that still leaves ``wanted`` corners, with the margin."""
        if self._sparse_images > 0:
            self._sparse_images -= 1
            return self.base
        sampling = max(self.base, self.last - SAMPLING_STEP_DOWN)
        estimate = self.estimate_counts(image, sampling)
        if estimate is None:
            self.last = self.base
            return self.base
        scores, scale = estimate
        needed = math.ceil(COUNT_MARGIN * self.wanted / scale)
        if len(scores) < needed:  # too few corners above the sampling threshold to tell
            if sampling == self.base:  # too few at all: the base it is for a while
                self._sparse_images = RECHECK_EVERY - 1
            self.last = self.base  # below it nothing was counted: sample from the base next
            return self.base
        chosen = int(np.partition(scores, len(scores) - needed)[len(scores) - needed])
        self.last = max(chosen, self.base)
        return self.last

    def reuse(self) -> int:
        """The threshold chosen for the last image, for the other image of the same stereo
        pair: both see the same scene through the same optics and exposure, so the corner
        count above it differs by far less than ``COUNT_MARGIN`` leaves room for, and sampling
        the strips again (about 1 ms at 1241 x 376) would only confirm it. A right image that
        still falls short is detected again at the base threshold (``FeatureDetector``)."""
        return self.last

    def estimate_counts(self, image: np.ndarray, threshold: int) -> tuple[np.ndarray, float] | None:
        """FAST scores of the corners in the sampled strips, and strip rows -> image rows.

        Only the area ORB keeps (``edge`` px in from the border) is sampled. Each strip is cut
        with FAST's circle and one row of suppression neighbours around it, so its corners and
        their suppression are exactly those of a run over the whole image. ``None`` when the
        image is too small to sample.
        """
        height, width = image.shape[:2]
        pad = _FAST_RADIUS + _NMS_RADIUS
        left, right = self.edge, width - self.edge  # columns ORB keeps: [left, right)
        starts = self.strip_starts(height)
        if starts is None or right - left < 2 * pad:
            return None
        scale = (height - 2 * self.edge) / (len(starts) * STRIP_ROWS)
        window = STRIP_ROWS + 2 * pad
        # The strips, each with its margin, stacked into one image: one FAST call. A corner in
        # a strip's own rows sees only rows of its window, so the seams change nothing.
        columns = slice(left - pad, right + pad)
        stacked = np.concatenate([image[s - pad : s + pad + STRIP_ROWS, columns] for s in starts])
        self._fast.setThreshold(int(threshold))
        corners = self._fast.detect(stacked)
        if not corners:
            return np.zeros(0), scale
        position = cv2.KeyPoint_convert(corners)
        row_in_window = position[:, 1].astype(int) % window
        inside = (
            (row_in_window >= pad)
            & (row_in_window < pad + STRIP_ROWS)
            & (position[:, 0] >= pad)
            & (position[:, 0] < pad + right - left)
        )
        sampled = np.fromiter(map(_RESPONSE, corners), float, len(corners))[inside]
        return sampled, scale

    def strip_starts(self, height: int) -> np.ndarray | None:
        """First row of each sampled strip (``STRIP_ROWS`` rows each), spread evenly over the
        rows ORB keeps; ``None`` when the image is too low to sample."""
        top, bottom = self.edge, height - self.edge  # rows ORB keeps: [top, bottom)
        if bottom - top < 4 * STRIP_ROWS or top < _FAST_RADIUS + _NMS_RADIUS:
            return None
        strips = max(1, round((bottom - top) * SAMPLED_ROW_FRACTION / STRIP_ROWS))
        return (top + (np.arange(strips) + 0.5) * (bottom - top - STRIP_ROWS) / strips).astype(int)
