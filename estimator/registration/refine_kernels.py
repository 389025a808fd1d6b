"""Compiled per-pair loop of the Mahalanobis refinement (``refine.py``).

A frame refines about a hundred pairs, eight or so times; at that size the NumPy version spent
its time in some twenty array calls per linearisation, not in arithmetic. One compiled pass
over the pairs forms the same quantities: the source-frame residual r' = R^T (t_j - t) - s_j,
its covariance C_src + R^T C_tgt R and that covariance's inverse (adjugate, as the NumPy
version), the robust weight, and the sums J^T W J and J^T W r' with J = [[s]x, -I].
"""

from __future__ import annotations

import numpy as np

from estimator.compiled import kernel
from estimator.registration.swarm_kernels import exp_quaternion, quaternion_rotation

__all__ = [
    "ROBUST_CODES",
    "kernel_pairs",
    "kernel_pose",
    "levenberg_marquardt",
    "linearise_pairs",
    "scaled_condition",
    "score_outer_products",
    "sensitivity_terms",
    "solve_pivoted",
    "squared_distances",
]

ROBUST_CODES = {"none": 0, "cauchy": 1, "huber": 2}


def kernel_pairs(*arrays: np.ndarray) -> tuple[np.ndarray, ...]:
    """The pairs' points and covariances as the kernels take them: contiguous float64."""
    return tuple(np.ascontiguousarray(array, dtype=float) for array in arrays)


