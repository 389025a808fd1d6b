"""Compiled kernels of the swarm: pair forms, particle scoring and the Horn refit loop.

Each pair is reduced once to the 10 coefficients of its symmetric Horn matrix N_j, so a particle
(a rotation) costs 10 multiply-adds per pair; the refits solve Horn's closed form with a small
Jacobi eigen solver (steps 3 and 4 of ``pso_support``).
"""

from __future__ import annotations

import math

import numpy as np

from estimator.compiled import kernel

__all__ = [
    "MIN_SUPPORT",
    "degenerate_points",
    "degenerate_rows",
    "exp_quaternion",
    "fit_pose",
    "horn_fit",
    "pair_forms",
    "quaternion_rotation",
    "refit_loop",
    "swarm_residuals",
    "swarm_scores",
    "symmetric_eigen",
]

# Fewest supporters of a pose (a fit of 3 pairs cannot be checked).
MIN_SUPPORT = 4

# Each call of pso-robust runs these on a few hundred pairs: compiled, a step costs
# microseconds, where the equivalent dozen small numpy calls would cost ten times more.
# They are written as scalar loops (no array expressions, matmul or linalg), which keeps
# their one-off compilation (cached on disk) short. error_model="numpy": a division is a
# plain IEEE division, not a ZeroDivisionError check, whose branch would stop the loops
# from vectorising (the scaled rigidity kernel ran 6x slower with it).


