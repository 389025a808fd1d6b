"""Compiled inner loops of binary descriptor matching.

Stereo matching compares each left descriptor with the right descriptors of its row band:
about 3000 candidate pairs per frame. Expanding them into index arrays, computing their
Hamming distances and reducing them per point with NumPy costs a dozen array passes and
temporaries per frame; one compiled pass over the bands does the same work with the same
results (:func:`band_matches` equals ``row_band_pairs`` + ``descriptor_distances`` +
``match_candidates``, tie-breaking included; tests/test_detection_equivalence.py).
"""

from __future__ import annotations

import numpy as np

from estimator.compiled import kernel

__all__ = ["as_words", "band_matches", "hamming", "window_matches", "zero_mean_sad"]


def as_words(descriptors: np.ndarray) -> np.ndarray:
    """Binary descriptors viewed as 64-bit words (padded with zero bytes when needed)."""
    descriptors = np.ascontiguousarray(descriptors, dtype=np.uint8)
    width = descriptors.shape[1]
    if width % 8:
        descriptors = np.pad(descriptors, ((0, 0), (0, 8 - width % 8)))
    return descriptors.view(np.uint64)


@kernel(inline="always")
def _popcount(word: np.uint64) -> np.int64:
    """Set bits of a 64-bit word (SWAR; compiles to the popcount instruction)."""
    word = word - ((word >> np.uint64(1)) & np.uint64(0x5555555555555555))
    word = (word & np.uint64(0x3333333333333333)) + (
        (word >> np.uint64(2)) & np.uint64(0x3333333333333333)
    )
    word = (word + (word >> np.uint64(4))) & np.uint64(0x0F0F0F0F0F0F0F0F)
    return np.int64((word * np.uint64(0x0101010101010101)) >> np.uint64(56))


@kernel()
def hamming(a: np.ndarray, b: np.ndarray) -> np.int64:
    """Hamming distance of two descriptors given as 64-bit words."""
    total = np.int64(0)
    for word in range(a.shape[0]):
        total += _popcount(a[word] ^ b[word])
    return total


