"""The rigidity graph of ``pso-robust``: pairs of pairs that keep their distance, ranked.

A rigid motion preserves distances, so two correct pairs agree on ||p_i - p_j|| and every
pair of pairs gets a weight for that agreement; the leading eigenvector of the weights ranks
the correct pairs first, and a greedy pass takes a small mutually rigid core from the top
(step 1 and 2 of ``pso_support``). The O(M^2) weights are compiled kernels.
"""

from __future__ import annotations

import numpy as np

from estimator.compiled import kernel

__all__ = [
    "graph_sample",
    "precise_ranking",
    "rigid_core",
    "rigidity_scores",
    "rigidity_weights",
    "top_ranked",
]

# Each call of pso-robust runs these on a few hundred pairs: compiled, a step costs
# microseconds, where the equivalent dozen small numpy calls would cost ten times more.
# They are written as scalar loops (no array expressions, matmul or linalg), which keeps
# their one-off compilation (cached on disk) short. error_model="numpy": a division is a
# plain IEEE division, not a ZeroDivisionError check, whose branch would stop the loops
# from vectorising (the scaled rigidity kernel ran 6x slower with it).


def graph_sample(count: int, limit: int, rng: np.random.Generator) -> np.ndarray:
    """All pair indices, or ``limit`` of them drawn at random (sorted) when there are more."""
    if count <= limit:
        return np.arange(count)
    return np.sort(rng.choice(count, limit, replace=False))


def rigid_core(weights: np.ndarray, ranking: np.ndarray, size: int) -> np.ndarray:
    """Top-ranked pairs taken greedily when rigid-consistent with all pairs taken before.

    ``ranking`` is best first (at least its first 4 * size entries). Falls back to the plain
    top of the ranking when no consistent core of 3 exists.
    """
    candidates = ranking[: 4 * size]
    taken = _greedy_core(weights, candidates, size)
    if len(taken) < 3:
        return ranking[:size]
    return candidates[taken]


def precise_ranking(
    scores: np.ndarray, noise: np.ndarray, count: int, share: float = 0.5
) -> np.ndarray:
    """The ``count`` most precise pairs (smallest ``noise``) among the well-ranked ones.

    Well ranked: a score of at least ``share`` of the best score, where the rigid majority
    lies (wrong matches agree only by chance and score far lower). Ordered most precise first,
    so that a greedy core taken from it (``rigid_core``) anchors on the best-measured pairs
    instead of on the most connected ones, which can be one distant patch whose depth error
    the distances between its points barely see.
    """
    if len(scores) == 0:
        return np.empty(0, dtype=np.int64)
    eligible = np.flatnonzero(scores >= share * scores.max())
    order = np.argsort(noise[eligible], kind="stable")[:count]
    return eligible[order].astype(np.int64)


def rigidity_weights(
    source: np.ndarray,
    target: np.ndarray,
    tolerance: float,
    scales: np.ndarray | None = None,
) -> np.ndarray:
    """(N, N) weights max(0, 1 - (||p_i - p_j|| - ||p'_i - p'_j||)^2 / tolerance^2), 0 diagonal.

    With per-pair noise ``scales`` s the tolerance of i, j is tolerance * sqrt((s_i^2 +
    s_j^2) / 2): the distance error has variance sigma_i^2 + sigma_j^2.
    O(N^2) time and memory, independent of the outlier ratio. Compiled, in float32 on
    centred coordinates (distance rounding ~1e-6 relative, far below any useful
    tolerance) so that the inner loop vectorises; numpy would need several (N, N)
    temporaries per step.
    """
    source = np.ascontiguousarray(source, dtype=float)
    target = np.ascontiguousarray(target, dtype=float)
    if scales is None:
        return _rigidity_kernel(source, target, float(tolerance))
    half_squares = np.ascontiguousarray(0.5 * np.asarray(scales) ** 2, dtype=np.float32)
    return _scaled_rigidity_kernel(source, target, float(tolerance), half_squares)


def rigidity_scores(weights: np.ndarray, power_steps: int = 2) -> np.ndarray:
    """Leading-eigenvector approximation of the weight matrix (spectral matching).

    The degree counts consistent partners; each power step also rewards partners that are
    themselves consistent with many, which is what separates a rigid cluster of inliers
    from chance agreements of outliers.
    """
    return _spectral_scores(np.ascontiguousarray(weights, dtype=np.float32), power_steps)


@kernel("float32[:, ::1], int64", fastmath=True, error_model="numpy")
def _spectral_scores(weights: np.ndarray, power_steps: int) -> np.ndarray:
    # Row sums, then power steps scaled to a peak of 1, all in float32 (as the weights).
    count = weights.shape[0]
    scores = np.empty(count, dtype=np.float32)
    if count == 0:
        return scores
    for i in range(count):
        row = weights[i]
        total = np.float32(0.0)
        for j in range(count):
            total += row[j]
        scores[i] = total
    for _ in range(power_steps):
        stepped = np.empty(count, dtype=np.float32)
        for i in range(count):
            row = weights[i]
            total = np.float32(0.0)
            for j in range(count):
                total += row[j] * scores[j]
            stepped[i] = total
        peak = stepped[0]
        for i in range(1, count):
            peak = max(peak, stepped[i])
        if peak <= 0.0:
            return stepped
        for i in range(count):
            stepped[i] /= peak
        scores = stepped
    return scores