@kernel("float64[:, ::1]", error_model="numpy")
def symmetric_eigen(matrix: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    # Cyclic Jacobi for a small symmetric matrix: eigenvalues ascending, unit eigenvectors
    # as columns. For 3x3 and 4x4 it is faster than a LAPACK call and compiles in a
    # fraction of the time of numba's linalg wrappers. Accuracy ~1e-16 of the norm, as
    # LAPACK's: off-diagonal elements below 1e-18 of the norm are dropped, which also ends
    # the sweeps (quadratic convergence: a handful for 4x4).
    size = matrix.shape[0]
    a = np.empty((size, size))
    vectors = np.zeros((size, size))
    squares = 0.0
    for p in range(size):
        vectors[p, p] = 1.0
        for q in range(size):
            a[p, q] = matrix[p, q]
            squares += matrix[p, q] * matrix[p, q]
    negligible = 1e-18 * math.sqrt(squares)
    for _ in range(64):
        rotated = False
        for p in range(size - 1):
            for q in range(p + 1, size):
                apq = a[p, q]
                if abs(apq) <= negligible:
                    continue
                rotated = True
                theta = (a[q, q] - a[p, p]) / (2.0 * apq)
                if abs(theta) > 1e150:
                    tangent = 0.5 / theta
                elif theta >= 0.0:
                    tangent = 1.0 / (theta + math.sqrt(theta * theta + 1.0))
                else:
                    tangent = -1.0 / (-theta + math.sqrt(theta * theta + 1.0))
                cosine = 1.0 / math.sqrt(tangent * tangent + 1.0)
                sine = tangent * cosine
                for k in range(size):  # A <- A J (columns p, q)
                    akp, akq = a[k, p], a[k, q]
                    a[k, p] = cosine * akp - sine * akq
                    a[k, q] = sine * akp + cosine * akq
                for k in range(size):  # A <- J^T A (rows p, q)
                    apk, aqk = a[p, k], a[q, k]
                    a[p, k] = cosine * apk - sine * aqk
                    a[q, k] = sine * apk + cosine * aqk
                a[p, q] = 0.0
                a[q, p] = 0.0
                for k in range(size):  # V <- V J
                    vkp, vkq = vectors[k, p], vectors[k, q]
                    vectors[k, p] = cosine * vkp - sine * vkq
                    vectors[k, q] = sine * vkp + cosine * vkq
        if not rotated:
            break
    values = np.empty(size)
    for k in range(size):
        values[k] = a[k, k]
    for k in range(1, size):  # insertion sort, ascending, columns along
        j = k
        while j > 0 and values[j - 1] > values[j]:
            values[j - 1], values[j] = values[j], values[j - 1]
            for row in range(size):
                vectors[row, j - 1], vectors[row, j] = vectors[row, j], vectors[row, j - 1]
            j -= 1
    return values, vectors


@kernel("float64[:, ::1], int64[::1]", error_model="numpy")
def degenerate_points(points: np.ndarray, rows: np.ndarray) -> bool:
    # ``geometry.is_degenerate`` of points[rows], without the copy: the same two criteria
    # on the singular values of the centred set (square roots of the scatter's eigenvalues).
    if len(rows) < 3:
        return True
    mean = np.zeros(3)
    peak = 0.0
    for row in rows:
        for axis in range(3):
            mean[axis] += points[row, axis]
            peak = max(peak, abs(points[row, axis]))
    for axis in range(3):
        mean[axis] /= len(rows)
    scatter = np.zeros((3, 3))
    for row in rows:
        for a in range(3):
            offset = points[row, a] - mean[a]
            for b in range(3):
                scatter[a, b] += offset * (points[row, b] - mean[b])
    values = symmetric_eigen(scatter)[0]
    middle, largest = math.sqrt(max(values[1], 0.0)), math.sqrt(max(values[2], 0.0))
    return largest <= 1e-12 * max(peak, 1e-300) or middle <= 1e-6 * largest


@kernel("float64[:, ::1], float64[:, ::1], int64[::1]", error_model="numpy")
def degenerate_rows(source: np.ndarray, target: np.ndarray, rows: np.ndarray) -> bool:
    return degenerate_points(source, rows) or degenerate_points(target, rows)


@kernel(
    "float64[:, ::1], float64[:, ::1], int64[::1], float64[:, ::1], float64[::1]",
    error_model="numpy",
)
def pair_forms(
    source: np.ndarray,
    target: np.ndarray,
    anchor: np.ndarray,
    rotation: np.ndarray,
    inverse_scales: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    # s_j = R (p_j - c) / scale_j, t_j = (p'_j - c') / scale_j with c, c' the centroids of
    # the anchor rows; returns the (10, M) forms
    # -2 (N00, N11, N22, N33, 2 N01, 2 N02, 2 N03, 2 N12, 2 N13, 2 N23) of Horn's matrix
    # N(s_j t_j^T) and |s_j|^2 + |t_j|^2, so that ||t_j - q s_j q^-1||^2 is
    # norms_j + forms[:, j] . (q0q0, q1q1, q2q2, q3q3, q0q1, q0q2, q0q3, q1q2, q1q3, q2q3).
    source_centre = np.zeros(3)
    target_centre = np.zeros(3)
    for row in anchor:
        for a in range(3):
            source_centre[a] += source[row, a]
            target_centre[a] += target[row, a]
    for a in range(3):
        source_centre[a] /= len(anchor)
        target_centre[a] /= len(anchor)
    count = len(source)
    forms = np.empty((10, count))
    norms = np.empty(count)
    s = np.empty(3)
    t = np.empty(3)
    for j in range(count):
        scale = inverse_scales[j]
        for a in range(3):
            s[a] = (
                rotation[a, 0] * (source[j, 0] - source_centre[0])
                + rotation[a, 1] * (source[j, 1] - source_centre[1])
                + rotation[a, 2] * (source[j, 2] - source_centre[2])
            ) * scale
            t[a] = (target[j, a] - target_centre[a]) * scale
        xx, xy, xz = s[0] * t[0], s[0] * t[1], s[0] * t[2]
        yx, yy, yz = s[1] * t[0], s[1] * t[1], s[1] * t[2]
        zx, zy, zz = s[2] * t[0], s[2] * t[1], s[2] * t[2]
        forms[0, j] = -2.0 * (xx + yy + zz)
        forms[1, j] = -2.0 * (xx - yy - zz)
        forms[2, j] = -2.0 * (yy - xx - zz)
        forms[3, j] = -2.0 * (zz - xx - yy)
        forms[4, j] = -4.0 * (yz - zy)
        forms[5, j] = -4.0 * (zx - xz)
        forms[6, j] = -4.0 * (xy - yx)
        forms[7, j] = -4.0 * (xy + yx)
        forms[8, j] = -4.0 * (zx + xz)
        forms[9, j] = -4.0 * (yz + zy)
        norms[j] = s[0] ** 2 + s[1] ** 2 + s[2] ** 2 + t[0] ** 2 + t[1] ** 2 + t[2] ** 2
    return forms, norms


@kernel(error_model="numpy")
def exp_quaternion(rotation_vector: np.ndarray) -> tuple[float, float, float, float]:
    """(w, x, y, z) of the exponential map of a rotation vector, as
    ``geometry.rotation_vector_to_quat`` forms it, for compiled callers."""
    angle = math.sqrt(rotation_vector[0] ** 2 + rotation_vector[1] ** 2 + rotation_vector[2] ** 2)
    half = 0.5 * angle
    scale = 0.5 - angle * angle / 48.0 if angle < 1e-8 else math.sin(half) / angle
    w = math.cos(half)
    x, y, z = rotation_vector[0] * scale, rotation_vector[1] * scale, rotation_vector[2] * scale
    return w, x, y, z


@kernel(error_model="numpy")
def _quat_products(rotation_vector: np.ndarray, products: np.ndarray) -> None:
    # The exponential map, then the 10 products of the quaternion's components in the order
    # of ``pair_forms``, into ``products``.
    w, x, y, z = exp_quaternion(rotation_vector)
    products[0], products[1], products[2], products[3] = w * w, x * x, y * y, z * z
    products[4], products[5], products[6] = w * x, w * y, w * z
    products[7], products[8], products[9] = x * y, x * z, y * z


@kernel("float64[:, ::1], float64[:, ::1], float64[::1]", fastmath=True, error_model="numpy")
def swarm_residuals(positions: np.ndarray, forms: np.ndarray, norms: np.ndarray) -> np.ndarray:
    # (P, M) squared residuals of every particle against every pair.
    squared = np.empty((positions.shape[0], len(norms)))
    products = np.empty(10)
    for particle in range(positions.shape[0]):
        _quat_products(positions[particle], products)
        for j in range(len(norms)):
            value = norms[j]
            for k in range(10):
                value += forms[k, j] * products[k]
            squared[particle, j] = max(value, 0.0)
    return squared


@kernel(
    "float64[:, ::1], float64[:, ::1], float64[::1], float64, bool",
    fastmath=True,
    error_model="numpy",
)
def swarm_scores(
    positions: np.ndarray, forms: np.ndarray, norms: np.ndarray, limit: float, truncate: bool
) -> tuple[np.ndarray, np.ndarray]:
    # Support (squared residual < limit) and cost (sum of squares, truncated at limit or not)
    # of every particle, without the (P, M) matrix. fastmath lets the sums vectorise
    # (reordered additions: ~1e-14 relative, deterministic for a given machine).
    support = np.zeros(positions.shape[0], dtype=np.int64)
    cost = np.zeros(positions.shape[0])
    products = np.empty(10)
    for particle in range(positions.shape[0]):
        _quat_products(positions[particle], products)
        count = 0
        total = 0.0
        for j in range(len(norms)):
            value = norms[j]
            for k in range(10):
                value += forms[k, j] * products[k]
            value = max(value, 0.0)
            if value < limit:
                count += 1
            total += min(value, limit) if truncate else value
        support[particle] = count
        cost[particle] = total
    return support, cost


@kernel("float64[:, ::1], float64[:, ::1], float64[::1], bool[::1]", error_model="numpy")
def horn_fit(
    source: np.ndarray, target: np.ndarray, weights: np.ndarray, mask: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    # Weighted Horn on the pairs in mask: centroids, correlation, top eigenvector of the
    # 4x4 Horn matrix as the quaternion (w >= 0), its rotation, t = c' - R c.
    total, source_mean, target_mean = _weighted_centroids(source, target, weights, mask)
    correlation = _weighted_correlation(
        source, target, weights, mask, total, source_mean, target_mean
    )
    quaternion = _top_quaternion(_horn_matrix(correlation))
    rotation = quaternion_rotation(quaternion)
    return quaternion, rotation, _translation(rotation, source_mean, target_mean)


@kernel(error_model="numpy")
def _weighted_centroids(
    source: np.ndarray, target: np.ndarray, weights: np.ndarray, mask: np.ndarray
) -> tuple[float, np.ndarray, np.ndarray]:
    # The total weight of the pairs in mask and their weighted means.
    total = 0.0
    for j in range(len(source)):
        if mask[j]:
            total += weights[j]
    source_mean = np.zeros(3)
    target_mean = np.zeros(3)
    for j in range(len(source)):
        if mask[j]:
            for a in range(3):
                source_mean[a] += weights[j] * source[j, a]
                target_mean[a] += weights[j] * target[j, a]
    for a in range(3):
        source_mean[a] /= total
        target_mean[a] /= total
    return total, source_mean, target_mean


@kernel(error_model="numpy")
def _weighted_correlation(
    source: np.ndarray,
    target: np.ndarray,
    weights: np.ndarray,
    mask: np.ndarray,
    total: float,
    source_mean: np.ndarray,
    target_mean: np.ndarray,
) -> np.ndarray:
    # c[a, b] = sum_j (w_j / total) (s_j - s_mean)_a (t_j - t_mean)_b over the pairs in mask.
    c = np.zeros((3, 3))
    for j in range(len(source)):
        if mask[j]:
            share = weights[j] / total
            for a in range(3):
                offset = share * (source[j, a] - source_mean[a])
                for b in range(3):
                    c[a, b] += offset * (target[j, b] - target_mean[b])
    return c


@kernel(error_model="numpy")
def _horn_matrix(c: np.ndarray) -> np.ndarray:
    # Horn's symmetric 4x4 matrix of the correlation (``estimator.geometry.horn``).
    horn_matrix = np.empty((4, 4))
    horn_matrix[0, 0] = c[0, 0] + c[1, 1] + c[2, 2]
    horn_matrix[1, 1] = c[0, 0] - c[1, 1] - c[2, 2]
    horn_matrix[2, 2] = c[1, 1] - c[0, 0] - c[2, 2]
    horn_matrix[3, 3] = c[2, 2] - c[0, 0] - c[1, 1]
    horn_matrix[0, 1] = horn_matrix[1, 0] = c[1, 2] - c[2, 1]
    horn_matrix[0, 2] = horn_matrix[2, 0] = c[2, 0] - c[0, 2]
    horn_matrix[0, 3] = horn_matrix[3, 0] = c[0, 1] - c[1, 0]
    horn_matrix[1, 2] = horn_matrix[2, 1] = c[0, 1] + c[1, 0]
    horn_matrix[1, 3] = horn_matrix[3, 1] = c[2, 0] + c[0, 2]
    horn_matrix[2, 3] = horn_matrix[3, 2] = c[1, 2] + c[2, 1]
    return horn_matrix


@kernel(error_model="numpy")
def _top_quaternion(horn_matrix: np.ndarray) -> np.ndarray:
    # The eigenvector of the largest eigenvalue, normalised, with w >= 0.
    vectors = symmetric_eigen(horn_matrix)[1]
    top = vectors[:, 3]
    length = math.sqrt(top[0] ** 2 + top[1] ** 2 + top[2] ** 2 + top[3] ** 2)
    sign = -1.0 if top[0] < 0.0 else 1.0
    quaternion = np.empty(4)
    for k in range(4):
        quaternion[k] = sign * top[k] / length
    return quaternion


@kernel(error_model="numpy")
def quaternion_rotation(quaternion: np.ndarray) -> np.ndarray:
    """The rotation matrix of a unit quaternion (w, x, y, z), as ``geometry.quat_to_matrix``
    forms it, for compiled callers."""
    w, x, y, z = quaternion[0], quaternion[1], quaternion[2], quaternion[3]
    rotation = np.empty((3, 3))
    rotation[0, 0], rotation[0, 1], rotation[0, 2] = (
        1 - 2 * (y * y + z * z),
        2 * (x * y - w * z),
        2 * (x * z + w * y),
    )
    rotation[1, 0], rotation[1, 1], rotation[1, 2] = (
        2 * (x * y + w * z),
        1 - 2 * (x * x + z * z),
        2 * (y * z - w * x),
    )
    rotation[2, 0], rotation[2, 1], rotation[2, 2] = (
        2 * (x * z - w * y),
        2 * (y * z + w * x),
        1 - 2 * (x * x + y * y),
    )
    return rotation


@kernel(error_model="numpy")
def _translation(
    rotation: np.ndarray, source_mean: np.ndarray, target_mean: np.ndarray
) -> np.ndarray:
    # t = c' - R c: the translation that maps the source centroid onto the target's.
    translation = np.empty(3)
    for a in range(3):
        translation[a] = target_mean[a] - (
            rotation[a, 0] * source_mean[0]
            + rotation[a, 1] * source_mean[1]
            + rotation[a, 2] * source_mean[2]
        )
    return translation


@kernel(error_model="numpy")
def _normalised_residuals(
    source: np.ndarray,
    target: np.ndarray,
    rotation: np.ndarray,
    translation: np.ndarray,
    inverse_scales: np.ndarray,
) -> np.ndarray:
    # ||p'_j - (R p_j + t)|| / scale_j for every pair.
    residual = np.empty(len(source))
    for j in range(len(source)):
        total = 0.0
        for a in range(3):
            difference = (
                target[j, a]
                - rotation[a, 0] * source[j, 0]
                - rotation[a, 1] * source[j, 1]
                - rotation[a, 2] * source[j, 2]
                - translation[a]
            )
            total += difference * difference
        residual[j] = math.sqrt(total) * inverse_scales[j]
    return residual


@kernel(
    "float64[:, ::1], float64[:, ::1], bool[::1], float64[::1], float64[::1]",
    error_model="numpy",
)
def fit_pose(
    source: np.ndarray,
    target: np.ndarray,
    mask: np.ndarray,
    weights: np.ndarray,
    inverse_scales: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    quaternion, rotation, translation = horn_fit(source, target, weights, mask)
    residual = _normalised_residuals(source, target, rotation, translation, inverse_scales)
    return quaternion, rotation, translation, residual


@kernel(
    "float64[:, ::1], float64[:, ::1], bool[::1], float64, float64[::1], float64[::1], "
    "float64[::1], float64, bool, bool, int64, float64, float64",
    error_model="numpy",
)
def refit_loop(
    source: np.ndarray,
    target: np.ndarray,
    supporters: np.ndarray,
    delta: float,
    weights: np.ndarray,
    inverse_scales: np.ndarray,
    residual: np.ndarray,
    floor: float,
    weighted: bool,
    adapt: bool,
    refits: int,
    delta_min: float,
    delta_max: float,
) -> tuple[np.ndarray, float, np.ndarray, np.ndarray, np.ndarray, np.ndarray, bool]:
    # PsoSupportEstimator._refine: fit (weights, or with ``weighted`` weights /
    # max(residual, floor)^2 from the previous pose), recount, until the set repeats.
    # Adaptive delta: 4 sigma of the supporters' residuals, sigma = RMS / sqrt(3).
    quaternion, rotation, translation = np.zeros(4), np.zeros((3, 3)), np.zeros(3)
    fit_weights = weights.copy()
    for _ in range(refits):
        support = 0
        for j in range(len(supporters)):
            support += supporters[j]
        if support < MIN_SUPPORT:
            break
        if weighted:
            for j in range(len(supporters)):
                if supporters[j]:
                    fit_weights[j] = weights[j] / max(residual[j], floor) ** 2
        quaternion, rotation, translation = horn_fit(source, target, fit_weights, supporters)
        residual = _normalised_residuals(source, target, rotation, translation, inverse_scales)
        if adapt:
            squares = 0.0
            for j in range(len(supporters)):
                if supporters[j]:
                    squares += residual[j] * residual[j]
            delta = 4.0 * math.sqrt(squares / support / 3.0)
            delta = min(max(delta, delta_min), delta_max)
        refreshed = np.empty_like(supporters)
        settled = True
        for j in range(len(supporters)):
            refreshed[j] = residual[j] < delta
            settled = settled and refreshed[j] == supporters[j]
        if settled:
            return supporters, delta, quaternion, rotation, translation, residual, True
        supporters = refreshed
    return supporters, delta, quaternion, rotation, translation, residual, False
