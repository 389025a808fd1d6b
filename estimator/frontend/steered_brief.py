"""Intensity-centroid orientation and steered binary descriptors, compiled, for kept corners.

The compiled detectors (compiled_orb.py) describe only the corners their grid keeps, the way
OpenCV's ORB does on one pyramid level and to the bit: each corner gets the angle of its
intensity centroid over ORB's disc of radius ``PATCH_RADIUS`` (the angle of (m10, m01), the
first moments about the corner, by OpenCV's polynomial arctangent in degrees), and 256 binary
tests on the Gaussian-smoothed image: bit k is 1 when the smoothed grey value at the first point
of pair k, rotated by the corner's angle and rounded to a pixel, is below the one at the second
point. The descriptor is the 32 bytes of those bits (bit k in byte k // 8 at position k % 8).

Two sets of test pairs: ORB's own (``orb_pattern``, measured on OpenCV's ORB by
orb_pattern.py and checked against its descriptors), and this project's seeded Gaussian pairs
(``seeded_pattern``, the ``fast-brief`` detector). Rotated, a point stays within 15 sqrt(2) <
22 px of the corner, and the smoothing reaches 3 px further: corners need ``DESCRIPTOR_BORDER``
px to the edge.
"""

from __future__ import annotations

import functools
import logging
import math

import cv2
import numpy as np

from estimator.compiled import kernel
from estimator.frontend.fast_kernels import check_inside
from estimator.frontend.orb_pattern import OrbPatternError, measure_orb_pattern

__all__ = [
    "DESCRIPTOR_BORDER",
    "PATCH_RADIUS",
    "PATTERN",
    "describe",
    "orb_pattern",
    "orientation",
    "seeded_pattern",
    "smoothed",
]

_LOG = logging.getLogger(__name__)

PATCH_RADIUS = 15  # the orientation disc and the half size of the test patch (31 x 31)
DESCRIPTOR_BORDER = 25  # 15 sqrt(2) rotated + 3 smoothing, rounded up
PATTERN_SEED = 20261203
BITS = 256
SMOOTHING_KERNEL = 7  # Gaussian, sigma 2: the tests compare smoothed values, not single pixels
SMOOTHING_SIGMA = 2.0
# OpenCV's fastAtan2: an odd polynomial in min/max of |y|, |x|, in degrees, all in float32.
_DEGREES = np.float32(180.0 / math.pi)
_ATAN_1 = np.float32(0.9997878412794807) * _DEGREES
_ATAN_3 = np.float32(-0.3258083974640975) * _DEGREES
_ATAN_5 = np.float32(0.1555786518463281) * _DEGREES
_ATAN_7 = np.float32(-0.04432655554792128) * _DEGREES
_ATAN_EPS = np.float32(np.finfo(np.float64).eps)
_F90, _F180, _F360 = np.float32(90.0), np.float32(180.0), np.float32(360.0)
_RADIANS = np.float32(math.pi / 180.0)


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
    """ORB's disc: half width of each row 0..radius, rounded, then made symmetric about the
    diagonal (the rows past it take the columns' widths)."""
    diagonal = math.ceil(radius * math.sqrt(2.0) / 2)
    widths = [int(np.rint(math.sqrt(radius * radius - v * v))) for v in range(radius + 1)]
    column = 0
    for v in range(radius, diagonal - 1, -1):
        while widths[column] == widths[column + 1]:
            column += 1
        widths[v] = column
        column += 1
    return np.array(widths, dtype=np.int64)


_HALF_WIDTHS = _disc_half_widths(PATCH_RADIUS)


def smoothed(image: np.ndarray) -> np.ndarray:
    """The image the binary tests read: Gaussian-smoothed against pixel noise (the separable
    floating-point filter, as ORB's, not GaussianBlur's fixed-point one: they differ by a grey
    level here and there, and so would the bits)."""
    kernel = _gaussian_kernel()
    return cv2.sepFilter2D(image, -1, kernel, kernel, borderType=cv2.BORDER_REFLECT_101)


@functools.cache
def _gaussian_kernel() -> np.ndarray:
    return cv2.getGaussianKernel(SMOOTHING_KERNEL, SMOOTHING_SIGMA)


def orientation(image: np.ndarray, xs: np.ndarray, ys: np.ndarray) -> np.ndarray:
    """Angle (float32 degrees in [0, 360)) of each corner's intensity centroid, from the raw
    (unsmoothed) image."""
    check_inside(xs, ys, image.shape, PATCH_RADIUS)
    return _orientation(image, xs, ys, _HALF_WIDTHS)


def describe(
    smooth: np.ndarray,
    xs: np.ndarray,
    ys: np.ndarray,
    angle: np.ndarray,
    pattern: np.ndarray = PATTERN,
) -> np.ndarray:
    """(N, 32) uint8 descriptors of the corners (x, y), the tests rotated by ``angle``
    (degrees, as ``orientation`` gives them)."""
    check_inside(xs, ys, smooth.shape, DESCRIPTOR_BORDER)
    if not smooth.flags.c_contiguous:
        smooth = np.ascontiguousarray(smooth)
    # Both points of every test in one row each (first points, then second points).
    test_x = np.ascontiguousarray(pattern[:, [0, 2]].T.ravel(), dtype=np.float32)
    test_y = np.ascontiguousarray(pattern[:, [1, 3]].T.ravel(), dtype=np.float32)
    angle = np.asarray(angle, dtype=np.float32)
    return _describe(smooth.ravel(), smooth.shape[1], xs, ys, angle, test_x, test_y)


