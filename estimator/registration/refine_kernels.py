"""Compiled per-pair loop of the Mahalanobis refinement (``refine.py``).

A frame refines about a hundred pairs, eight or so times; at that size the NumPy version spent
its time in some twenty array calls per linearisation, not in arithmetic. One compiled pass
over the pairs forms the same quantities: the source-frame residual r' = R^T (t_j - t) - s_j,
its covariance C_src + R^T C_tgt R and that covariance's inverse (adjugate, as the NumPy
version), the robust weight, and the sums J^T W J and J^T W r' with J = [[s]x, -I].
"""

from __future__ import annotations

import numba
import numpy as np

__all__ = ["ROBUST_CODES", "linearise_pairs", "score_outer_products", "squared_distances"]

ROBUST_CODES = {"none": 0, "cauchy": 1, "huber": 2}


@numba.njit(cache=True, nogil=True, inline="always")
def _pair(source, target, source_cov, target_cov, rotation, translation, n, residual, info):
    """Fill ``residual`` (3,) and ``info`` (3, 3) of pair ``n``; False for a singular one."""
    difference = np.empty(3)
    for k in range(3):
        difference[k] = target[n, k] - translation[k]
    for i in range(3):
        value = 0.0
        for k in range(3):
            value += difference[k] * rotation[k, i]
        residual[i] = value - source[n, i]
    # A = C_tgt R, then R^T A; plus C_src.
    product = np.empty((3, 3))
    for k in range(3):
        for j in range(3):
            value = 0.0
            for m in range(3):
                value += target_cov[n, k, m] * rotation[m, j]
            product[k, j] = value
    covariance = np.empty((3, 3))
    for i in range(3):
        for j in range(3):
            value = 0.0
            for k in range(3):
                value += rotation[k, i] * product[k, j]
            covariance[i, j] = source_cov[n, i, j] + value
    a, b, c = covariance[0, 0], covariance[0, 1], covariance[0, 2]
    d, e, f = covariance[1, 1], covariance[1, 2], covariance[2, 2]
    cofactor_a, cofactor_b, cofactor_c = d * f - e * e, c * e - b * f, b * e - c * d
    determinant = a * cofactor_a + b * cofactor_b + c * cofactor_c
    if not abs(determinant) > 0.0:
        return False
    info[0, 0], info[0, 1], info[0, 2] = cofactor_a, cofactor_b, cofactor_c
    info[1, 1], info[1, 2], info[2, 2] = a * f - c * c, b * c - a * e, a * d - b * b
    info[1, 0], info[2, 0], info[2, 1] = cofactor_b, cofactor_c, info[1, 2]
    for i in range(3):
        for j in range(3):
            info[i, j] /= determinant
    return True


@numba.njit(cache=True, nogil=True)
def _quadratic_form(info, residual):
    """r^T W r for one pair's 3x3 information matrix."""
    value = 0.0
    for i in range(3):
        whitened = 0.0
        for j in range(3):
            whitened += info[i, j] * residual[j]
        value += residual[i] * whitened
    return value


@numba.njit(cache=True, nogil=True)
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


@numba.njit(cache=True, nogil=True)
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
                    total += info[i, k] * jacobian[k, j]
                weighted[i, j] = total * weight
        for a in range(6):
            for b in range(6):
                total = 0.0
                for k in range(3):
                    total += jacobian[k, a] * weighted[k, b]
                hessian[a, b] += total
            total = 0.0
            for k in range(3):
                total += weighted[k, a] * residual[k]
            gradient[a] += total
    return cost, hessian, gradient, squared, True


@numba.njit(cache=True, nogil=True)
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