@kernel(
    "float64[::1], float64[::1], uint64[:, ::1], uint64[:, ::1], int64[::1], int64[::1], "
    "int64[::1], UniTuple(float64, 2), float64, float64",
)
def band_matches(
    left_x: np.ndarray,
    right_x: np.ndarray,
    left_words: np.ndarray,
    right_words: np.ndarray,
    order: np.ndarray,
    low: np.ndarray,
    high: np.ndarray,
    disparity_range: tuple[float, float],
    ratio: float,
    max_distance: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Mutual, ratio-tested nearest right partner of each left point within its row band.

    Right points ``order[low[i]:high[i]]`` (sorted by row) are left point i's band; a pair
    is a candidate when its disparity lies in ``disparity_range``. A left point takes its
    nearest candidate (the first in band order on ties) if it is within ``max_distance`` and
    below ``ratio`` times the second nearest, and if no left point with a smaller index is
    as near to that right point and none is nearer. Returns (left, right, distance) ordered
    by left.
    """
    tables = _nearest_tables(len(left_x), len(right_x))
    for i in range(len(left_x)):
        for k in range(low[i], high[i]):
            j = order[k]
            disparity = left_x[i] - right_x[j]
            if disparity < disparity_range[0] or disparity > disparity_range[1]:
                continue
            _add_pair(tables, i, j, float(hamming(left_words[i], right_words[j])))
    return _mutual_matches(tables, ratio, max_distance)


@kernel(
    "float64[:, ::1], float64[:, ::1], uint64[:, ::1], uint64[:, ::1], int64[::1], int64[::1], "
    "int64[::1], float64[::1], float64, float64",
)
def window_matches(
    expected: np.ndarray,
    observed: np.ndarray,
    expected_words: np.ndarray,
    observed_words: np.ndarray,
    order: np.ndarray,
    low: np.ndarray,
    high: np.ndarray,
    radii: np.ndarray,
    ratio: float,
    max_distance: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`band_matches` with round windows: observed points within ``radii[i]`` pixels of
    expected position i are its candidates (``order[low[i]:high[i]]``: those whose row is
    within ``radii[i]``, sorted by row)."""
    tables = _nearest_tables(len(expected), len(observed))
    for i in range(len(expected)):
        squared_radius = radii[i] * radii[i]
        for k in range(low[i], high[i]):
            j = order[k]
            dx = observed[j, 0] - expected[i, 0]
            dy = observed[j, 1] - expected[i, 1]
            if dx * dx + dy * dy > squared_radius:
                continue
            _add_pair(tables, i, j, float(hamming(expected_words[i], observed_words[j])))
    return _mutual_matches(tables, ratio, max_distance)


@kernel()
def _nearest_tables(
    count_a: int, count_b: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Running nearest partner, nearest and second-nearest distance of each ``a``; nearest
    distance and nearest ``a`` of each ``b``."""
    return (
        np.full(count_a, -1, dtype=np.int64),
        np.full(count_a, np.inf),
        np.full(count_a, np.inf),
        np.full(count_b, np.inf),
        np.full(count_b, -1, dtype=np.int64),
    )


@kernel(inline="always")
def _add_pair(tables: tuple, i: int, j: int, distance: float) -> None:
    """Fold candidate pair (i, j) in; ties keep the pair seen first."""
    partner, best, second, owner_distance, owner = tables
    if distance < best[i]:
        second[i] = best[i]
        best[i] = distance
        partner[i] = j
    elif distance < second[i]:
        second[i] = distance
    if distance < owner_distance[j]:
        owner_distance[j] = distance
        owner[j] = i


@kernel()
def _mutual_matches(
    tables: tuple,
    ratio: float,
    max_distance: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Pairs (a, its nearest b) that pass the distance and ratio tests and that b agrees on."""
    partner, best, second, _, owner = tables
    keep = np.zeros(len(best), dtype=np.bool_)
    for i in range(len(best)):
        j = partner[i]
        if j < 0 or best[i] > max_distance or not best[i] < ratio * second[i]:
            continue
        keep[i] = owner[j] == i
    a = np.flatnonzero(keep)
    return a, partner[a], best[a]


@kernel("uint8[:, ::1], uint8[:, ::1], int64[::1], int64[::1], int64[::1], int64, int64[::1]")
def zero_mean_sad(
    left_image: np.ndarray,
    right_image: np.ndarray,
    u: np.ndarray,
    v: np.ndarray,
    right_u: np.ndarray,
    half: int,
    shifts: np.ndarray,
) -> np.ndarray:
    """(N, S) zero-mean SAD between the left patch at (u, v) and the right patches at
    (right_u + shift, v) for consecutive ``shifts``, each patch ``2 half + 1`` square, means
    rounded down to integers."""
    size = 2 * half + 1
    area = size * size
    span = size + len(shifts) - 1
    costs = np.empty((len(u), len(shifts)))
    patch = np.empty((size, size), dtype=np.int32)
    strip = np.empty((size, span), dtype=np.int32)
    column_sums = np.empty(span, dtype=np.int32)
    for index in range(len(u)):
        top, x_left = v[index] - half, u[index] - half
        x_right = right_u[index] + shifts[0] - half
        left_sum = np.int32(0)
        column_sums[:] = 0
        for row in range(size):
            left_row = left_image[top + row]
            right_row = right_image[top + row]
            for col in range(size):
                patch[row, col] = left_row[x_left + col]
                left_sum += patch[row, col]
            for col in range(span):
                strip[row, col] = right_row[x_right + col]
                column_sums[col] += strip[row, col]
        left_mean = left_sum // area
        for k in range(len(shifts)):
            right_sum = np.int32(0)
            for col in range(size):
                right_sum += column_sums[k + col]
            offset = right_sum // area - left_mean
            cost = np.int32(0)
            for row in range(size):
                for col in range(size):
                    cost += abs(strip[row, k + col] - patch[row, col] - offset)
            costs[index, k] = cost
    return costs
