"""Mahalanobis pose refinement: exact on exact data, better than Kabsch on stereo-like noise,
a calibrated covariance, and the input pose back (flagged) on data it cannot use."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from estimator.formats.calibration import Rectification, StereoRig
from estimator.frontend.stereo import point_covariances
from estimator.geometry import kabsch, rotation_angle_deg
from estimator.registration.refine import (
    refine_pose_mahalanobis,
    residual_spread,
    squared_mahalanobis,
)

# A stereo rig like EuRoC's: 460 px focal length, 11 cm baseline.
FOCAL, BASELINE = 460.0, 0.11
SIGMA_U, SIGMA_D = 0.3, 0.5  # pixels


def _rectification() -> Rectification:
    """The rig above, already rectified: the covariances need its focal length and baseline."""
    camera = {
        "width": 752, "height": 480, "fx": FOCAL, "fy": FOCAL, "cx": 376.0, "cy": 240.0,
        "distortion_model": "none", "distortion": [],
    }  # fmt: skip
    right = np.eye(4)
    right[0, 3] = BASELINE
    rig = StereoRig.from_dict(
        {
            "left": {**camera, "T_BS": np.eye(4).tolist()},
            "right": {**camera, "T_BS": right.tolist()},
        }
    )
    return rig.rectification


RECTIFICATION = _rectification()


def _covariances(points: np.ndarray) -> np.ndarray:
    """Ray-aligned stereo covariances as the front end gives them: (Z/f)^2 sigma_u^2 across,
    (sigma_d Z/(f b))^2 p p^T along the ray."""
    return point_covariances(points, RECTIFICATION, SIGMA_U, SIGMA_U, SIGMA_D)


def _scene(rng: np.random.Generator, count: int = 150):
    """Points 2-10 m in front of a camera, seen again after a small random motion."""
    depth = rng.uniform(2.0, 10.0, count)
    lateral = rng.uniform(-1.0, 1.0, (count, 2)) * [0.75, 0.5] * depth[:, None]
    source = np.column_stack([lateral, depth])
    rotation = Rotation.from_rotvec(rng.normal(0.0, 0.05, 3)).as_matrix()
    translation = rng.normal(0.0, 0.1, 3)
    target = source @ rotation.T + translation
    return source, target, rotation, translation


def _noisy(points: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    factor = np.linalg.cholesky(_covariances(points))
    return points + np.einsum("nij,nj->ni", factor, rng.normal(size=points.shape))


def _rotation_error(estimate: np.ndarray, truth: np.ndarray) -> float:
    return float(np.radians(rotation_angle_deg(truth.T @ estimate)))


def test_exact_data_is_recovered_from_a_distant_start() -> None:
    rng = np.random.default_rng(0)
    source, target, rotation, translation = _scene(rng)
    start = Rotation.from_rotvec([0.05, -0.04, 0.03]).as_matrix() @ rotation
    result = refine_pose_mahalanobis(
        source,
        target,
        _covariances(source),
        _covariances(target),
        start,
        translation + np.array([0.1, -0.05, 0.2]),
        iterations=20,
    )
    assert result.success, result.message
    assert _rotation_error(result.rotation, rotation) < 1e-9
    np.testing.assert_allclose(result.translation, translation, atol=1e-8)
    assert result.final_cost < 1e-12 <= result.initial_cost
    assert result.covariance is not None and result.covariance.shape == (6, 6)
    assert np.all(np.linalg.eigvalsh(result.covariance) > 0)


def test_refinement_beats_kabsch_on_stereo_noise() -> None:
    """Depth noise along the rays misleads an isotropic fit; the ML fit discounts it."""
    kabsch_errors, refined_errors = [], []
    kabsch_translation, refined_translation = [], []
    for seed in range(60):
        rng = np.random.default_rng(seed)
        source, target, rotation, translation = _scene(rng)
        source, target = _noisy(source, rng), _noisy(target, rng)
        start_r, start_t = kabsch(source, target)[:2]
        result = refine_pose_mahalanobis(
            source, target, _covariances(source), _covariances(target), start_r, start_t
        )
        assert result.success, result.message
        assert np.isfinite(result.rotation).all() and np.isfinite(result.translation).all()
        assert result.final_cost <= result.initial_cost
        kabsch_errors.append(_rotation_error(start_r, rotation))
        refined_errors.append(_rotation_error(result.rotation, rotation))
        kabsch_translation.append(np.linalg.norm(start_t - translation))
        refined_translation.append(np.linalg.norm(result.translation - translation))
    # Measured: ~40x lower in rotation, ~80x in translation (the far points dominate an
    # isotropic fit); ask for 30 % lower.
    assert np.mean(refined_errors) < 0.7 * np.mean(kabsch_errors)
    assert np.mean(refined_translation) < 0.7 * np.mean(kabsch_translation)


def test_covariance_matches_the_scatter_of_the_estimates() -> None:
    """With Gaussian noise as modelled, the pose error's Mahalanobis norm is chi-square(6).

    The covariances are those of the true points: evaluated at the noisy points (all a
    pipeline has) the far points' metre-sized depth errors inflate the mean to ~10.
    """
    rng = np.random.default_rng(1)
    source, target, rotation, translation = _scene(rng, count=80)
    covariances = (_covariances(source), _covariances(target))
    squared = []
    for _ in range(300):
        result = refine_pose_mahalanobis(
            _noisy(source, rng),
            _noisy(target, rng),
            *covariances,
            rotation,
            translation,
            robust="none",
        )
        assert result.success and result.covariance is not None
        # Right perturbation: R = R_true Exp(omega), t = t_true + R_true v.
        omega = Rotation.from_matrix(rotation.T @ result.rotation).as_rotvec()
        v = rotation.T @ (result.translation - translation)
        error = np.concatenate([omega, v])
        squared.append(error @ np.linalg.solve(result.covariance, error))
    # Mean 6 for a calibrated covariance (measured 6.3); the mean's standard error is ~0.2.
    assert 5.3 < np.mean(squared) < 7.2


def test_cauchy_weight_resists_leftover_outliers() -> None:
    gross_robust, gross_plain = [], []
    for seed in range(20):
        rng = np.random.default_rng(100 + seed)
        source, target, rotation, _ = _scene(rng)
        source, target = _noisy(source, rng), _noisy(target, rng)
        bad = rng.choice(len(target), 8, replace=False)
        target[bad] += rng.normal(0.0, 0.3, (8, 3))  # wrong matches that passed as inliers
        start_r, start_t = kabsch(source, target)[:2]
        covariances = (_covariances(source), _covariances(target))
        robust = refine_pose_mahalanobis(source, target, *covariances, start_r, start_t)
        plain = refine_pose_mahalanobis(
            source, target, *covariances, start_r, start_t, robust="none"
        )
        gross_robust.append(_rotation_error(robust.rotation, rotation))
        gross_plain.append(_rotation_error(plain.rotation, rotation))
    assert np.mean(gross_robust) < 0.5 * np.mean(gross_plain)  # measured 0.23


@pytest.mark.parametrize("kind", ["cauchy", "huber", "none"])
def test_every_robust_weight_converges_on_clean_data(kind: str) -> None:
    rng = np.random.default_rng(7)
    source, target, rotation, _ = _scene(rng)
    source, target = _noisy(source, rng), _noisy(target, rng)
    start_r, start_t = kabsch(source, target)[:2]
    result = refine_pose_mahalanobis(
        source, target, _covariances(source), _covariances(target), start_r, start_t, robust=kind
    )
    assert result.success
    assert _rotation_error(result.rotation, rotation) < _rotation_error(start_r, rotation)


def _assert_unchanged(result, rotation: np.ndarray, translation: np.ndarray) -> None:
    assert not result.success
    assert result.covariance is None
    assert result.message
    np.testing.assert_array_equal(result.rotation, rotation)
    np.testing.assert_array_equal(result.translation, translation)


def test_collinear_points_leave_the_pose_unchanged_and_flagged() -> None:
    rng = np.random.default_rng(3)
    line = np.outer(np.linspace(2.0, 8.0, 40), [0.1, 0.2, 1.0]) + np.array([0.3, -0.2, 0.0])
    rotation = Rotation.from_rotvec([0.01, 0.02, -0.01]).as_matrix()
    translation = np.array([0.05, 0.0, 0.1])
    target = line @ rotation.T + translation
    covariance = np.broadcast_to(np.eye(3) * 1e-6, (len(line), 3, 3))
    start = Rotation.from_rotvec(rng.normal(0, 0.01, 3)).as_matrix() @ rotation
    result = refine_pose_mahalanobis(line, target, covariance, covariance, start, translation)
    _assert_unchanged(result, start, translation)
    assert "ill-conditioned" in result.message


def test_bad_input_is_returned_unchanged() -> None:
    rng = np.random.default_rng(5)
    source, target, rotation, translation = _scene(rng, count=20)
    covariance = _covariances(source)
    two = refine_pose_mahalanobis(
        source[:2], target[:2], covariance[:2], covariance[:2], rotation, translation
    )
    _assert_unchanged(two, rotation, translation)
    with_nan = target.copy()
    with_nan[4, 1] = np.nan
    nan = refine_pose_mahalanobis(source, with_nan, covariance, covariance, rotation, translation)
    _assert_unchanged(nan, rotation, translation)
    zero = np.zeros_like(covariance)
    singular = refine_pose_mahalanobis(source, target, zero, zero, rotation, translation)
    _assert_unchanged(singular, rotation, translation)
    with pytest.raises(ValueError, match="source_cov"):
        refine_pose_mahalanobis(source, target, covariance[:3], covariance, rotation, translation)


def test_refinement_is_deterministic() -> None:
    rng = np.random.default_rng(9)
    source, target, rotation, translation = _scene(rng)
    source, target = _noisy(source, rng), _noisy(target, rng)
    arguments = (source, target, _covariances(source), _covariances(target), rotation, translation)
    first, second = refine_pose_mahalanobis(*arguments), refine_pose_mahalanobis(*arguments)
    np.testing.assert_array_equal(first.rotation, second.rotation)
    np.testing.assert_array_equal(first.translation, second.translation)


def test_the_kernel_in_the_residuals_own_spread_resists_a_coherent_cluster() -> None:
    """Covariances 8x too generous (a session's first frames on the noise prior) make a
    cluster of pairs that moved together (a car) look consistent: a kernel in covariance
    sigmas weighs it almost fully, one scaled by ``residual_spread`` weighs it down."""
    fixed_errors, spread_errors, spreads = [], [], []
    for seed in range(20):
        rng = np.random.default_rng(300 + seed)
        source, target, rotation, translation = _scene(rng)
        source, target = _noisy(source, rng), _noisy(target, rng)
        car = np.argsort(source[:, 0])[:20]  # one side of the view, 13 % of the pairs
        target[car] += source[car] - (source[car] @ rotation.T + translation)  # moved along
        generous = (64.0 * _covariances(source), 64.0 * _covariances(target))
        # Started at the majority's motion, where the registration's support vote puts it.
        start_r, start_t = rotation, translation
        spread = residual_spread(squared_mahalanobis(source, target, *generous, start_r, start_t))
        fixed = refine_pose_mahalanobis(
            source, target, *generous, start_r, start_t, robust_scale=6.0
        )
        scaled = refine_pose_mahalanobis(
            source, target, *generous, start_r, start_t, robust_scale=6.0 * spread
        )
        spreads.append(spread)
        fixed_errors.append(np.linalg.norm(fixed.translation - translation))
        spread_errors.append(np.linalg.norm(scaled.translation - translation))
    assert 0.1 < np.median(spreads) < 0.2  # 1/8 of the covariance sigmas (measured 0.136)
    assert np.mean(spread_errors) < 0.5 * np.mean(fixed_errors)  # measured 2.1 and 5.9 mm


def test_the_spread_is_one_when_the_covariances_fit() -> None:
    spreads = []
    for seed in range(20):
        rng = np.random.default_rng(400 + seed)
        source, target, rotation, translation = _scene(rng)
        source, target = _noisy(source, rng), _noisy(target, rng)
        covariances = (_covariances(source), _covariances(target))
        squared = squared_mahalanobis(source, target, *covariances, rotation, translation)
        spreads.append(residual_spread(squared))
    assert np.median(spreads) == pytest.approx(1.0, abs=0.1)
    assert residual_spread(squared[:5]) == 1.0  # too few pairs to measure
