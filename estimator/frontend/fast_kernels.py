"""FAST-9 corners and their Harris score as compiled kernels with array output.

The compiled detector (compiled_orb.py: ORB on one pyramid level, and ``fast-brief``) finds the
corners OpenCV's ORB finds, but returns arrays instead of one Python object per corner: on a
752 x 480 EuRoC image the objects of ~2 000 candidates cost about as much as finding them
(docs/performance.md).

FAST-9: a pixel p is a corner when 9 contiguous pixels of the 16 on the radius-3 Bresenham
circle are all brighter than p + t or all darker than p - t. Its score is the largest t for
which it still is (the best 9-arc's smallest difference, minus one), so it does not depend on
the threshold; a corner survives the non-maximum suppression when its score beats all 8
neighbours' (a neighbour that is no corner scores 0). Harris: R = det(M) - k tr(M)^2 with M the
sums of the Sobel gradient products over a 7 x 7 block around the corner.
"""

from __future__ import annotations

import threading

import numpy as np

from estimator.compiled import kernel

__all__ = [
    "CIRCLE",
    "HARRIS_BLOCK",
    "HARRIS_K",
    "check_inside",
    "fast_corners",
    "harris_response",
]

# The radius-3 circle, in order around it: (dx, dy) of its 16 pixels.
CIRCLE = np.array(
    [(0, 3), (1, 3), (2, 2), (3, 1), (3, 0), (3, -1), (2, -2), (1, -3),
     (0, -3), (-1, -3), (-2, -2), (-3, -1), (-3, 0), (-3, 1), (-2, 2), (-1, 3)],
    dtype=np.int64,
)  # fmt: skip
HARRIS_BLOCK = 7
HARRIS_K = 0.04
# Gradients are scaled to [-1, 1] per unit step (Sobel weights sum 4, over 255 grey levels)
# and averaged over the block, so responses are comparable between images. The response is
# formed in float32, operation for operation as OpenCV's ORB forms it, so that both rank the
# corners alike to the last bit (ties at ORB's cut included).
_HARRIS_K32 = np.float32(HARRIS_K)
_HARRIS_SCALE32 = np.float32(1.0) / (np.float32(4 * HARRIS_BLOCK) * np.float32(255.0))
_HARRIS_SCALE4 = _HARRIS_SCALE32 * _HARRIS_SCALE32 * _HARRIS_SCALE32 * _HARRIS_SCALE32


@kernel()
def _ring_masks(
    image: np.ndarray, y: int, low_x: int, threshold: np.uint8,
    above: np.ndarray, below: np.ndarray, high: np.ndarray, low: np.ndarray,
) -> None:
    """Bit i of above[k] / below[k]: circle pixel i of (low_x + k, y) is brighter / darker
    than the centre by more than ``threshold``; then each mask is replaced by its 9-arcs
    (non-zero: a corner).

    Loops over row slices with non-negative indices only, in 8 and 16 bits: numba compiles
    them to SIMD (signed offsets into the image would add a wrap-around branch per access).
    The bounds saturate at 255 and 0, where no grey value can pass them anyway.
    """
    n = len(above)
    centre = image[y, low_x : low_x + n]
    top = np.uint8(255 - threshold)
    for k in range(n):
        value = centre[k]
        high[k] = value + threshold if value < top else np.uint8(255)
        low[k] = value - threshold if value > threshold else np.uint8(0)
        above[k] = 0
        below[k] = 0
    for i in range(16):
        bit = np.uint16(1 << i)
        none = np.uint16(0)
        ring = image[y + CIRCLE[i, 1], low_x + CIRCLE[i, 0] : low_x + CIRCLE[i, 0] + n]
        for k in range(n):
            value = ring[k]
            above[k] |= bit if value > high[k] else none
            below[k] |= bit if value < low[k] else none
    for k in range(n):
        above[k] = _arcs(np.uint32(above[k]))
        below[k] = _arcs(np.uint32(below[k]))


