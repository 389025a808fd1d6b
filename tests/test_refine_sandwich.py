"""The refinement's robust sandwich covariance follows the noise the residuals show: heavy
tails and a noise level other than the point covariances say (registration/refine.py)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from test_refine import _covariances  # EuRoC-like rig; 0.3 px pixel, 0.5 px disparity noise

from estimator.registration.refine import refine_pose_mahalanobis
from estimator.registration.refine_kernels import ROBUST_CODES, score_outer_products


def _noise(points: np.ndarray, rng: np.random.Generator, scale: float, tail: float) -> np.ndarray:
    """Noise with the modelled covariance times ``scale``^2; a tenth of the points (blur,
    edges) ``tail`` times larger still."""
    factor = np.linalg.cholesky(_covariances(points))
    size = np.where(rng.random(len(points)) < 0.1, tail, 1.0) * scale
    return np.einsum("nij,nj->ni", factor, rng.normal(size=points.shape)) * size[:, None]


def _nees_per_dof(
    model: str, scale: float, tail: float, robust: str = "cauchy", trials: int = 200
) -> float:
    """Mean NEES per DOF of the refined pose over ``trials`` noisy draws of one scene."""
    rng = np.random.default_rng(11)
    depth = rng.uniform(2.0, 10.0, 120)
    lateral = rng.uniform(-1.0, 1.0, (120, 2)) * [0.75, 0.5] * depth[:, None]
    source = np.column_stack([lateral, depth])
    rotation = Rotation.from_rotvec([0.02, -0.05, 0.01]).as_matrix()
    translation = np.array([0.1, 0.02, -0.05])
    target = source @ rotation.T + translation
    covariances = (_covariances(source), _covariances(target))
    values = []
    for _ in range(trials):
        result = refine_pose_mahalanobis(
            source + _noise(source, rng, scale, tail),
            target + _noise(target, rng, scale, tail),
            *covariances,
            rotation,
            translation,
            robust=robust,  # type: ignore[arg-type]
            sandwich=True,
        )
        covariance = result.sandwich_covariance if model == "sandwich" else result.covariance
        assert result.success and covariance is not None
        omega = Rotation.from_matrix(rotation.T @ result.rotation).as_rotvec()
        error = np.concatenate([omega, rotation.T @ (result.translation - translation)])
        values.append(error @ np.linalg.solve(covariance, error) / 6.0)
    return float(np.mean(values))


@pytest.mark.parametrize(
    ("robust", "scale", "tail"),
    [("cauchy", 1.0, 1.0), ("cauchy", 1.0, 4.0), ("cauchy", 3.0, 4.0), ("none", 2.0, 4.0)],
)
def test_sandwich_follows_the_noise_the_residuals_show(
    robust: str, scale: float, tail: float
) -> None:
    """Noise as modelled, a tenth of the pairs 4x noisier (blur, edges), and all of it 2-3x
    larger than the point covariances say: the sandwich stays consistent (measured 1.2-1.4;
    a finite-sample sandwich is a little small where a few near points lever the pose)."""
    assert 0.6 <= _nees_per_dof("sandwich", scale, tail, robust) <= 1.6


def test_the_median_scale_misses_heavy_tails_the_sandwich_sees() -> None:
    """Without a kernel the heavy-tailed pairs weigh fully: the median of the distances does
    not see them, the pose does (measured: median-scaled 2.4, sandwich 1.25)."""
    median = _nees_per_dof("median", 1.0, 4.0, robust="none")
    sandwich = _nees_per_dof("sandwich", 1.0, 4.0, robust="none")
    assert median > 1.8
    assert sandwich < 0.7 * median


def test_too_few_pairs_give_no_sandwich() -> None:
    rng = np.random.default_rng(2)
    source = np.column_stack([rng.uniform(-1, 1, (10, 2)), rng.uniform(2, 6, 10)])
    target = source + 0.01 * rng.normal(size=source.shape)
    covariance = _covariances(source)
    args = (source, target, covariance, covariance, np.eye(3), np.zeros(3))
    few = refine_pose_mahalanobis(*args, sandwich=True)
    assert few.success and few.covariance is not None and few.sandwich_covariance is None
    more = refine_pose_mahalanobis(
        *(np.concatenate([a, a]) for a in args[:4]), *args[4:], sandwich=True
    )
    assert more.sandwich_covariance is not None
    assert refine_pose_mahalanobis(*args).sandwich_covariance is None  # not asked for


@pytest.mark.parametrize("robust", ["none", "cauchy", "huber"])
def test_compiled_sums_match_the_per_pair_formula(robust: str) -> None:
    """B = sum g g^T and the kernel's curvature term D against a per-pair NumPy version."""
    rng = np.random.default_rng(4)
    source = np.column_stack([rng.uniform(-2, 2, (50, 2)), rng.uniform(2, 8, 50)])
    rotation = Rotation.from_rotvec([0.03, -0.02, 0.05]).as_matrix()
    translation = np.array([0.2, -0.1, 0.05])
    covariance = _covariances(source)
    target = source @ rotation.T + translation + 0.05 * rng.standard_t(2, source.shape)
    scale = 3.0
    meat, curvature, regular = score_outer_products(
        source, target, covariance, covariance, rotation, translation, ROBUST_CODES[robust], scale
    )
    assert regular
    expected_meat, expected_curvature = np.zeros((6, 6)), np.zeros((6, 6))
    for s, t, c in zip(source, target, covariance, strict=True):
        residual = rotation.T @ (t - translation) - s
        info = np.linalg.inv(c + rotation.T @ c @ rotation)
        squared = residual @ info @ residual
        weight, loss = 1.0, 0.0
        if robust == "cauchy":
            weight, loss = 1.0 / (1.0 + squared / scale**2), 2.0 / scale**2
        elif robust == "huber" and np.sqrt(squared) > scale:
            weight, loss = scale / np.sqrt(squared), 1.0 / (scale * np.sqrt(squared))
        skew = np.array([[0, -s[2], s[1]], [s[2], 0, -s[0]], [-s[1], s[0], 0]])
        jacobian = np.hstack([skew, -np.eye(3)])
        score = weight * jacobian.T @ info @ residual
        expected_meat += np.outer(score, score)
        expected_curvature += loss * np.outer(score, score)
    np.testing.assert_allclose(meat, expected_meat, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(curvature, expected_curvature, rtol=1e-9, atol=1e-12)
