"""FAST-9 corners and their Harris score as compiled kernels with array output.

The ``fast-brief`` detector (features.py) finds the corners ORB finds on one pyramid level, but
returns arrays instead of one Python object per corner: on a 752 x 480 EuRoC image the objects
of ~2 000 candidates cost about as much as finding them (docs/performance.md).

FAST-9: a pixel p is a corner when 9 contiguous pixels of the 16 on the radius-3 Bresenham
circle are all brighter than p + t or all darker than p - t. Its score is the largest t for
which it still is (the best 9-arc's smallest difference, minus one), so it does not depend on
the threshold; a corner survives the non-maximum suppression when its score beats all 8
neighbours' (a neighbour that is no corner scores 0). Harris: R = det(M) - k tr(M)^2 with M the
sums of the Sobel gradient products over a 7 x 7 block around the corner.
"""

from __future__ import annotations

import numba
import numpy as np

__all__ = ["CIRCLE", "HARRIS_BLOCK", "HARRIS_K", "fast_corners", "harris_response"]

# The radius-3 circle, in order around it: (dx, dy) of its 16 pixels.
CIRCLE = np.array(
    [(0, 3), (1, 3), (2, 2), (3, 1), (3, 0), (3, -1), (2, -2), (1, -3),
     (0, -3), (-1, -3), (-2, -2), (-3, -1), (-3, 0), (-3, 1), (-2, 2), (-1, 3)],
    dtype=np.int64,
)  # fmt: skip
HARRIS_BLOCK = 7
HARRIS_K = 0.04
# Gradients are scaled to [-1, 1] per unit step (Sobel weights sum 4, over 255 grey levels)
# and averaged over the block, so responses are comparable between images.
_HARRIS_SCALE = 1.0 / (4.0 * HARRIS_BLOCK * 255.0)


@numba.njit(cache=True, nogil=True)
def _ring_masks(
    image: np.ndarray, y: int, low_x: int, threshold: int,
    above: np.ndarray, below: np.ndarray, high: np.ndarray, low: np.ndarray,
) -> None:
    """Bit i of above[k] / below[k]: circle pixel i of (low_x + k, y) is brighter / darker
    than the centre by more than ``threshold``; then only the masks with a 9-arc are kept.

    Loops over row slices with non-negative indices only: numba compiles them to SIMD (signed
    offsets into the image would add a wrap-around branch per access and stop that).
    """
    n = len(above)
    centre = image[y, low_x : low_x + n]
    for k in range(n):
        high[k] = np.int16(centre[k]) + threshold
        low[k] = np.int16(centre[k]) - threshold
        above[k] = 0
        below[k] = 0
    for i in range(16):
        bit = np.uint32(1 << i)
        ring = image[y + CIRCLE[i, 1], low_x + CIRCLE[i, 0] : low_x + CIRCLE[i, 0] + n]
        for k in range(n):
            value = np.int16(ring[k])
            above[k] |= bit if value > high[k] else np.uint32(0)
            below[k] |= bit if value < low[k] else np.uint32(0)
    for k in range(n):
        above[k] = _arcs(above[k])
        below[k] = _arcs(below[k])


@numba.njit(cache=True, nogil=True, inline="always")
def _arcs(bits: np.uint32) -> np.uint32:
    """Non-zero when a 16-bit ring mask has 9 contiguous set bits (wrapping around)."""
    ring = bits | (bits << np.uint32(16))
    run = ring & (ring >> np.uint32(1))  # runs of 2
    run = run & (run >> np.uint32(2))  # 4
    run = run & (run >> np.uint32(4))  # 8
    run = run & (ring >> np.uint32(8))  # 9
    return run & np.uint32(0xFFFF)


@numba.njit(cache=True, nogil=True)
def _row_scores(
    image: np.ndarray, y: int, low_x: int, index: np.ndarray, sign: np.ndarray,
    diff: np.ndarray, pair: np.ndarray, out: np.ndarray,
) -> None:
    """FAST scores of the row's corners at x = low_x + index[j] (``sign`` +1 for a bright
    arc, -1 for a dark one): the best 9-arc's smallest difference, minus one.

    Column j of ``diff`` holds the 16 circle differences and the first 8 again; the sliding
    minimum over 9 is built from pairs, then runs of 4 and 8, each a loop over the corners.
    """
    m = len(index)
    centre = image[y, low_x:]
    for i in range(16):
        ring = image[y + CIRCLE[i, 1], low_x + CIRCLE[i, 0] :]
        row = diff[i]
        for j in range(m):
            row[j] = sign[j] * (np.int16(ring[index[j]]) - np.int16(centre[index[j]]))
    for i in range(16, 24):
        diff[i, :m] = diff[i - 16, :m]
    for i in range(23):
        a, b, p = diff[i], diff[i + 1], pair[i]
        for j in range(m):
            p[j] = min(a[j], b[j])
    for j in range(m):
        out[j] = -32768
    for i in range(16):
        a, b, c, d, e = pair[i], pair[i + 2], pair[i + 4], pair[i + 6], diff[i + 8]
        for j in range(m):
            out[j] = max(out[j], min(min(min(a[j], b[j]), min(c[j], d[j])), e[j]))
    for j in range(m):
        out[j] -= 1


