"""Keypoints of an image, their spread over it, and descriptor matching between candidate pairs.

Registration is only as good as the geometry of its points: corners bunched in one textured
corner give a poorly conditioned rotation. Detection (detection.py) therefore over-samples and
then keeps the strongest corners cell by cell (``grid_select``), round-robin over the cells, up
to a budget.

Matching works on *candidate pairs* that the caller has already restricted geometrically (the
same row band for stereo, a search radius in time), so the descriptor distances computed are
only the plausible ones and the ratio / mutual checks happen within those candidates.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from estimator.compiled import kernel
from estimator.frontend.match_kernels import as_words

__all__ = [
    "Features",
    "MatchSet",
    "descriptor_distances",
    "empty_features",
    "grid_select",
    "match_candidates",
    "strongest_first",
]


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


def empty_features(binary: bool) -> Features:
    """No keypoints, with the descriptor width and type of the detector."""
    width = 32 if binary else 128
    dtype = np.uint8 if binary else np.float32
    return Features(np.zeros((0, 2)), np.zeros((0, width), dtype), np.zeros(0), binary)


def strongest_first(points: np.ndarray, response: np.ndarray) -> np.ndarray:
    """Order of the points by decreasing response, equal responses by row, then column: an
    order that does not depend on the detector's implementation and favours no part of the
    image in the matching's tie rules.

    Points already in raster order (the compiled detector's) need only a stable sort by
    response, a quarter of the three-key sort's time."""
    column, row = points[:, 0], points[:, 1]
    row_step = np.diff(row)
    if ((row_step > 0) | ((row_step == 0) & (np.diff(column) > 0))).all():
        return np.argsort(-response, kind="stable")
    return np.lexsort((column, row, -response))


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


@kernel("int64[::1], int64[::1], int64")
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