@kernel(inline="always")
def _arcs(bits: np.uint32) -> np.uint32:
    """Non-zero when a 16-bit ring mask has 9 contiguous set bits (wrapping around)."""
    ring = bits | (bits << np.uint32(16))
    run = ring & (ring >> np.uint32(1))  # runs of 2
    run = run & (run >> np.uint32(2))  # 4
    run = run & (run >> np.uint32(4))  # 8
    run = run & (ring >> np.uint32(8))  # 9
    return run & np.uint32(0xFFFF)


@kernel()
def _scores(image: np.ndarray, xs: np.ndarray, ys: np.ndarray, sign: np.ndarray) -> np.ndarray:
    """FAST scores of corners (``sign`` +1 for a bright arc, -1 for a dark one): the best
    9-arc's smallest difference, minus one.

    Row i of ``diff`` holds circle pixel i's difference for every corner (and rows 16-23
    the first 8 again); the sliding minimum over 9 is built from pairs, then runs of 4 and 8,
    each a loop over all corners (long loops: SIMD).
    """
    count = len(xs)
    width = image.shape[1]
    flat = image.ravel()
    # Unsigned flat indices from 4 rows above the corner: no wrap-around test per access.
    above = 4 * width
    offsets = np.empty(16, dtype=np.uint64)
    for i in range(16):
        offsets[i] = np.uint64(CIRCLE[i, 1] * width + CIRCLE[i, 0] + above)
    diff = np.empty((24, count), dtype=np.int16)
    for j in range(count):
        base = np.uint64(ys[j] * width + xs[j] - above)
        centre = np.int16(flat[base + np.uint64(above)])
        for i in range(16):
            diff[i, j] = sign[j] * (np.int16(flat[base + offsets[i]]) - centre)
    for i in range(16, 24):
        diff[i] = diff[i - 16]
    pair = np.empty((23, count), dtype=np.int16)
    for i in range(23):
        a, b, p = diff[i], diff[i + 1], pair[i]
        for j in range(count):
            p[j] = min(a[j], b[j])
    best = np.full(count, -32768, dtype=np.int16)
    for i in range(16):
        a, b, c, d, e = pair[i], pair[i + 2], pair[i + 4], pair[i + 6], diff[i + 8]
        for j in range(count):
            best[j] = max(best[j], min(min(min(a[j], b[j]), min(c[j], d[j])), e[j]))
    return best - np.int16(1)


