"""The compiled linearisation equals the NumPy formulas it replaced (to rounding)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from estimator.geometry import quat_to_matrix, rotation_vector_to_quat, skew
from estimator.registration.refine import squared_mahalanobis
from estimator.registration.refine_kernels import (
    ROBUST_CODES,
    levenberg_marquardt,
    linearise_pairs,
    scaled_condition,
    solve_pivoted,
)


def _reference(source, target, source_cov, target_cov, rotation, translation, kind, scale):
    """The stacked-array version: residual and covariance in the source frame, then sums."""
    residual = (target - translation) @ rotation - source
    moved = np.einsum("ki,nkl,lj->nij", rotation, target_cov, rotation)
    information = np.linalg.inv(source_cov + moved)
    squared = np.einsum("ni,nij,nj->n", residual, information, residual)
    c2 = scale * scale
    if kind == "cauchy":
        rho, weight = c2 * np.log1p(squared / c2), 1.0 / (1.0 + squared / c2)
    elif kind == "huber":
        distance = np.sqrt(squared)
        outside = distance > scale
        rho = np.where(outside, 2.0 * scale * distance - c2, squared)
        weight = np.where(outside, scale / distance, 1.0)
    else:
        rho, weight = squared, np.ones_like(squared)
    jacobian = np.concatenate([skew(source), np.broadcast_to(-np.eye(3), (len(source), 3, 3))], 2)
    weighted = information @ jacobian * weight[:, None, None]
    hessian = np.einsum("nki,nkj->ij", jacobian, weighted)
    gradient = np.einsum("nki,nk->i", weighted, residual)
    return rho.sum(), hessian, gradient, squared


def _pairs(count: int, seed: int):
    rng = np.random.default_rng(seed)
    source = rng.normal(size=(count, 3)) * 3.0 + [0.0, 0.0, 6.0]
    a = rng.normal(size=(count, 3, 3)) * 0.02
    b = rng.normal(size=(count, 3, 3)) * 0.02
    source_cov = a @ a.transpose(0, 2, 1) + 1e-4 * np.eye(3)
    target_cov = b @ b.transpose(0, 2, 1) + 1e-4 * np.eye(3)
    rotation = quat_to_matrix(rotation_vector_to_quat(rng.normal(size=3) * 0.2))
    translation = rng.normal(size=3) * 0.3
    target = source @ rotation.T + translation + rng.normal(size=(count, 3)) * 0.05
    target[: count // 5] += rng.normal(size=(count // 5, 3))  # outliers: the robust tails
    return source, target, source_cov, target_cov, rotation, translation


@pytest.mark.parametrize("kind", ["cauchy", "huber", "none"])
def test_the_kernel_equals_the_array_formulas(kind: str) -> None:
    for count, seed in ((3, 1), (97, 2), (400, 3)):
        data = _pairs(count, seed)
        cost, hessian, gradient, squared, regular = linearise_pairs(*data, ROBUST_CODES[kind], 1.5)
        assert regular
        expected = _reference(*data, kind, 1.5)
        assert cost == pytest.approx(expected[0], rel=1e-10)
        np.testing.assert_allclose(hessian, expected[1], rtol=1e-9, atol=1e-9 * abs(hessian).max())
        np.testing.assert_allclose(
            gradient, expected[2], rtol=1e-9, atol=1e-9 * abs(gradient).max()
        )
        np.testing.assert_allclose(squared, expected[3], rtol=1e-10)
        np.testing.assert_allclose(squared_mahalanobis(*data), expected[3], rtol=1e-10)


def test_a_singular_covariance_is_reported() -> None:
    source, target, source_cov, target_cov, rotation, translation = _pairs(10, 4)
    source_cov[4] = 0.0
    target_cov[4] = 0.0
    *_, regular = linearise_pairs(
        source, target, source_cov, target_cov, rotation, translation, 1, 3.0
    )
    assert not regular
    with pytest.raises(np.linalg.LinAlgError):
        squared_mahalanobis(source, target, source_cov, target_cov, rotation, translation)


def _looped_reference(source, target, source_cov, target_cov, rotation, translation, code, scale):
    """The kernel's arithmetic in plain Python floats, every product of the full 3x3 and 3x6
    matrices summed in order from 0.0 (no skipped zeros, no scalar shortcuts)."""
    jacobian = [[0.0] * 6 for _ in range(3)]
    for i in range(3):
        jacobian[i][3 + i] = -1.0
    hessian = [[0.0] * 6 for _ in range(6)]
    gradient, squared, cost, c2 = [0.0] * 6, [], 0.0, scale * scale
    r, t = rotation.tolist(), translation.tolist()
    for s, p, cs, ct in zip(source.tolist(), target.tolist(), source_cov.tolist(),
                            target_cov.tolist(), strict=True):  # fmt: skip
        difference = [p[k] - t[k] for k in range(3)]
        residual = []
        for i in range(3):
            value = 0.0
            for k in range(3):
                value += difference[k] * r[k][i]
            residual.append(value - s[i])
        product = [[0.0] * 3 for _ in range(3)]
        for k in range(3):
            for j in range(3):
                value = 0.0
                for m in range(3):
                    value += ct[k][m] * r[m][j]
                product[k][j] = value
        cov = [[0.0] * 3 for _ in range(3)]
        for i in range(3):
            for j in range(3):
                value = 0.0
                for k in range(3):
                    value += r[k][i] * product[k][j]
                cov[i][j] = cs[i][j] + value
        a, b, c, d, e, f = cov[0][0], cov[0][1], cov[0][2], cov[1][1], cov[1][2], cov[2][2]
        ca, cb, cc = d * f - e * e, c * e - b * f, b * e - c * d
        det = a * ca + b * cb + c * cc
        ce = b * c - a * e
        info = [[ca, cb, cc], [cb, a * f - c * c, ce], [cc, ce, a * d - b * b]]
        info = [[value / det for value in row] for row in info]
        value = 0.0
        for i in range(3):
            whitened = 0.0
            for j in range(3):
                whitened += info[i][j] * residual[j]
            value += residual[i] * whitened
        squared.append(value)
        if code == 1:
            cost += c2 * math.log1p(value / c2)
            weight = 1.0 / (1.0 + value / c2)
        elif code == 2 and math.sqrt(value) > scale:
            cost += 2.0 * scale * math.sqrt(value) - c2
            weight = scale / max(math.sqrt(value), 1e-300)
        else:
            cost += value
            weight = 1.0
        jacobian[0][1], jacobian[0][2] = -s[2], s[1]
        jacobian[1][0], jacobian[1][2] = s[2], -s[0]
        jacobian[2][0], jacobian[2][1] = -s[1], s[0]
        weighted = [[0.0] * 6 for _ in range(3)]
        for i in range(3):
            for j in range(6):
                total = 0.0
                for k in range(3):
                    total += info[i][k] * jacobian[k][j]
                weighted[i][j] = total * weight
        for m in range(6):
            for n in range(6):
                total = 0.0
                for k in range(3):
                    total += jacobian[k][m] * weighted[k][n]
                hessian[m][n] += total
            total = 0.0
            for k in range(3):
                total += weighted[k][m] * residual[k]
            gradient[m] += total
    return cost, np.array(hessian), np.array(gradient), np.array(squared)


@pytest.mark.parametrize("kind", ["cauchy", "huber", "none"])
def test_the_kernel_equals_the_full_loops_bit_for_bit(kind: str) -> None:
    """Skipping the Jacobian's structural zeros and keeping the 3x3 products in scalars
    changes no bit: a sum from 0.0 is unchanged by adding +-0.0."""
    for count, seed in ((3, 5), (60, 6), (200, 7)):
        data = _pairs(count, seed)
        data[0][0] = [0.0, -0.0, 2.5]  # a source point with zero coordinates
        cost, hessian, gradient, squared, regular = linearise_pairs(*data, ROBUST_CODES[kind], 1.5)
        expected = _looped_reference(*data, ROBUST_CODES[kind], 1.5)
        assert regular and cost == expected[0]
        np.testing.assert_array_equal(hessian, expected[1])
        np.testing.assert_array_equal(gradient, expected[2])
        np.testing.assert_array_equal(squared, expected[3])
        np.testing.assert_array_equal(squared_mahalanobis(*data), expected[3])


def test_the_scaled_condition_number_is_numpys() -> None:
    """The compiled conditioning test: NumPy's 2-norm condition number of the Jacobi-scaled
    matrix (to rounding), and inf where the scaling is undefined."""
    rng = np.random.default_rng(8)
    for exponent in (0, 4, 8, 12):
        a = rng.normal(size=(6, 6)) * np.logspace(0, exponent, 6)
        hessian = a @ a.T
        scale = 1.0 / np.sqrt(np.diag(hessian))
        expected = np.linalg.cond(hessian * scale[:, None] * scale[None, :])
        assert scaled_condition(hessian) == pytest.approx(expected, rel=1e-9)
    hessian = np.eye(6)
    hessian[2, 2] = 0.0
    assert scaled_condition(hessian) == np.inf
    hessian = np.eye(6)
    hessian[1, 4] = np.nan
    assert scaled_condition(hessian) == np.inf


def test_the_step_solver_equals_numpys_and_reports_a_singular_system() -> None:
    rng = np.random.default_rng(7)
    for _ in range(200):
        root = rng.normal(size=(6, 6))
        matrix = root @ root.T + 1e-3 * np.eye(6)
        rhs = rng.normal(size=6)
        solution, regular = solve_pivoted(matrix, rhs)
        assert regular
        np.testing.assert_allclose(solution, np.linalg.solve(matrix, rhs), rtol=1e-9, atol=1e-12)
    singular = np.ones((6, 6))
    assert not solve_pivoted(singular, np.ones(6))[1]
    assert not solve_pivoted(np.full((6, 6), np.nan), np.ones(6))[1]


def _numpy_levenberg_marquardt(data, rotation, translation, iterations, kind, scale):
    """The damped loop written with NumPy calls: keep a step that does not raise the cost."""
    code = ROBUST_CODES[kind]
    cost, hessian, gradient, _, _ = linearise_pairs(*data, rotation, translation, code, scale)
    damping, steps, rejected = 1e-4, 0, 0
    while steps < iterations and rejected < 6:
        step = np.linalg.solve(hessian + damping * np.diag(np.diag(hessian)), -gradient)
        if np.linalg.norm(step) < 1e-6:
            break
        moved_r = rotation @ quat_to_matrix(rotation_vector_to_quat(step[:3]))
        moved_t = translation + rotation @ step[3:]
        moved = linearise_pairs(*data, moved_r, moved_t, code, scale)
        if moved[0] <= cost:
            rotation, translation, (cost, hessian, gradient) = moved_r, moved_t, moved[:3]
            damping, steps = max(damping * 0.1, 1e-9), steps + 1
        elif np.linalg.norm(step) < 1e-5:
            break
        else:
            damping, rejected = damping * 10.0, rejected + 1
    return rotation, translation, cost, steps


@pytest.mark.parametrize("kind", ["cauchy", "huber", "none"])
def test_the_compiled_loop_follows_the_numpy_loop(kind: str) -> None:
    for count, seed in ((12, 4), (97, 5), (400, 6)):
        source, target, source_cov, target_cov, rotation, translation = _pairs(count, seed)
        data = (source, target, source_cov, target_cov)
        start_r = rotation @ quat_to_matrix(rotation_vector_to_quat(np.array([0.02, -0.01, 0.03])))
        start_t = translation + 0.05
        code = ROBUST_CODES[kind]
        first = linearise_pairs(*data, start_r, start_t, code, 2.0)
        result = levenberg_marquardt(
            *data, start_r, start_t, *first[:4], 8, code, 2.0, 6, 1e-6, 1e-5
        )  # fmt: skip
        expected = _numpy_levenberg_marquardt(data, start_r, start_t, 8, kind, 2.0)
        assert result[6] == expected[3] > 0
        assert result[2] == pytest.approx(expected[2], rel=1e-10)
        assert result[2] < first[0]
        np.testing.assert_allclose(result[0], expected[0], atol=1e-12)
        np.testing.assert_allclose(result[1], expected[1], atol=1e-12)
        # The returned linearisation is the one at the returned pose.
        again = linearise_pairs(*data, result[0], result[1], code, 2.0)
        assert again[0] == result[2]
        np.testing.assert_array_equal(again[1], result[3])
