"""ORB's 256 binary tests, measured on OpenCV's ORB rather than copied from it.

The compiled detector (compiled_orb.py) reproduces OpenCV's one-level ORB to the bit, and ORB's
descriptor is defined by the point pairs its authors learned, which are data inside OpenCV.
They are read back here by experiment: ORB describes tiles that each hold one straight step
edge (dark to bright) at a known offset from a corner of angle 0. A test compares the smoothed
grey values at its two points, so its bit is 1 exactly for the edge offsets that separate the
points' smoothed values; the first and last such offsets give both points' coordinates along
the edge's normal. Vertical edges give x, horizontal ones y, and diagonal ones x + y for the
tests whose points share an x or a y.

ORB smooths with a 7 x 7 Gaussian (sigma 2). Across an edge at offset t (bright where the
coordinate c >= t) the smoothed value is 0 for c - t <= -(h + 1), 255 for c - t >= h, and
strictly between in between, with h = 3 along an axis and h = 6 along a diagonal (both kernel
axes add up). For a test with its second point Q further along c than its first point P, the bit
(P darker than Q) is therefore 1 for t in [P - h + 1, Q + h]; mirrored edges (bright where
c <= t) give the tests with Q behind P: t in [Q - h, P + h - 1].

The result is checked for consistency (every test resolved, x + y agreeing with the diagonal
edges, points inside the patch); ``steered_brief.orb_pattern`` then checks the descriptors made
from it against ORB's on a texture before the detector uses them.
"""

from __future__ import annotations

import cv2
import numpy as np

__all__ = ["OrbPatternError", "measure_orb_pattern"]

BITS = 256
_TILE = 96  # the tests reach 13 px and the smoothing 3 (6 diagonally) more: room to spare
_OFFSETS = np.arange(-40, 41)  # edge offsets from the corner, past every test's reach
_REACH = {"x": 3, "y": 3, "diagonal": 6}  # h above: the smoothed edge's half width
_TILES_PER_ROW = 16


class OrbPatternError(RuntimeError):
    """OpenCV's ORB did not behave as the measurement assumes (another OpenCV build)."""


def measure_orb_pattern() -> np.ndarray:
    """(256, 4) int32 rows (x1, y1, x2, y2): ORB's test k has bit 1 when the smoothed grey
    value at (x1, y1), rotated by the corner's angle, is below the one at (x2, y2)."""
    along = {name: _along(name) for name in _REACH}
    (x1, x2), (y1, y2), (d1, d2) = along["x"], along["y"], along["diagonal"]
    # A test whose points share an x (or a y) is invisible to that edge: use x + y.
    x1, x2 = np.where(np.isnan(x1), d1 - y1, x1), np.where(np.isnan(x2), d2 - y2, x2)
    y1, y2 = np.where(np.isnan(y1), d1 - x1, y1), np.where(np.isnan(y2), d2 - x2, y2)
    pattern = np.column_stack((x1, y1, x2, y2))
    seen = ~np.isnan(d1)
    if (
        np.isnan(pattern).any()
        or np.any((x1 + y1 != d1)[seen])
        or np.any((x2 + y2 != d2)[seen])
        or np.abs(pattern).max() > 15
    ):
        raise OrbPatternError("OpenCV's ORB tests could not be measured consistently")
    return pattern.astype(np.int32)


def _along(direction: str) -> tuple[np.ndarray, np.ndarray]:
    """Both points' coordinates of every test along the normal of ``direction``'s edges
    (NaN where the two points are level with each other)."""
    reach = _REACH[direction]
    rising = _bits(direction, rising=True)
    falling = _bits(direction, rising=False)
    first = np.full(BITS, np.nan)
    second = np.full(BITS, np.nan)
    for test in range(BITS):
        up = _OFFSETS[rising[:, test]]
        down = _OFFSETS[falling[:, test]]
        if len(up) and len(down):
            raise OrbPatternError("a test answered both edge directions")
        if len(up):
            first[test], second[test] = up[0] + reach - 1, up[-1] - reach
        elif len(down):
            second[test], first[test] = down[0] + reach, down[-1] - reach + 1
        for on in (up, down):
            if len(on) and len(on) != on[-1] - on[0] + 1:
                raise OrbPatternError("a test's edge offsets are not one interval")
    return first, second


def _bits(direction: str, rising: bool) -> np.ndarray:
    """(offsets, 256) bool: ORB's bits for one tile per edge offset, corner angle 0."""
    count = len(_OFFSETS)
    rows = -(-count // _TILES_PER_ROW)
    image = np.zeros((rows * _TILE, _TILES_PER_ROW * _TILE), dtype=np.uint8)
    centre = _TILE // 2
    v, u = np.mgrid[0:_TILE, 0:_TILE] - centre
    coordinate = {"x": u, "y": v, "diagonal": u + v}[direction]
    keypoints = []
    for index, offset in enumerate(_OFFSETS):
        row, column = divmod(index, _TILES_PER_ROW)
        bright = coordinate >= offset if rising else coordinate <= offset
        image[row * _TILE : (row + 1) * _TILE, column * _TILE : (column + 1) * _TILE] = (
            bright * np.uint8(255)
        )
        position = (float(column * _TILE + centre), float(row * _TILE + centre))
        keypoints.append(cv2.KeyPoint(*position, 31.0, 0.0))
    orb = cv2.ORB_create(nlevels=1, edgeThreshold=31, patchSize=31)
    described, descriptors = orb.compute(image, keypoints)
    if descriptors is None or len(described) != count or descriptors.shape[1] * 8 != BITS:
        raise OrbPatternError("OpenCV's ORB did not describe every probe")
    if any(keypoint.angle != 0.0 for keypoint in described):
        raise OrbPatternError("OpenCV's ORB changed the probes' angle")
    return np.unpackbits(descriptors, axis=1, bitorder="little").astype(bool)