@kernel()
def _raw_corners(
    image: np.ndarray, threshold: int, border: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """x, y (raster order) and arc sign of every FAST corner with at least ``border`` - 1
    pixels to the image's edge, before the suppression."""
    height, width = image.shape
    low_y, high_y = max(border - 1, 3), min(height - border + 1, height - 3)
    low_x, high_x = max(border - 1, 3), min(width - border + 1, width - 3)
    n = max(high_x - low_x, 0)
    above = np.empty(n, dtype=np.uint16)
    below = np.empty(n, dtype=np.uint16)
    high = np.empty(n, dtype=np.uint8)
    low = np.empty(n, dtype=np.uint8)
    index = np.empty(n + 1, dtype=np.int64)
    xs = np.empty(4096, dtype=np.int64)
    ys = np.empty(4096, dtype=np.int64)
    sign = np.empty(4096, dtype=np.int16)
    count = 0
    for y in range(low_y, high_y):
        _ring_masks(image, y, low_x, np.uint8(threshold), above, below, high, low)
        m = 0
        for k in range(n):  # branch-free compaction of the row's corners
            index[m] = k
            m += (above[k] | below[k]) != 0
        if count + m > len(xs):
            size = 2 * (count + m)
            xs, ys, sign = _grown(xs, size), _grown(ys, size), _grown(sign, size)
        for j in range(m):
            k = index[j]
            xs[count + j] = low_x + k
            ys[count + j] = y
            sign[count + j] = 1 if above[k] != 0 else -1
        count += m
    return xs[:count], ys[:count], sign[:count]


def fast_corners(
    image: np.ndarray, threshold: int, border: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """FAST-9 corners at least ``border`` pixels inside the image, after 3 x 3 suppression.

    Returns (x, y, score) int64 arrays in raster order. A pixel at exactly ``border`` counts as
    inside, one at ``size - border`` does not. ``image``: 8-bit grey, ``border`` >= 3 (the
    circle's radius), ``threshold`` in 1..254.
    """
    if image.dtype != np.uint8 or image.ndim != 2:
        raise ValueError(f"FAST needs an 8-bit grey image, got {image.dtype} {image.shape}")
    if not 1 <= threshold <= 254 or border < 3:
        raise ValueError(
            f"FAST threshold must be in 1..254 and border >= 3, got {threshold}, {border}"
        )
    scratch = getattr(_SCRATCH, "scores", None)
    if scratch is None or scratch.shape != image.shape:
        scratch = _SCRATCH.scores = np.zeros(image.shape, dtype=np.int16)
    return _fast_corners(np.ascontiguousarray(image), threshold, border, scratch)


# Per thread: int16 zeros of the last image's shape for the suppression's scores, zeroed again
# after each use (a fresh array per image costs its page faults, ~0.2 ms on 752 x 480).
_SCRATCH = threading.local()


@kernel("uint8[:, ::1], int64, int64, int16[:, ::1]")
def _fast_corners(
    image: np.ndarray, threshold: int, border: int, scratch: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    height, width = image.shape
    xs, ys, sign = _raw_corners(image, threshold, border)
    scores = _scores(image, xs, ys, sign)
    for j in range(len(xs)):
        scratch[ys[j], xs[j]] = scores[j]
    keep = np.empty(len(xs), dtype=np.bool_)
    for j in range(len(xs)):
        x, y, value = xs[j], ys[j], scores[j]
        keep[j] = (
            border <= x < width - border and border <= y < height - border
            and value > scratch[y - 1, x - 1] and value > scratch[y - 1, x]
            and value > scratch[y - 1, x + 1] and value > scratch[y, x - 1]
            and value > scratch[y, x + 1] and value > scratch[y + 1, x - 1]
            and value > scratch[y + 1, x] and value > scratch[y + 1, x + 1]
        )  # fmt: skip
    for j in range(len(xs)):
        scratch[ys[j], xs[j]] = 0
    kept = np.flatnonzero(keep)
    return xs[kept], ys[kept], scores[kept].astype(np.int64)


@kernel()
def _grown(values: np.ndarray, capacity: int) -> np.ndarray:
    grown = np.empty(capacity, dtype=values.dtype)
    grown[: len(values)] = values
    return grown


def harris_response(image: np.ndarray, xs: np.ndarray, ys: np.ndarray) -> np.ndarray:
    """Harris response of each (x, y): Sobel gradients over the 7 x 7 block centred on it.
    Points must keep 4 px to the image's edge (FAST's border does)."""
    check_inside(xs, ys, image.shape, HARRIS_BLOCK // 2 + 1)
    return _harris_response(image, xs, ys)


def check_inside(xs: np.ndarray, ys: np.ndarray, shape: tuple, margin: int) -> None:
    """The compiled kernels read around each point without bounds checks: refuse points
    closer than ``margin`` to the image's edge."""
    if len(xs) == 0:
        return
    height, width = shape[:2]
    if (
        min(xs.min(), ys.min()) < margin
        or xs.max() >= width - margin
        or ys.max() >= height - margin
    ):
        raise ValueError(
            f"points must keep {margin} px inside the edge of a {width} x {height} image"
        )


@kernel("uint8[:, ::1], int64[::1], int64[::1]")
def _harris_response(image: np.ndarray, xs: np.ndarray, ys: np.ndarray) -> np.ndarray:
    """The block and its gradients reach 4 pixels from the point: no bounds checks here."""
    radius = HARRIS_BLOCK // 2
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
        a, b, c = np.float32(sxx), np.float32(syy), np.float32(sxy)
        trace = a + b
        response[k] = (a * b - c * c - _HARRIS_K32 * trace * trace) * _HARRIS_SCALE4
    return response