@functools.cache
def orb_pattern() -> np.ndarray | None:
    """ORB's test pairs, or None when this OpenCV's ORB cannot be reproduced (the detector
    then runs OpenCV's ORB itself).

    Measured once per process (orb_pattern.py, ~20 ms) and accepted only when the compiled
    orientation and descriptors equal ORB's on a texture's corners.
    """
    try:
        pattern = measure_orb_pattern()
    except OrbPatternError as error:
        _LOG.warning("compiled ORB unavailable, using OpenCV's: %s", error)
        return None
    rng = np.random.default_rng(0)
    coarse = rng.integers(0, 256, size=(40, 60)).astype(np.uint8)
    image = cv2.GaussianBlur(cv2.resize(coarse, (240, 160), interpolation=cv2.INTER_NEAREST),
                             (0, 0), 1.5)  # fmt: skip
    orb = cv2.ORB_create(nfeatures=300, nlevels=1)
    keypoints, expected = orb.detectAndCompute(image, None)
    xs = np.array([round(k.pt[0]) for k in keypoints], dtype=np.int64)
    ys = np.array([round(k.pt[1]) for k in keypoints], dtype=np.int64)
    angle = orientation(image, xs, ys)
    same_angle = np.array_equal(angle, np.array([k.angle for k in keypoints], np.float32))
    described = describe(smoothed(image), xs, ys, angle, pattern)
    if len(keypoints) < 50 or not same_angle or not np.array_equal(described, expected):
        _LOG.warning("compiled ORB differs from this OpenCV's ORB; using OpenCV's")
        return None
    return pattern


@kernel()
def _fast_atan2(y: np.float32, x: np.float32) -> np.float32:
    """OpenCV's fastAtan2 (degrees), operation for operation in float32."""
    ax, ay = abs(x), abs(y)
    if ax >= ay:
        c = ay / (ax + _ATAN_EPS)
        c2 = c * c
        a = (((_ATAN_7 * c2 + _ATAN_5) * c2 + _ATAN_3) * c2 + _ATAN_1) * c
    else:
        c = ax / (ay + _ATAN_EPS)
        c2 = c * c
        a = _F90 - (((_ATAN_7 * c2 + _ATAN_5) * c2 + _ATAN_3) * c2 + _ATAN_1) * c
    if x < 0:
        a = _F180 - a
    if y < 0:
        a = _F360 - a
    return a


@kernel("uint8[:, ::1], int64[::1], int64[::1], int64[::1]")
def _orientation(
    image: np.ndarray, xs: np.ndarray, ys: np.ndarray, half_widths: np.ndarray
) -> np.ndarray:
    """Rows v and -v of the disc are summed together (the same columns): m10 takes their sum,
    m01 their difference; integer sums, so the result does not depend on the order."""
    radius = len(half_widths) - 1
    angle = np.empty(len(xs), dtype=np.float32)
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
        angle[k] = _fast_atan2(np.float32(m01), np.float32(m10))
    return angle


@kernel("uint8[::1], int64, int64[::1], int64[::1], float32[::1], float32[::1], float32[::1]")
def _describe(
    flat: np.ndarray,
    width: int,
    xs: np.ndarray,
    ys: np.ndarray,
    angle: np.ndarray,
    test_x: np.ndarray,
    test_y: np.ndarray,
) -> np.ndarray:
    """Each corner's test points rotated in float32 and rounded half to even, as ORB does.

    Offsets, values, comparisons and packing run as separate passes over the tests: each is a
    simple loop the compiler vectorises (about twice as fast as one loop per bit).
    """
    points = len(test_x)
    bits = points // 2
    descriptors = np.empty((len(xs), bits // 8), dtype=np.uint8)
    offset = np.empty(points, dtype=np.int32)
    value = np.empty(points, dtype=np.uint8)
    less = np.empty(bits, dtype=np.uint8)
    stride = np.int32(width)
    for k in range(len(xs)):
        theta = angle[k] * _RADIANS
        cos = np.float32(math.cos(np.float64(theta)))
        sin = np.float32(math.sin(np.float64(theta)))
        for i in range(points):
            column = np.rint(test_x[i] * cos - test_y[i] * sin)
            row = np.rint(test_x[i] * sin + test_y[i] * cos)
            offset[i] = np.int32(row) * stride + np.int32(column)
        base = ys[k] * width + xs[k]
        for i in range(points):
            value[i] = flat[base + offset[i]]
        for i in range(bits):
            less[i] = value[i] < value[bits + i]
        for byte in range(bits // 8):
            j = 8 * byte
            descriptors[k, byte] = (
                less[j] | (less[j + 1] << 1) | (less[j + 2] << 2) | (less[j + 3] << 3)
                | (less[j + 4] << 4) | (less[j + 5] << 5) | (less[j + 6] << 6) | (less[j + 7] << 7)
            )  # fmt: skip
    return descriptors