def kernel_pose(rotation: np.ndarray, translation: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A pose as the kernels take it: contiguous (3, 3) and (3,) float64."""
    return (
        np.ascontiguousarray(rotation, dtype=float),
        np.ascontiguousarray(translation, dtype=float).reshape(3),
    )


# Where J = [[s]x, -I] is not a structural zero (row k, column j). The sums skip the zeros:
# a running sum that starts at 0.0 is unchanged by adding +-0.0, so for finite data the result
# is bit for bit the full sum's, at half the multiply-adds.
_JACOBIAN_NONZERO = np.array(
    [[k != j if j < 3 else k == j - 3 for j in range(6)] for k in range(3)], dtype=np.bool_
)


@kernel(inline="always")
def _column(x, y, z, rotation, j):
    """x R[0, j] + y R[1, j] + z R[2, j], summed from 0.0 in that order (the rounding the
    array version had, signed zeros included)."""
    value = 0.0
    value += x * rotation[0, j]
    value += y * rotation[1, j]
    value += z * rotation[2, j]
    return value


@kernel(inline="always")
def _pair(source, target, source_cov, target_cov, rotation, translation, n, residual, info):
    """Fill ``residual`` (3,) and ``info`` (3, 3) of pair ``n``; False for a singular one.

    Scalars only: three small temporary arrays per pair (heap allocations in compiled code)
    cost more than the arithmetic.
    """
    d0 = target[n, 0] - translation[0]
    d1 = target[n, 1] - translation[1]
    d2 = target[n, 2] - translation[2]
    for i in range(3):
        residual[i] = _column(d0, d1, d2, rotation, i) - source[n, i]
    # P = C_tgt R (row k: C_tgt[k] R), then C_src + R^T P, of which the upper triangle.
    c = target_cov
    p00 = _column(c[n, 0, 0], c[n, 0, 1], c[n, 0, 2], rotation, 0)
    p01 = _column(c[n, 0, 0], c[n, 0, 1], c[n, 0, 2], rotation, 1)
    p02 = _column(c[n, 0, 0], c[n, 0, 1], c[n, 0, 2], rotation, 2)
    p10 = _column(c[n, 1, 0], c[n, 1, 1], c[n, 1, 2], rotation, 0)
    p11 = _column(c[n, 1, 0], c[n, 1, 1], c[n, 1, 2], rotation, 1)
    p12 = _column(c[n, 1, 0], c[n, 1, 1], c[n, 1, 2], rotation, 2)
    p20 = _column(c[n, 2, 0], c[n, 2, 1], c[n, 2, 2], rotation, 0)
    p21 = _column(c[n, 2, 0], c[n, 2, 1], c[n, 2, 2], rotation, 1)
    p22 = _column(c[n, 2, 0], c[n, 2, 1], c[n, 2, 2], rotation, 2)
    s = source_cov
    a = s[n, 0, 0] + _column(p00, p10, p20, rotation, 0)
    b = s[n, 0, 1] + _column(p01, p11, p21, rotation, 0)
    c_ = s[n, 0, 2] + _column(p02, p12, p22, rotation, 0)
    d = s[n, 1, 1] + _column(p01, p11, p21, rotation, 1)
    e = s[n, 1, 2] + _column(p02, p12, p22, rotation, 1)
    f = s[n, 2, 2] + _column(p02, p12, p22, rotation, 2)
    cofactor_a, cofactor_b, cofactor_c = d * f - e * e, c_ * e - b * f, b * e - c_ * d
    determinant = a * cofactor_a + b * cofactor_b + c_ * cofactor_c
    if not abs(determinant) > 0.0:
        return False
    info[0, 0], info[0, 1], info[0, 2] = cofactor_a, cofactor_b, cofactor_c
    info[1, 1], info[1, 2], info[2, 2] = a * f - c_ * c_, b * c_ - a * e, a * d - b * b
    info[1, 0], info[2, 0], info[2, 1] = cofactor_b, cofactor_c, info[1, 2]
    for i in range(3):
        for j in range(3):
            info[i, j] /= determinant
    return True


@kernel()
def _quadratic_form(info, residual):
    """r^T W r for one pair's 3x3 information matrix."""
    value = 0.0
    for i in range(3):
        whitened = 0.0
        for j in range(3):
            whitened += info[i, j] * residual[j]
        value += residual[i] * whitened
    return value


@kernel(
    "float64[:, ::1], float64[:, ::1], float64[:, :, ::1], float64[:, :, ::1], float64[:, ::1], "
    "float64[::1]",
)
def squared_distances(source, target, source_cov, target_cov, rotation, translation):
    """(N,) squared Mahalanobis distances and whether every pair's covariance is regular."""
    count = source.shape[0]
    squared = np.empty(count)
    residual = np.empty(3)
    info = np.empty((3, 3))
    for n in range(count):
        if not _pair(source, target, source_cov, target_cov, rotation, translation, n,
                     residual, info):  # fmt: skip
            return squared, False
        value = _quadratic_form(info, residual)
        squared[n] = value
    return squared, True


@kernel(
    "float64[:, ::1], float64[:, ::1], float64[:, :, ::1], float64[:, :, ::1], float64[:, ::1], "
    "float64[::1], int64, float64",
)
def linearise_pairs(
    source, target, source_cov, target_cov, rotation, translation, robust_code, scale
):
    """(cost, J^T W J (6, 6), J^T W r' (6,), squared distances (N,), regular) in one pass."""
    count = source.shape[0]
    squared = np.empty(count)
    hessian = np.zeros((6, 6))
    gradient = np.zeros(6)
    residual = np.empty(3)
    info = np.empty((3, 3))
    jacobian = np.zeros((3, 6))
    weighted = np.empty((3, 6))
    c2 = scale * scale
    cost = 0.0
    for i in range(3):
        jacobian[i, 3 + i] = -1.0
    for n in range(count):
        if not _pair(source, target, source_cov, target_cov, rotation, translation, n,
                     residual, info):  # fmt: skip
            return 0.0, hessian, gradient, squared, False
        value = _quadratic_form(info, residual)
        squared[n] = value
        if robust_code == 1:
            cost += c2 * np.log1p(value / c2)
            weight = 1.0 / (1.0 + value / c2)
        elif robust_code == 2:
            distance = np.sqrt(value)
            if distance > scale:
                cost += 2.0 * scale * distance - c2
                weight = scale / max(distance, 1e-300)
            else:
                cost += value
                weight = 1.0
        else:
            cost += value
            weight = 1.0
        s0, s1, s2 = source[n, 0], source[n, 1], source[n, 2]
        jacobian[0, 1], jacobian[0, 2] = -s2, s1
        jacobian[1, 0], jacobian[1, 2] = s2, -s0
        jacobian[2, 0], jacobian[2, 1] = -s1, s0
        for i in range(3):
            for j in range(6):
                total = 0.0
                for k in range(3):
                    if _JACOBIAN_NONZERO[k, j]:
                        total += info[i, k] * jacobian[k, j]
                weighted[i, j] = total * weight
        for a in range(6):
            for b in range(6):
                total = 0.0
                for k in range(3):
                    if _JACOBIAN_NONZERO[k, a]:
                        total += jacobian[k, a] * weighted[k, b]
                hessian[a, b] += total
            total = 0.0
            for k in range(3):
                total += weighted[k, a] * residual[k]
            gradient[a] += total
    return cost, hessian, gradient, squared, True


@kernel(
    "float64[:, ::1], float64[:, ::1], float64[:, :, ::1], float64[:, :, ::1], float64[:, ::1], "
    "float64[::1], int64, float64",
)
def score_outer_products(
    source, target, source_cov, target_cov, rotation, translation, robust_code, scale
):
    """(B, D, regular): B = sum_j g_j g_j^T with g_j = w_j J_j^T W_j r'_j, each pair's share
    of the gradient (the "meat" of the robust sandwich covariance, ``refine.py``), and D the
    part of J^T W J that the robust cost's own curvature takes off (the Gauss-Newton Hessian
    minus D is the Hessian of the robust cost): with half the cost per pair
    rho(z) = c^2/2 log(1 + |z|^2/c^2) (Cauchy) the Hessian in the whitened residual z is
    w I - 2 w^2 / c^2 z z^T, so D_j = 2 / c^2 g_j g_j^T; Huber beyond its threshold k:
    w I - w / |z|^2 z z^T, D_j = g_j g_j^T / (k |z|)."""
    count = source.shape[0]
    meat = np.zeros((6, 6))
    curvature = np.zeros((6, 6))
    residual = np.empty(3)
    info = np.empty((3, 3))
    whitened = np.empty(3)
    score = np.empty(6)
    c2 = scale * scale
    for n in range(count):
        if not _pair(source, target, source_cov, target_cov, rotation, translation, n,
                     residual, info):  # fmt: skip
            return meat, curvature, False
        value = _quadratic_form(info, residual)
        weight, loss = 1.0, 0.0
        if robust_code == 1:
            weight = 1.0 / (1.0 + value / c2)
            loss = 2.0 / c2
        elif robust_code == 2:
            distance = np.sqrt(value)
            if distance > scale:
                weight = scale / max(distance, 1e-300)
                loss = 1.0 / (scale * distance)
        for i in range(3):
            total = 0.0
            for k in range(3):
                total += info[i, k] * residual[k]
            whitened[i] = weight * total
        s0, s1, s2 = source[n, 0], source[n, 1], source[n, 2]
        # J^T w with J = [[s]x, -I]: [s]x^T w = w x s, then -w.
        score[0] = whitened[1] * s2 - whitened[2] * s1
        score[1] = whitened[2] * s0 - whitened[0] * s2
        score[2] = whitened[0] * s1 - whitened[1] * s0
        score[3], score[4], score[5] = -whitened[0], -whitened[1], -whitened[2]
        for a in range(6):
            for b in range(6):
                product = score[a] * score[b]
                meat[a, b] += product
                curvature[a, b] += loss * product
    return meat, curvature, True


@kernel("float64[:, ::1]")
def scaled_condition(hessian):
    """2-norm condition number of the Jacobi-scaled ``hessian`` (radians and metres are not
    comparable units); inf when it is not finite or a diagonal entry is not positive.
    The refinement only compares it with a limit, so LAPACK's rounding here is immaterial."""
    size = hessian.shape[0]
    scale = np.empty(size)
    for i in range(size):
        if not hessian[i, i] > 0.0:
            return np.inf
        scale[i] = 1.0 / np.sqrt(hessian[i, i])
    scaled = np.empty((size, size))
    for i in range(size):
        for j in range(size):
            if not np.isfinite(hessian[i, j]):
                return np.inf
            scaled[i, j] = hessian[i, j] * scale[i] * scale[j]
    return np.linalg.cond(scaled)


@kernel(inline="always")
def _robust_weight(value, robust_code, scale):
    """The IRLS weight of a pair with squared distance ``value`` (as ``linearise_pairs``)."""
    if robust_code == 1:
        return 1.0 / (1.0 + value / (scale * scale))
    if robust_code == 2:
        distance = np.sqrt(value)
        return scale / max(distance, 1e-300) if distance > scale else 1.0
    return 1.0


@kernel(
    "float64[:, ::1], float64[:, ::1], float64[:, :, ::1], float64[:, :, ::1], float64[:, ::1], "
    "float64[::1], int64, float64",
)
def sensitivity_terms(
    source, target, source_cov, target_cov, rotation, translation, robust_code, scale
):
    """The per-pair terms of the refined pose's point sensitivities (``sensitivity.py``):
    (J_j^T W_j - [[W_j r_j']x; 0] (N, 6, 3), -J_j^T W_j R^T (N, 6, 3), H = sum J^T W J (6, 6),
    regular), with W_j the robust-weighted information and J_j = [[s_j]x, -I]."""
    count = source.shape[0]
    own = np.zeros((count, 6, 3))
    other = np.zeros((count, 6, 3))
    hessian = np.zeros((6, 6))
    residual = np.empty(3)
    info = np.empty((3, 3))
    for n in range(count):
        if not _pair(source, target, source_cov, target_cov, rotation, translation, n,
                     residual, info):  # fmt: skip
            return own, other, hessian, False
        weight = _robust_weight(_quadratic_form(info, residual), robust_code, scale)
        s0, s1, s2 = source[n, 0], source[n, 1], source[n, 2]
        for b in range(3):  # J^T W: rows [s]x^T W, then -W
            w0, w1, w2 = info[0, b] * weight, info[1, b] * weight, info[2, b] * weight
            own[n, 0, b] = s2 * w1 - s1 * w2
            own[n, 1, b] = s0 * w2 - s2 * w0
            own[n, 2, b] = s1 * w0 - s0 * w1
            own[n, 3, b], own[n, 4, b], own[n, 5, b] = -w0, -w1, -w2
        for a in range(6):
            t0, t1, t2 = own[n, a, 0], own[n, a, 1], own[n, a, 2]
            hessian[a, 0] += t1 * s2 - t2 * s1
            hessian[a, 1] += t2 * s0 - t0 * s2
            hessian[a, 2] += t0 * s1 - t1 * s0
            hessian[a, 3] -= t0
            hessian[a, 4] -= t1
            hessian[a, 5] -= t2
            for c in range(3):
                other[n, a, c] = -(t0 * rotation[c, 0] + t1 * rotation[c, 1] + t2 * rotation[c, 2])
        # J_j moves with source_j too: take [W_j r_j']x off the rotation rows.
        r0, r1, r2 = residual[0], residual[1], residual[2]
        p0 = weight * (info[0, 0] * r0 + info[0, 1] * r1 + info[0, 2] * r2)
        p1 = weight * (info[1, 0] * r0 + info[1, 1] * r1 + info[1, 2] * r2)
        p2 = weight * (info[2, 0] * r0 + info[2, 1] * r1 + info[2, 2] * r2)
        own[n, 0, 1] += p2
        own[n, 0, 2] -= p1
        own[n, 1, 0] -= p2
        own[n, 1, 2] += p0
        own[n, 2, 0] += p1
        own[n, 2, 1] -= p0
    return own, other, hessian, True


@kernel("float64[:, ::1], float64[::1]")
def solve_pivoted(matrix, rhs):
    """x with matrix x = rhs by Gaussian elimination with partial pivoting (what LAPACK's
    gesv does), and whether every pivot was non-zero; the inputs are left as they were."""
    a = matrix.copy()
    x = rhs.copy()
    size = x.shape[0]
    for column in range(size):
        pivot, largest = column, abs(a[column, column])
        for row in range(column + 1, size):
            if abs(a[row, column]) > largest:
                pivot, largest = row, abs(a[row, column])
        if not largest > 0.0:  # zero or NaN: no unique solution
            return x, False
        if pivot != column:
            for k in range(size):
                a[column, k], a[pivot, k] = a[pivot, k], a[column, k]
            x[column], x[pivot] = x[pivot], x[column]
        for row in range(column + 1, size):
            factor = a[row, column] / a[column, column]
            for k in range(column, size):
                a[row, k] -= factor * a[column, k]
            x[row] -= factor * x[column]
    for row in range(size - 1, -1, -1):
        total = x[row]
        for k in range(row + 1, size):
            total -= a[row, k] * x[k]
        x[row] = total / a[row, row]
    return x, True


@kernel()
def _step_pose(rotation, translation, step):
    """T Exp(step) with step = (omega, v), the right perturbation: R Exp(omega), t + R v
    (the exponential map and the normalised quaternion's matrix, as ``geometry`` forms them)."""
    w, x, y, z = exp_quaternion(step)
    norm = np.sqrt(w * w + x * x + y * y + z * z)
    turn = quaternion_rotation(np.array([w / norm, x / norm, y / norm, z / norm]))
    moved_r = np.empty((3, 3))
    moved_t = np.empty(3)
    for i in range(3):
        for j in range(3):
            total = 0.0
            for k in range(3):
                total += rotation[i, k] * turn[k, j]
            moved_r[i, j] = total
        total = 0.0
        for k in range(3):
            total += rotation[i, k] * step[3 + k]
        moved_t[i] = translation[i] + total
    return moved_r, moved_t


@kernel(
    "float64[:, ::1], float64[:, ::1], float64[:, :, ::1], float64[:, :, ::1], float64[:, ::1], "
    "float64[::1], float64, float64[:, ::1], float64[::1], float64[::1], int64, int64, float64, "
    "int64, float64, float64",
)
def levenberg_marquardt(
    source, target, source_cov, target_cov, rotation, translation, cost, hessian, gradient,
    squared, iterations, robust_code, scale, max_rejections, step_tolerance, settled_step,
):  # fmt: skip
    """The refinement's damped Gauss-Newton loop (``refine._levenberg_marquardt``) from the
    linearisation (cost, hessian, gradient, squared) at (rotation, translation).

    A step is kept only when it does not raise the cost, and the damping grows tenfold after
    each rejected one (at most ``max_rejections``); it stops when a step is shorter than
    ``step_tolerance``, or rejected while shorter than ``settled_step``. Returns the pose, its
    linearisation and the number of accepted steps.
    """
    estimate_r, estimate_t = rotation.copy(), translation.copy()
    damping, steps, rejected = 1e-4, 0, 0
    while steps < iterations and rejected < max_rejections:
        damped = hessian.copy()
        for i in range(6):
            damped[i, i] += damping * damped[i, i]
        step, regular = solve_pivoted(damped, -gradient)
        size = np.sqrt(np.sum(step * step)) if regular else np.nan
        if size < step_tolerance:
            break  # converged; a smaller step would only compare rounding errors
        usable = regular and np.isfinite(step).all()
        if usable:
            moved_r, moved_t = _step_pose(estimate_r, estimate_t, step)
            moved = linearise_pairs(
                source, target, source_cov, target_cov, moved_r, moved_t, robust_code, scale
            )
            usable = moved[4]
            if usable and moved[0] <= cost:  # False for NaN
                estimate_r, estimate_t = moved_r, moved_t
                cost, hessian, gradient, squared = moved[0], moved[1], moved[2], moved[3]
                damping = max(damping * 0.1, 1e-9)
                steps += 1
                continue
        if usable and size < settled_step:
            break
        damping *= 10.0
        rejected += 1
    return estimate_r, estimate_t, cost, hessian, gradient, squared, steps
