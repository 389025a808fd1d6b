"""The synthetic registration problems: visibility, exact outlier fraction, the model, seeds."""

from __future__ import annotations

import numpy as np
import pytest

from estimator.geometry import quat_to_matrix, rotation_vector_to_quat
from estimator.rendered.simulation import (
    DEFAULT_SCENE,
    camera_matrix,
    rotation_error_deg,
    simulate_pair,
    translation_error,
    visible,
)


def _intrinsics() -> np.ndarray:
    return camera_matrix(DEFAULT_SCENE["focal"], DEFAULT_SCENE["width"], DEFAULT_SCENE["height"])


def test_kept_points_are_visible_in_both_images() -> None:
    pair = simulate_pair(noise_sigma=0.0, rng=3)
    k = _intrinsics()
    w, h = DEFAULT_SCENE["width"], DEFAULT_SCENE["height"]
    assert visible(pair.source, k, w, h).all()
    clean_target = pair.source @ pair.rotation.T + pair.translation
    assert visible(clean_target, k, w, h).all()


def test_visibility_rejects_points_behind_or_outside() -> None:
    k = _intrinsics()
    points = np.array([[0.0, 0.0, 5.0], [0.0, 0.0, -5.0], [100.0, 0.0, 5.0], [0.0, 0.0, 0.0]])
    assert visible(points, k, 640, 480).tolist() == [True, False, False, False]


def test_about_275_of_400_points_survive_on_average() -> None:
    counts = [len(simulate_pair(n_points=400, rng=seed).source) for seed in range(200)]
    assert 255 <= np.mean(counts) <= 295
    assert max(counts) <= 400


@pytest.mark.parametrize("ratio", [0.0, 0.2, 0.5, 0.9, 0.95, 1.0])
def test_outlier_fraction_is_exact_and_outliers_are_wrong_matches(ratio: float) -> None:
    pair = simulate_pair(noise_sigma=0.0, outlier_ratio=ratio, rng=11)
    count = len(pair.source)
    assert (~pair.inlier_mask).sum() == round(ratio * count)
    predicted = pair.source @ pair.rotation.T + pair.translation
    outliers = ~pair.inlier_mask
    # Each outlier target is exactly some other point's (clean) target, never its own.
    matches = np.linalg.norm(pair.target[outliers, None, :] - predicted[None], axis=2) < 1e-9
    assert matches.any(axis=1).all()
    own = np.flatnonzero(outliers)
    assert not matches[np.arange(len(own)), own].any()


def test_inliers_follow_the_model_within_the_noise() -> None:
    sigma = 0.02
    pair = simulate_pair(noise_sigma=sigma, outlier_ratio=0.3, rng=5)
    residual = pair.target - (pair.source @ pair.rotation.T + pair.translation)
    inlier_residual = residual[pair.inlier_mask]
    assert abs(inlier_residual.std() - sigma) < 0.2 * sigma
    assert np.abs(inlier_residual).max() < 5 * sigma
    np.testing.assert_allclose(pair.rotation @ pair.rotation.T, np.eye(3), atol=1e-12)
    assert np.isclose(np.linalg.det(pair.rotation), 1.0)


def test_motion_stays_in_the_documented_ranges() -> None:
    for seed in range(50):
        pair = simulate_pair(n_points=10, rng=seed)
        assert rotation_error_deg(pair.rotation, np.eye(3)) <= DEFAULT_SCENE["max_rotation_deg"]
        assert np.linalg.norm(pair.translation) <= DEFAULT_SCENE["max_translation_m"]


def test_same_seed_same_problem_different_seed_different_problem() -> None:
    a = simulate_pair(outlier_ratio=0.4, rng=42)
    b = simulate_pair(outlier_ratio=0.4, rng=42)
    c = simulate_pair(outlier_ratio=0.4, rng=43)
    for field in ("source", "target", "rotation", "translation", "inlier_mask"):
        np.testing.assert_array_equal(getattr(a, field), getattr(b, field))
    assert not np.array_equal(a.rotation, c.rotation)


def test_scene_overrides_and_bad_options() -> None:
    narrow = simulate_pair(rng=1, max_rotation_deg=0.0, max_translation_m=0.0)
    np.testing.assert_allclose(narrow.rotation, np.eye(3), atol=1e-12)
    assert len(narrow.source) == 400  # no motion: everything stays visible
    with pytest.raises(ValueError, match="unknown scene option"):
        simulate_pair(focal_length=3.0)
    with pytest.raises(ValueError, match="outlier_ratio"):
        simulate_pair(outlier_ratio=1.5)
    with pytest.raises(ValueError, match="noise_sigma"):
        simulate_pair(noise_sigma=-1.0)


def test_error_helpers() -> None:
    rotation = quat_to_matrix(rotation_vector_to_quat(np.radians([0.0, 0.0, 2.0])))
    assert np.isclose(rotation_error_deg(rotation, np.eye(3)), 2.0)
    assert np.isclose(rotation_error_deg(np.eye(3), rotation), 2.0)
    assert np.isclose(translation_error([1.0, 2.0, 2.0], [0.0, 0.0, 0.0]), 3.0)


def test_depth_noise_grows_with_depth_squared_along_the_rays() -> None:
    sigma_at_1m = 0.001
    pair = simulate_pair(2000, sigma_at_1m, 0.0, rng=21, depth_noise=True, min_depth_m=1.0)
    clean_target = pair.source @ pair.rotation.T + pair.translation
    residual = np.linalg.norm(pair.target - clean_target, axis=1)
    assert pair.noise_sigmas is not None and pair.noise_sigmas.shape == (len(pair.source),)
    # Both points slide along their rays with std sigma Z^2: E r^2 = sum of both sigma^2
    # (target noise alone would give a mean of ~0.5 here).
    normalised = residual / pair.noise_sigmas
    assert 0.9 < np.mean(normalised**2) < 1.1
    far = pair.source[:, 2] > 7.0
    near = pair.source[:, 2] < 2.0
    assert np.median(residual[far]) > 10.0 * np.median(residual[near])


def test_depth_noise_is_off_by_default() -> None:
    assert simulate_pair(rng=4).noise_sigmas is None
