"""Combining the keyframe measurement with the chain through the previous frame."""

from __future__ import annotations

import numpy as np

from estimator.geometry import invert_pose, make_pose, quat_to_matrix, rotation_vector_to_quat
from estimator.odometry.chains import (
    chain_covariance,
    fuse_poses,
    inverse_covariance,
    perturbed,
    pose_difference,
)


def _pose(rotvec: list[float], translation: list[float]) -> np.ndarray:
    return make_pose(quat_to_matrix(rotation_vector_to_quat(np.array(rotvec))), translation)


def _covariance(rng: np.random.Generator, rotation_sigma: float, translation_sigma: float):
    shape = rng.normal(size=(6, 6)) * 0.3 + np.eye(6)
    scale = np.diag([rotation_sigma] * 3 + [translation_sigma] * 3)
    return scale @ shape @ shape.T @ scale


def test_pose_difference_inverts_the_right_perturbation() -> None:
    pose = _pose([0.3, -0.2, 0.5], [1.0, -2.0, 0.5])
    xi = np.array([0.01, -0.02, 0.03, 0.1, 0.2, -0.05])
    assert np.allclose(pose_difference(pose, perturbed(pose, xi)), xi, atol=1e-12)


def test_chain_covariance_matches_sampled_chains() -> None:
    rng = np.random.default_rng(3)
    first, second = (
        _pose([0.1, 0.4, -0.2], [0.3, 0.1, -0.2]),
        _pose([0.2, -0.1, 0.3], [0.5, -0.4, 1.2]),
    )
    first_cov, second_cov = _covariance(rng, 2e-3, 3e-3), _covariance(rng, 1e-3, 2e-3)
    chained = first @ second
    samples = []
    for a, b in zip(
        rng.multivariate_normal(np.zeros(6), first_cov, 4000),
        rng.multivariate_normal(np.zeros(6), second_cov, 4000),
        strict=True,
    ):
        samples.append(pose_difference(chained, perturbed(first, a) @ perturbed(second, b)))
    sampled = np.cov(np.array(samples).T)
    predicted = chain_covariance(first_cov, second, second_cov)
    # 4,000 samples: a variance is known to about 2 %
    scale = np.sqrt(np.outer(np.diag(predicted), np.diag(predicted)))
    assert np.abs(sampled - predicted).max() / scale.max() < 0.08
    assert np.abs(np.diag(sampled) / np.diag(predicted) - 1).max() < 0.08


def test_fusion_weighs_by_covariance_and_beats_either_estimate() -> None:
    rng = np.random.default_rng(7)
    truth = _pose([0.05, -0.3, 0.1], [0.2, 0.0, 0.4])
    first_cov, second_cov = _covariance(rng, 1e-3, 2e-3), _covariance(rng, 3e-3, 1e-3)
    errors, first_errors, second_errors = [], [], []
    for _ in range(1500):
        first = perturbed(truth, rng.multivariate_normal(np.zeros(6), first_cov))
        second = perturbed(truth, rng.multivariate_normal(np.zeros(6), second_cov))
        fused = fuse_poses(first, first_cov, second, second_cov)
        assert fused is not None
        errors.append(pose_difference(truth, fused[0]))
        first_errors.append(pose_difference(truth, first))
        second_errors.append(pose_difference(truth, second))
    expected = np.linalg.inv(np.linalg.inv(first_cov) + np.linalg.inv(second_cov))
    assert np.allclose(fused[1], expected)
    sampled = np.cov(np.array(errors).T)
    assert np.abs(np.diag(sampled) / np.diag(expected) - 1).max() < 0.15
    for other in (first_errors, second_errors):
        assert (np.diag(sampled) < np.diag(np.cov(np.array(other).T))).all()


def test_fusion_of_equal_estimates_is_the_midpoint_and_refuses_bad_covariances() -> None:
    truth = _pose([0.2, 0.1, -0.1], [1.0, 2.0, 3.0])
    offset = np.array([0.02, 0.0, -0.01, 0.04, -0.02, 0.0])
    covariance = np.diag([1e-6] * 3 + [1e-4] * 3)
    fused = fuse_poses(perturbed(truth, offset), covariance, perturbed(truth, -offset), covariance)
    assert fused is not None
    assert np.allclose(pose_difference(truth, fused[0]), 0.0, atol=1e-4)
    assert np.allclose(fused[1], covariance / 2)
    assert fuse_poses(truth, np.zeros((6, 6)), truth, covariance) is None
    assert fuse_poses(truth, -covariance, truth, covariance) is None


def test_inverse_covariance_matches_sampled_inverses() -> None:
    rng = np.random.default_rng(5)
    pose = _pose([0.3, -0.5, 0.2], [0.4, -0.3, 1.5])
    covariance = _covariance(rng, 2e-3, 3e-3)
    inverse = invert_pose(pose)
    samples = np.array(
        [
            pose_difference(inverse, invert_pose(perturbed(pose, xi)))
            for xi in rng.multivariate_normal(np.zeros(6), covariance, 4000)
        ]
    )
    predicted = inverse_covariance(pose, covariance)
    sampled = np.cov(samples.T)
    scale = np.sqrt(np.outer(np.diag(predicted), np.diag(predicted)))
    assert np.abs(sampled - predicted).max() / scale.max() < 0.08
    assert np.abs(np.diag(sampled) / np.diag(predicted) - 1).max() < 0.08
