"""ORB's corner scoring and orientation, computed only where they are needed.

``cv2.ORB.detect`` on one pyramid level runs FAST, scores every FAST corner with a 7x7 Harris
response, keeps the best ``nfeatures`` and computes the intensity-centroid orientation of all of
them. The front end then keeps only ``max_features`` of those (grid bucketing), so half of the
orientations are thrown away, and the keypoints make a round trip through Python objects twice.
Here FAST is still OpenCV's, the Harris response and the orientation are the same integer sums
and float32 formulas as OpenCV's (compiled), and the orientation is computed only for the corners
the grid keeps. Corners, responses, angles and therefore descriptors equal ORB's; only the order
of the corners differs (ORB's partial sort leaves them in an unspecified order, here they stay
in FAST's raster order).
"""

from __future__ import annotations

import math

import cv2
import numba
import numpy as np

__all__ = ["harris_responses", "orb_corners", "orientations", "patch_row_extents"]

_HARRIS_BLOCK = 7  # OpenCV's ORB: HARRIS_BLOCK_SIZE
_HARRIS_K = np.float32(0.04)  # OpenCV's ORB: HARRIS_K


def patch_row_extents(half_patch: int) -> np.ndarray:
    """Half-width of each row of ORB's circular orientation patch (OpenCV's ``umax``)."""
    extents = np.zeros(half_patch + 2, dtype=np.int64)
    vmax = math.floor(half_patch * math.sqrt(2.0) / 2 + 1)
    vmin = math.ceil(half_patch * math.sqrt(2.0) / 2)
    for v in range(vmax + 1):
        extents[v] = round(math.sqrt(half_patch * half_patch - v * v))
    v0 = 0
    for v in range(half_patch, vmin - 1, -1):  # mirror the first octant: a symmetric circle
        while extents[v0] == extents[v0 + 1]:
            v0 += 1
        extents[v] = v0
        v0 += 1
    return extents


@numba.njit(cache=True, nogil=True)
def harris_responses(image: np.ndarray, xs: np.ndarray, ys: np.ndarray) -> np.ndarray:
    """OpenCV ORB's Harris score (7x7 block, k = 0.04) at integer pixels, bit for bit."""
    radius = _HARRIS_BLOCK // 2
    scale = np.float32(1.0) / (np.float32(4 * _HARRIS_BLOCK) * np.float32(255.0))
    scale4 = scale * scale * scale * scale
    out = np.empty(len(xs), dtype=np.float32)
    for index in range(len(xs)):
        a = 0
        b = 0
        c = 0
        for y in range(ys[index] - radius, ys[index] + radius + 1):
            up, row, down = image[y - 1], image[y], image[y + 1]
            for x in range(xs[index] - radius, xs[index] + radius + 1):
                ix = (
                    (np.int64(row[x + 1]) - np.int64(row[x - 1])) * 2
                    + (np.int64(up[x + 1]) - np.int64(up[x - 1]))
                    + (np.int64(down[x + 1]) - np.int64(down[x - 1]))
                )
                iy = (
                    (np.int64(down[x]) - np.int64(up[x])) * 2
                    + (np.int64(down[x - 1]) - np.int64(up[x - 1]))
                    + (np.int64(down[x + 1]) - np.int64(up[x + 1]))
                )
                a += ix * ix
                b += iy * iy
                c += ix * iy
        fa, fb, fc = np.float32(a), np.float32(b), np.float32(c)
        trace = fa + fb
        out[index] = (fa * fb - fc * fc - _HARRIS_K * trace * trace) * scale4
    return out


@numba.njit(cache=True, nogil=True)
def _centroid_moments(
    image: np.ndarray, xs: np.ndarray, ys: np.ndarray, extents: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """First moments (m10, m01) of the circular patch around each pixel (OpenCV's ICAngles)."""
    half = len(extents) - 2
    m10 = np.empty(len(xs), dtype=np.float32)
    m01 = np.empty(len(xs), dtype=np.float32)
    for index in range(len(xs)):
        x0, y0 = xs[index], ys[index]
        sum10 = np.int32(0)
        sum01 = np.int32(0)
        centre = image[y0, x0 - half : x0 + half + 1]
        for u in range(2 * half + 1):
            sum10 += np.int32(u - half) * np.int32(centre[u])
        for v in range(1, half + 1):
            width = extents[v]
            below = image[y0 + v, x0 - width : x0 + width + 1]
            above = image[y0 - v, x0 - width : x0 + width + 1]
            v_sum = np.int32(0)
            for u in range(2 * width + 1):
                plus, minus = np.int32(below[u]), np.int32(above[u])
                v_sum += plus - minus
                sum10 += np.int32(u - width) * (plus + minus)
            sum01 += np.int32(v) * v_sum
        m10[index] = sum10
        m01[index] = sum01
    return m10, m01


def orientations(
    image: np.ndarray, xs: np.ndarray, ys: np.ndarray, extents: np.ndarray
) -> np.ndarray:
    """ORB's keypoint angles in degrees [0, 360): intensity centroid, OpenCV's fast atan2."""
    m10, m01 = _centroid_moments(image, xs, ys, extents)
    return cv2.phase(m10, m01, angleInDegrees=True).ravel()


def _retain_best(response: np.ndarray, count: int) -> np.ndarray:
    """Mask of OpenCV's ``retainBest``: the ``count`` strongest plus ties with the weakest kept."""
    if len(response) <= count:
        return np.ones(len(response), dtype=bool)
    threshold = np.partition(response, len(response) - count)[len(response) - count]
    return response >= threshold


def orb_corners(
    image: np.ndarray,
    fast: cv2.FastFeatureDetector,
    candidates: int,
    border: int,
) -> tuple[list, np.ndarray, np.ndarray, np.ndarray]:
    """ORB's one-level corners without orientation.

    FAST corners closer than ``border`` to the edge are dropped, at most ``2 * candidates`` by
    FAST score get a Harris score and the ``candidates`` best by Harris score are kept, as
    ``cv2.ORB`` does on one level. Returns all FAST keypoints, the index of the kept ones
    among them, their (N, 2) positions and their Harris responses.
    """
    keypoints = fast.detect(image, None)
    if not keypoints:
        return [], np.zeros(0, dtype=np.intp), np.zeros((0, 2)), np.zeros(0)
    points = cv2.KeyPoint_convert(keypoints)
    height, width = image.shape[:2]
    inside = (
        (points[:, 0] >= border) & (points[:, 0] < width - border)
        & (points[:, 1] >= border) & (points[:, 1] < height - border)
    )  # fmt: skip
    if len(points) > 2 * candidates:
        score = np.fromiter((k.response for k in keypoints), np.float32, len(keypoints))
        index = np.flatnonzero(inside)
        inside[index[~_retain_best(score[index], 2 * candidates)]] = False
    index = np.flatnonzero(inside)
    pixels = np.rint(points[index]).astype(np.int64)
    response = harris_responses(image, pixels[:, 0], pixels[:, 1])
    best = _retain_best(response, candidates)
    index = index[best]
    return keypoints, index, points[index].astype(float), response[best].astype(float)