@kernel("float32[::1], int64", "float64[::1], int64", error_model="numpy")
def top_ranked(scores: np.ndarray, count: int) -> np.ndarray:
    # Indices of the ``count`` highest scores, highest first, ties by index: the head of a
    # stable descending argsort, by insertion into a short sorted list.
    size = max(min(count, len(scores)), 0)
    top = np.empty(size, dtype=np.int64)
    if size == 0:
        return top
    filled = 0
    for index in range(len(scores)):
        value = scores[index]
        if filled == size and not value > scores[top[size - 1]]:
            continue
        slot = min(filled, size - 1)  # the last slot is dropped when the list is full
        while slot > 0 and value > scores[top[slot - 1]]:
            top[slot] = top[slot - 1]
            slot -= 1
        top[slot] = index
        filled = min(filled + 1, size)
    return top


@kernel("float32[:, ::1], int64[::1], int64", error_model="numpy")
def _greedy_core(weights: np.ndarray, candidates: np.ndarray, size: int) -> np.ndarray:
    # Positions in ``candidates`` of the greedy core: each consistent (w > 0) with all before.
    taken = np.empty(max(min(size, len(candidates)), 0), dtype=np.int64)
    if len(taken) == 0:
        return taken
    taken[0] = 0
    found = 1
    for position in range(1, len(candidates)):
        if found == len(taken):
            break
        pair = candidates[position]
        consistent = True
        for earlier in range(found):
            if not weights[candidates[taken[earlier]], pair] > 0.0:
                consistent = False
                break
        if consistent:
            taken[found] = position
            found += 1
    return taken[:found]


@kernel(error_model="numpy")
def _centred_float32(points: np.ndarray) -> np.ndarray:
    # (3, N) float32 coordinates relative to the centroid: small numbers keep the float32
    # distances accurate, and rows of one coordinate make the kernels' inner loops SIMD.
    count = len(points)
    mean = np.zeros(3)
    for row in range(count):
        for axis in range(3):
            mean[axis] += points[row, axis]
    for axis in range(3):
        mean[axis] /= count
    centred = np.empty((3, count), dtype=np.float32)
    for row in range(count):
        for axis in range(3):
            centred[axis, row] = points[row, axis] - mean[axis]
    return centred


@kernel("float64[:, ::1], float64[:, ::1], float64", fastmath=True, error_model="numpy")
def _rigidity_kernel(source: np.ndarray, target: np.ndarray, tolerance: float) -> np.ndarray:
    # Full rows over structure-of-arrays inputs: branch-free, SIMD-friendly inner loop.
    source32, target32 = _centred_float32(source), _centred_float32(target)
    count = source32.shape[1]
    weights = np.empty((count, count), dtype=np.float32)
    scale = np.float32(1.0 / (tolerance * tolerance))
    zero, one = np.float32(0.0), np.float32(1.0)
    sx, sy, sz = source32[0], source32[1], source32[2]
    tx, ty, tz = target32[0], target32[1], target32[2]
    for i in range(count):
        row = weights[i]
        for j in range(count):
            source_sq = (sx[j] - sx[i]) ** 2 + (sy[j] - sy[i]) ** 2 + (sz[j] - sz[i]) ** 2
            target_sq = (tx[j] - tx[i]) ** 2 + (ty[j] - ty[i]) ** 2 + (tz[j] - tz[i]) ** 2
            error = np.sqrt(source_sq) - np.sqrt(target_sq)
            row[j] = max(one - error * error * scale, zero)
        row[i] = zero
    return weights


@kernel(
    "float64[:, ::1], float64[:, ::1], float64, float32[::1]",
    fastmath=True,
    error_model="numpy",
)
def _scaled_rigidity_kernel(
    source: np.ndarray, target: np.ndarray, tolerance: float, half_squares: np.ndarray
) -> np.ndarray:
    # As _rigidity_kernel, dividing by tolerance^2 (s_i^2 + s_j^2) / 2 per pair of pairs.
    source32, target32 = _centred_float32(source), _centred_float32(target)
    count = source32.shape[1]
    weights = np.empty((count, count), dtype=np.float32)
    scale = np.float32(1.0 / (tolerance * tolerance))
    zero, one = np.float32(0.0), np.float32(1.0)
    sx, sy, sz = source32[0], source32[1], source32[2]
    tx, ty, tz = target32[0], target32[1], target32[2]
    for i in range(count):
        row = weights[i]
        own = half_squares[i]
        for j in range(count):
            source_sq = (sx[j] - sx[i]) ** 2 + (sy[j] - sy[i]) ** 2 + (sz[j] - sz[i]) ** 2
            target_sq = (tx[j] - tx[i]) ** 2 + (ty[j] - ty[i]) ** 2 + (tz[j] - tz[i]) ** 2
            error = np.sqrt(source_sq) - np.sqrt(target_sq)
            row[j] = max(one - error * error * scale / (own + half_squares[j]), zero)
        row[i] = zero
    return weights


# The swarm's keyword options but the per-pair inputs (sigmas and covariances).