@numba.njit(cache=True, nogil=True)
def _score_image(
    image: np.ndarray, threshold: int, border: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """FAST score of every corner with at least ``border`` - 1 pixels to the image's edge
    (0 elsewhere), and those corners' x, y in raster order (the first ``count`` entries)."""
    height, width = image.shape
    score = np.zeros((height, width), dtype=np.int16)
    low_y, high_y = max(border - 1, 3), min(height - border + 1, height - 3)
    low_x, high_x = max(border - 1, 3), min(width - border + 1, width - 3)
    n = max(high_x - low_x, 0)
    above = np.empty(n, dtype=np.uint32)
    below = np.empty(n, dtype=np.uint32)
    high = np.empty(n, dtype=np.int16)
    low = np.empty(n, dtype=np.int16)
    index = np.empty(n, dtype=np.int64)
    sign = np.empty(n, dtype=np.int16)
    diff = np.empty((24, n), dtype=np.int16)
    pair = np.empty((23, n), dtype=np.int16)
    row_score = np.empty(n, dtype=np.int16)
    xs = np.empty(4096, dtype=np.int64)
    ys = np.empty(4096, dtype=np.int64)
    count = 0
    for y in range(low_y, high_y):
        _ring_masks(image, y, low_x, np.int16(threshold), above, below, high, low)
        m = 0
        for k in range(n):
            if above[k] != 0 or below[k] != 0:
                index[m] = k
                sign[m] = 1 if above[k] != 0 else -1
                m += 1
        if m == 0:
            continue
        _row_scores(image, y, low_x, index[:m], sign, diff, pair, row_score)
        if count + m > len(xs):
            xs, ys = _grown(xs, 2 * (count + m)), _grown(ys, 2 * (count + m))
        for j in range(m):
            score[y, low_x + index[j]] = row_score[j]
            xs[count], ys[count] = low_x + index[j], y
            count += 1
    return score, xs, ys, count


@numba.njit(cache=True, nogil=True)
def fast_corners(
    image: np.ndarray, threshold: int, border: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """FAST-9 corners at least ``border`` pixels inside the image, after 3 x 3 suppression.

    Returns (x, y, score) in raster order. A pixel at exactly ``border`` counts as inside, one
    at ``size - border`` does not. ``border`` >= 3 (the circle's radius).
    """
    height, width = image.shape
    score, xs, ys, count = _score_image(image, threshold, border)
    keep = np.empty(count, dtype=np.bool_)
    for j in range(count):
        x, y = xs[j], ys[j]
        value = score[y, x]
        keep[j] = (
            border <= x < width - border and border <= y < height - border
            and value > score[y - 1, x - 1] and value > score[y - 1, x]
            and value > score[y - 1, x + 1] and value > score[y, x - 1]
            and value > score[y, x + 1] and value > score[y + 1, x - 1]
            and value > score[y + 1, x] and value > score[y + 1, x + 1]
        )  # fmt: skip
    kept = np.flatnonzero(keep)
    out_x, out_y = xs[kept], ys[kept]
    out_score = np.empty(len(kept), dtype=np.int64)
    for j in range(len(kept)):
        out_score[j] = score[out_y[j], out_x[j]]
    return out_x, out_y, out_score


@numba.njit(cache=True, nogil=True)
def _grown(values: np.ndarray, capacity: int) -> np.ndarray:
    grown = np.empty(capacity, dtype=values.dtype)
    grown[: len(values)] = values
    return grown


@numba.njit(cache=True, nogil=True)
def harris_response(image: np.ndarray, xs: np.ndarray, ys: np.ndarray) -> np.ndarray:
    """Harris response of each (x, y): Sobel gradients over the 7 x 7 block centred on it.

    The block and its gradients reach 4 pixels from the point: callers keep points that far
    inside the image (FAST's border does).
    """
    radius = HARRIS_BLOCK // 2
    scale4 = _HARRIS_SCALE**4
    response = np.empty(len(xs), dtype=np.float64)
    for k in range(len(xs)):
        sxx = np.int64(0)
        syy = np.int64(0)
        sxy = np.int64(0)
        for y in range(ys[k] - radius, ys[k] + radius + 1):
            for x in range(xs[k] - radius, xs[k] + radius + 1):
                up_left = np.int64(image[y - 1, x - 1])
                up = np.int64(image[y - 1, x])
                up_right = np.int64(image[y - 1, x + 1])
                left = np.int64(image[y, x - 1])
                right = np.int64(image[y, x + 1])
                down_left = np.int64(image[y + 1, x - 1])
                down = np.int64(image[y + 1, x])
                down_right = np.int64(image[y + 1, x + 1])
                gx = 2 * (right - left) + (up_right - up_left) + (down_right - down_left)
                gy = 2 * (down - up) + (down_left - up_left) + (down_right - up_right)
                sxx += gx * gx
                syy += gy * gy
                sxy += gx * gy
        a, b, c = float(sxx), float(syy), float(sxy)
        response[k] = (a * b - c * c - HARRIS_K * (a + b) * (a + b)) * scale4
    return response
