"""The compiled linearisation equals the NumPy formulas it replaced (to rounding)."""

from __future__ import annotations

import numpy as np
import pytest

from estimator.geometry import quat_to_matrix, rotation_vector_to_quat, skew
from estimator.registration.refine import squared_mahalanobis
from estimator.registration.refine_kernels import ROBUST_CODES, linearise_pairs


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
