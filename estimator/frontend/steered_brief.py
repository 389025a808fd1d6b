"""Intensity-centroid orientation and steered binary descriptors, compiled, for kept corners.

The ``fast-brief`` detector (features.py) describes only the corners its grid keeps. Each gets
an orientation from the intensity centroid of the disc of radius ``PATCH_RADIUS`` around it
(the angle of (m10, m01), the first moments about the corner), and 256 binary tests on the
Gaussian-smoothed image: bit k is 1 when the smoothed grey value at the first point of pair k,
rotated by the corner's angle, is below the one at the second point. The descriptor is the 32
bytes of those bits (bit k in byte k // 8 at position k % 8), the same format as ORB's, so the
Hamming matching further on is unchanged.

The test pairs are this project's own, drawn once from a seeded generator: both points of a pair
isotropic Gaussian around the corner with sigma = patch / 5 (the sampling the BRIEF authors found
best), inside the 31 x 31 patch. Rotated, a point stays within 15 sqrt(2) < 22 px of the corner,
and the smoothing reaches 3 px further: corners need ``DESCRIPTOR_BORDER`` px to the edge.
"""

from __future__ import annotations

import functools

import cv2
import numba
import numpy as np

__all__ = [
    "DESCRIPTOR_BORDER",
    "PATCH_RADIUS",
    "PATTERN",
    "check_inside",
    "describe",
    "orientation",
    "seeded_pattern",
    "smoothed",
]

PATCH_RADIUS = 15  # the orientation disc and the half size of the test patch (31 x 31)
DESCRIPTOR_BORDER = 25  # 15 sqrt(2) rotated + 3 smoothing, rounded up
PATTERN_SEED = 20261203
BITS = 256
SMOOTHING_KERNEL = 7  # Gaussian, sigma 2: the tests compare smoothed values, not single pixels
SMOOTHING_SIGMA = 2.0
# The tests are rotated by the corner's angle rounded to one of these steps (1.4 deg: a test
# point at most 0.26 px from its exactly rotated place before rounding to a pixel), from
# tables of pixel offsets made once per image width.
ANGLE_STEPS = 256


def seeded_pattern(seed: int = PATTERN_SEED, bits: int = BITS) -> np.ndarray:
    """(bits, 4) int32 rows (x1, y1, x2, y2): the point pairs of the binary tests.

    Gaussian points (sigma = patch size / 5) rounded to pixels, redrawn outside the patch;
    a pair of one point twice tests nothing and is redrawn too.
    """
    rng = np.random.default_rng(seed)
    sigma = (2 * PATCH_RADIUS + 1) / 5.0
    pairs = np.empty((bits, 4), dtype=np.int32)
    count = 0
    while count < bits:
        draw = np.rint(rng.normal(0.0, sigma, size=4)).astype(np.int32)
        if np.abs(draw).max() > PATCH_RADIUS or (draw[0] == draw[2] and draw[1] == draw[3]):
            continue
        pairs[count] = draw
        count += 1
    return pairs


PATTERN = seeded_pattern()


def _disc_half_widths(radius: int) -> np.ndarray:
    """Half width of the disc's row at each offset 0..radius (pixels with u^2 + v^2 <= r^2)."""
    offsets = np.arange(radius + 1)
    return np.floor(np.sqrt(radius * radius - offsets * offsets)).astype(np.int64)


_HALF_WIDTHS = _disc_half_widths(PATCH_RADIUS)


def smoothed(image: np.ndarray) -> np.ndarray:
    """The image the binary tests read: Gaussian-smoothed against pixel noise."""
    return cv2.GaussianBlur(
        image,
        (SMOOTHING_KERNEL, SMOOTHING_KERNEL),
        SMOOTHING_SIGMA,
        sigmaY=SMOOTHING_SIGMA,
        borderType=cv2.BORDER_REFLECT_101,
    )


def orientation(image: np.ndarray, xs: np.ndarray, ys: np.ndarray) -> np.ndarray:
    """Angle (radians) of each corner's intensity centroid, from the raw (unsmoothed) image."""
    check_inside(xs, ys, image.shape, PATCH_RADIUS)
    return _orientation(image, xs, ys, _HALF_WIDTHS)


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
        raise ValueError(f"points must keep {margin} px to the edge of a {width} x {height} image")


def describe(
    smooth: np.ndarray, xs: np.ndarray, ys: np.ndarray, angle: np.ndarray
) -> np.ndarray:
    """(N, 32) uint8 descriptors of the corners (x, y), the tests rotated by ``angle``."""
    check_inside(xs, ys, smooth.shape, DESCRIPTOR_BORDER)
    if not smooth.flags.c_contiguous:
        smooth = np.ascontiguousarray(smooth)
    first, second = rotated_offsets(smooth.shape[1])
    step = np.rint(np.asarray(angle) * (ANGLE_STEPS / (2 * np.pi))).astype(np.int64) % ANGLE_STEPS
    return _describe(smooth.ravel(), ys * smooth.shape[1] + xs, step, first, second)


@functools.lru_cache(maxsize=4)
def rotated_offsets(width: int) -> tuple[np.ndarray, np.ndarray]:
    """(ANGLE_STEPS, BITS) flat pixel offsets of the first and second test points, the
    pattern rotated by each step's angle and rounded to the nearest pixel."""
    angle = np.arange(ANGLE_STEPS) * (2 * np.pi / ANGLE_STEPS)
    cos, sin = np.cos(angle)[:, None], np.sin(angle)[:, None]
    tables = []
    for x, y in ((PATTERN[:, 0], PATTERN[:, 1]), (PATTERN[:, 2], PATTERN[:, 3])):
        u = np.floor(x * cos - y * sin + 0.5).astype(np.int32)
        v = np.floor(x * sin + y * cos + 0.5).astype(np.int32)
        tables.append(np.ascontiguousarray(v * width + u))
    return tables[0], tables[1]


@numba.njit(cache=True, nogil=True)
def _orientation(
    image: np.ndarray, xs: np.ndarray, ys: np.ndarray, half_widths: np.ndarray
) -> np.ndarray:
    """Rows v and -v of the disc are summed together (the same columns): m10 takes their sum,
    m01 their difference; integer sums, so the result does not depend on the order."""
    radius = len(half_widths) - 1
    angle = np.empty(len(xs), dtype=np.float64)
    for k in range(len(xs)):
        x, y = xs[k], ys[k]
        centre = image[y, x - radius : x + radius + 1]
        m10 = np.int32(0)
        for j in range(2 * radius + 1):
            m10 += np.int32(j - radius) * np.int32(centre[j])
        m01 = np.int32(0)
        for v in range(1, radius + 1):
            half = half_widths[v]
            top = image[y - v, x - half : x + half + 1]
            bottom = image[y + v, x - half : x + half + 1]
            difference = np.int32(0)
            for j in range(2 * half + 1):
                a, b = np.int32(top[j]), np.int32(bottom[j])
                difference += b - a
                m10 += np.int32(j - half) * (a + b)
            m01 += np.int32(v) * difference
        angle[k] = np.arctan2(float(m01), float(m10))
    return angle


@numba.njit(cache=True, nogil=True)
def _describe(
    flat: np.ndarray, centre: np.ndarray, step: np.ndarray, first: np.ndarray, second: np.ndarray
) -> np.ndarray:
    bits = first.shape[1]
    descriptors = np.empty((len(centre), bits // 8), dtype=np.uint8)
    for k in range(len(centre)):
        base = centre[k]
        one, two = first[step[k]], second[step[k]]
        row = descriptors[k]
        for byte in range(bits // 8):
            packed = 0
            for bit in range(8):
                i = 8 * byte + bit
                packed |= np.int64(flat[base + one[i]] < flat[base + two[i]]) << bit
            row[byte] = packed
    return descriptors
