"""Properties every registration method must have, and robustness of the robust ones."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from estimator.geometry import (
    horn,
    is_degenerate,
    kabsch,
    quat_rotate,
    quat_to_matrix,
    rotation_vector_to_quat,
)
from estimator.registration import pso_support, rigidity, support_pairs, swarm_kernels
from estimator.registration.pso_support import weighted_horn
from estimator.registration.registry import available_methods, register
from estimator.registration.result import residual_norms
from estimator.registration.rigidity import (
    precise_ranking,
    rigidity_scores,
    rigidity_weights,
)
from estimator.rendered.simulation import rotation_error_deg, simulate_pair, translation_error

DATA = Path(__file__).parent / "data"
METHODS = ["pso-robust", "pso", "msac", "svd"]
ROBUST = ["pso-robust", "msac"]
seeds = st.integers(0, 2**31 - 1)


def _random_problem(
    seed: int, count: int, noise: float = 0.0, outliers: float = 0.0, max_angle: float = np.pi
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """A cloud in a 10 m box, any rotation up to ``max_angle``, wrong matches as outliers."""
    rng = np.random.default_rng(seed)
    source = rng.uniform(-5.0, 5.0, size=(count, 3)) + np.array([0.0, 0.0, 8.0])
    axis = rng.normal(size=3)
    rotvec = axis / np.linalg.norm(axis) * rng.uniform(0.0, max_angle)
    rotation = quat_to_matrix(rotation_vector_to_quat(rotvec))
    translation = rng.uniform(-2.0, 2.0, size=3)
    target = source @ rotation.T + translation + rng.normal(0.0, noise, size=(count, 3))
    inliers = np.ones(count, dtype=bool)
    wrong = rng.choice(count, size=round(outliers * count), replace=False)
    target[wrong] = target[(wrong + rng.integers(1, count, len(wrong))) % count]
    inliers[wrong] = False
    return source, target, rotation, translation, inliers


def _assert_valid(result, count: int) -> None:
    assert np.isfinite(result.rotation).all() and np.isfinite(result.quaternion).all()
    assert np.isclose(np.linalg.norm(result.quaternion), 1.0, atol=1e-12)
    assert np.isclose(np.linalg.det(result.rotation), 1.0, atol=1e-9)
    np.testing.assert_allclose(result.rotation, quat_to_matrix(result.quaternion), atol=1e-9)
    assert result.inliers.dtype == bool and result.inliers.shape == (count,)
    assert result.support == int(result.inliers.sum())


def test_all_methods_are_registered() -> None:
    assert set(METHODS) <= set(available_methods())


@pytest.mark.parametrize("method", [name for name in METHODS if name != "pso"])
@given(seed=seeds, count=st.integers(6, 80))
@settings(max_examples=12, deadline=None)
def test_exact_recovery_without_noise_or_outliers(method: str, seed: int, count: int) -> None:
    source, target, rotation, translation, _ = _random_problem(seed, count)
    result = register(source, target, method=method, seed=seed)
    _assert_valid(result, count)
    assert result.success, result.message
    assert rotation_error_deg(result.rotation, rotation) < 1e-6
    assert translation_error(result.translation, translation) < 1e-8
    assert result.inliers.all()


def test_faithful_pso_recovers_noise_free_poses_almost_always() -> None:
    """The paper's swarm is a global random search and misses ~0.3 % of these problems.

    Support ranks first (eq. 15), and pairs near the centroid support almost any rotation,
    so a swarm that has not yet reached the true basin can settle on 1-3 such supporters
    (seeds 1330 / 51 pairs and 1362793716 / 25 pairs are two). A per-example property test
    would fail at random; the rate over fixed seeds is the reproducible statement.
    """
    misses = 0
    for seed in range(300):
        count = 6 + seed % 75
        source, target, rotation, translation, _ = _random_problem(seed, count)
        result = register(source, target, method="pso", seed=seed)
        _assert_valid(result, count)
        exact = (
            result.success
            and rotation_error_deg(result.rotation, rotation) < 1e-6
            and translation_error(result.translation, translation) < 1e-8
            and result.inliers.all()
        )
        misses += not exact
    assert misses <= 3  # <= 1 %


@pytest.mark.parametrize("method", METHODS)
@given(seed=seeds)
@settings(max_examples=8, deadline=None)
def test_same_seed_gives_bitwise_equal_results(method: str, seed: int) -> None:
    source, target, *_ = _random_problem(seed, 60, noise=0.02, outliers=0.3, max_angle=0.5)
    first = register(source, target, method=method, seed=seed)
    second = register(source, target, method=method, seed=seed)
    for field in ("rotation", "translation", "quaternion", "inliers"):
        assert np.array_equal(getattr(first, field), getattr(second, field)), field
    assert (first.success, first.support, first.cost) == (
        second.success,
        second.support,
        second.cost,
    )


@pytest.mark.parametrize("method", METHODS)
@given(seed=seeds)
@settings(max_examples=8, deadline=None)
def test_pair_order_does_not_matter(method: str, seed: int) -> None:
    outliers = 0.0 if method == "svd" else 0.3
    source, target, *_ = _random_problem(seed, 60, noise=0.01, outliers=outliers, max_angle=0.5)
    order = np.random.default_rng(seed).permutation(60)
    plain = register(source, target, method=method, seed=7)
    permuted = register(source[order], target[order], method=method, seed=7)
    assert plain.success == permuted.success
    np.testing.assert_allclose(permuted.rotation, plain.rotation, atol=1e-9)
    np.testing.assert_allclose(permuted.translation, plain.translation, atol=1e-9)
    assert np.array_equal(permuted.inliers, plain.inliers[order])


@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("count", [0, 1, 2, 3])
def test_too_few_pairs_fail_gracefully(method: str, count: int) -> None:
    source, target, *_ = _random_problem(1, max(count, 1))
    result = register(source[:count], target[:count], method=method, seed=0)
    _assert_valid(result, count)
    if method == "svd" and count == 3:
        assert result.success  # three non-collinear pairs determine a pose
    else:
        assert not result.success and result.message
        np.testing.assert_array_equal(result.rotation, np.eye(3))


@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_non_finite_rows_are_rejected(method: str, bad: float) -> None:
    source, target, *_ = _random_problem(2, 10)
    target[4, 1] = bad
    with pytest.raises(ValueError, match="NaN or inf"):
        register(source, target, method=method)
    with pytest.raises(ValueError, match="shape"):
        register(source[:, :2], source[:, :2], method=method)


@pytest.mark.parametrize("method", METHODS)
def test_unknown_options_are_rejected(method: str) -> None:
    source, target, *_ = _random_problem(3, 20)
    with pytest.raises(ValueError, match="unknown option"):
        register(source, target, method=method, partciles=5)


@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("shape", ["line", "point", "line-target"])
def test_degenerate_sets_never_give_nan_or_raise(method: str, shape: str) -> None:
    steps = np.linspace(0.0, 4.0, 12)[:, None]
    line = steps * np.array([1.0, 2.0, 0.5]) + np.array([0.0, 0.0, 5.0])
    cloud = np.random.default_rng(4).normal(size=(12, 3))
    source = {"line": line, "point": np.ones((12, 3)), "line-target": cloud}[shape]
    target = line + np.array([0.3, -0.1, 0.2]) if shape != "point" else np.ones((12, 3)) * 2.0
    result = register(source, target, method=method, seed=0)
    _assert_valid(result, 12)
    assert not result.success and result.message


@pytest.mark.parametrize("method", ROBUST)
@given(seed=seeds)
@settings(max_examples=10, deadline=None)
def test_robust_methods_recover_the_pose_at_half_outliers(method: str, seed: int) -> None:
    source, target, rotation, translation, inliers = _random_problem(
        seed, 120, noise=0.01, outliers=0.5, max_angle=0.6
    )
    result = register(source, target, method=method, seed=seed)
    _assert_valid(result, 120)
    assert result.success, result.message
    assert rotation_error_deg(result.rotation, rotation) < 0.3
    assert translation_error(result.translation, translation) < 0.03
    # The inlier mask is the truth up to a handful of borderline pairs.
    assert np.count_nonzero(result.inliers != inliers) <= 3


@pytest.mark.parametrize("outlier_ratio", [0.9, 0.95])
def test_pso_robust_at_extreme_outlier_ratios_on_the_simulation(outlier_ratio: float) -> None:
    successes = 0
    for trial in range(20):
        pair = simulate_pair(noise_sigma=0.01, outlier_ratio=outlier_ratio, rng=500 + trial)
        result = register(pair.source, pair.target, method="pso-robust", seed=trial)
        successes += (
            rotation_error_deg(result.rotation, pair.rotation) < 1.0
            and translation_error(result.translation, pair.translation) < 0.05
        )
    assert successes >= 19


def test_faithful_pso_recovers_the_simulated_pose_without_outliers() -> None:
    for trial in range(5):
        pair = simulate_pair(noise_sigma=0.01, outlier_ratio=0.0, rng=700 + trial)
        result = register(pair.source, pair.target, method="pso", seed=trial)
        assert result.success, result.message
        assert rotation_error_deg(result.rotation, pair.rotation) < 0.5
        assert translation_error(result.translation, pair.translation) < 0.03


def test_rigidity_ranks_correct_pairs_first_at_90_percent_outliers() -> None:
    pair = simulate_pair(noise_sigma=0.02, outlier_ratio=0.9, rng=9)
    scores = rigidity_scores(rigidity_weights(pair.source, pair.target, 0.2))
    top = np.argsort(-scores)[: pair.inlier_mask.sum() // 2]
    assert pair.inlier_mask[top].all()


def test_fixed_delta_option_is_used() -> None:
    pair = simulate_pair(noise_sigma=0.02, outlier_ratio=0.2, rng=3)
    tight = register(pair.source, pair.target, method="pso-robust", seed=0, delta=0.02)
    loose = register(pair.source, pair.target, method="pso-robust", seed=0, delta=0.2)
    assert tight.support < loose.support <= len(pair.source)
    with pytest.raises(ValueError, match="delta must be positive"):
        register(pair.source, pair.target, method="pso-robust", delta=-1.0)


def _stereo_like(trial: int, outliers: float = 0.3):
    """Stereo-like pair: depth 1-10 m, error along the rays growing as depth^2.

    0.5 mm at 1 m, ~4 cm at 9 m (sqrt 2 more per pair: both sets are triangulated), like
    the rendered sequence on which a fixed-from-the-core threshold kept 3-70 % of the
    inliers (the refit loop never admitted the far, noisy pairs).
    """
    return simulate_pair(400, 0.0005, outliers, rng=3000 + trial, depth_noise=True, min_depth_m=1.0)


@pytest.mark.parametrize("with_sigmas", [False, True])
@pytest.mark.parametrize("method", ["pso-robust", "msac"])
def test_heteroscedastic_stereo_noise_keeps_the_far_inliers(method: str, with_sigmas: bool) -> None:
    for trial in range(10):
        pair = _stereo_like(trial)
        options = {"sigmas": pair.noise_sigmas} if with_sigmas else {}
        result = register(pair.source, pair.target, method=method, seed=trial, **options)
        assert result.success, result.message
        found = result.inliers & pair.inlier_mask
        recall = np.count_nonzero(found) / np.count_nonzero(pair.inlier_mask)
        precision = np.count_nonzero(found) / result.support
        assert recall > 0.9, (trial, recall)
        assert precision > 0.97, (trial, precision)
        assert rotation_error_deg(result.rotation, pair.rotation) < 0.5
        assert translation_error(result.translation, pair.translation) < 0.05


def test_sigmas_make_pso_robust_weigh_the_precise_pairs() -> None:
    """Weighted by 1 / sigma^2 the refit is the maximum-likelihood one: a better translation.

    (Without sigmas the ladder's residual weights already recover most of the rotation
    accuracy; the translation, fixed by the far and noisy pairs' centroid, gains most.)
    """
    plain, weighted = [], []
    for trial in range(10):
        pair = _stereo_like(trial)
        for errors, options in ((plain, {}), (weighted, {"sigmas": pair.noise_sigmas})):
            result = register(pair.source, pair.target, seed=trial, **options)
            errors.append(translation_error(result.translation, pair.translation))
    assert np.median(weighted) < 0.5 * np.median(plain)


def test_only_the_ratios_of_sigmas_matter() -> None:
    pair = _stereo_like(0)
    unit = register(pair.source, pair.target, seed=1, sigmas=pair.noise_sigmas)
    scaled = register(pair.source, pair.target, seed=1, sigmas=pair.noise_sigmas * 37.0)
    np.testing.assert_array_equal(unit.inliers, scaled.inliers)
    np.testing.assert_allclose(unit.rotation, scaled.rotation, atol=1e-9)
    np.testing.assert_allclose(unit.translation, scaled.translation, atol=1e-9)


@pytest.mark.parametrize("method", ["pso-robust", "pso", "msac"])
@pytest.mark.parametrize(
    ("sigmas", "message"),
    [
        (np.full(19, 0.01), "shape"),
        (np.full((20, 1), 0.01), "shape"),
        (np.r_[np.full(19, 0.01), np.nan], "finite"),
        (np.r_[np.full(19, 0.01), np.inf], "finite"),
        (np.r_[np.full(19, 0.01), 0.0], "positive"),
        (np.r_[np.full(19, 0.01), -0.01], "positive"),
    ],
)
def test_bad_sigmas_are_rejected(method: str, sigmas: np.ndarray, message: str) -> None:
    source, target, *_ = _random_problem(3, 20)
    with pytest.raises(ValueError, match=f"sigmas must .*{message}"):
        register(source, target, method=method, sigmas=sigmas)


def test_threshold_ladder_leaves_homoscedastic_problems_alone() -> None:
    """On equal noise the adaptive threshold already holds every inlier: no ladder step.

    A step would at least double delta, so the threshold stays below 6 sigma (the adaptive
    rule gives ~4 sigma) and the supporters are the true inliers up to borderline pairs.
    """
    for trial in range(10):
        pair = simulate_pair(noise_sigma=0.02, outlier_ratio=0.5, rng=800 + trial)
        result = register(pair.source, pair.target, seed=trial)
        assert np.count_nonzero(result.inliers != pair.inlier_mask) <= 2
        # cost = sum min(r^2, delta^2) and the non-supporters are those with r >= delta, so
        # each of them pays exactly delta^2: the final threshold can be read back.
        residual = residual_norms(result.rotation, result.translation, pair.source, pair.target)
        inside = float(np.sum(residual[result.inliers] ** 2))
        delta = np.sqrt((result.cost - inside) / np.count_nonzero(~result.inliers))
        assert 3.0 * 0.02 < delta < 6.0 * 0.02


def test_threshold_ladder_starts_from_the_core_when_too_few_pairs_pass() -> None:
    """One frame of a rendered drive (seed 1, frames 335 -> 336; ~350 stereo pairs from 3 m
    to beyond 100 m): the rigid core is eight pairs on one patch 37 m away, whose noise lies
    along the viewing rays where distances barely see it, so the threshold read from the core
    (6 mm) passed only 3 pairs and the frame was lost. The ladder must widen it from the
    core's pose and recover the motion (the rendered ground truth)."""
    data = np.load(DATA / "driving_quiet_core_pairs.npz")
    current, reference = data["current"].astype(float), data["reference"].astype(float)
    truth = data["reference_from_current"]
    result = register(current, reference, method="pso-robust", seed=int(data["seed"]))
    assert result.success, result.message
    assert np.count_nonzero(result.inliers) >= 0.8 * len(current)
    assert rotation_error_deg(result.rotation, truth[:3, :3]) < 0.05
    assert np.linalg.norm(result.translation - truth[:3, 3]) < 0.02


def test_a_one_patch_core_is_replaced_by_a_core_of_precise_pairs() -> None:
    """One frame of a rendered drive (seed 4, frames 225 -> 226; 312 stereo pairs from 8 m to
    185 m, with their stereo covariances): the most connected pairs, hence the rigid core,
    lie on one wall 21 m away, whose depth error tilts the core's rotation by ~1 deg; the
    search around it kept 22 pairs and the frame was lost. A second core from the most
    precise pairs must recover the motion (the rendered ground truth) and nearly every pair."""
    data = np.load(DATA / "driving_one_patch_core_pairs.npz")
    current, reference = data["current"], data["reference"]
    truth = data["reference_from_current"]
    covariances = {
        "source_cov": data["current_cov"].astype(float),
        "target_cov": data["reference_cov"].astype(float),
        "gate_chi2": float(data["gate_chi2"]),
    }
    seed = int(data["seed"])
    result = register(current, reference, method="pso-robust", seed=seed, **covariances)
    assert result.success, result.message
    assert np.count_nonzero(result.inliers) >= 0.9 * len(current)
    assert rotation_error_deg(result.rotation, truth[:3, :3]) < 0.02
    assert np.linalg.norm(result.translation - truth[:3, 3]) < 0.02


def test_precise_ranking_takes_the_quietest_of_the_well_ranked_pairs() -> None:
    scores = np.array([1.0, 0.9, 0.2, 0.6, 0.55, 0.1, 0.7])
    noise = np.array([5.0, 3.0, 0.1, 1.0, 2.0, 0.01, 4.0])
    # Pairs 2 and 5 are the quietest but score below half the best: left out.
    np.testing.assert_array_equal(precise_ranking(scores, noise, 3), [3, 4, 1])
    np.testing.assert_array_equal(precise_ranking(scores, noise, 10), [3, 4, 1, 6, 0])
    assert len(precise_ranking(np.empty(0), np.empty(0), 4)) == 0


def test_weighted_horn_matches_horn_and_ignores_zero_weight_pairs() -> None:
    source, target, *_ = _random_problem(5, 30, noise=0.01)
    np.testing.assert_allclose(
        weighted_horn(source, target, np.full(30, 3.0))[1], horn(source, target)[1], atol=1e-12
    )
    target[0] += 5.0  # a gross error that a tiny weight must neutralise
    weights = np.ones(30)
    weights[0] = 1e-12
    quaternion, fitted, shift = weighted_horn(source, target, weights)
    expected = horn(source[1:], target[1:])
    np.testing.assert_allclose(fitted, expected[1], atol=1e-9)
    np.testing.assert_allclose(shift, expected[2], atol=1e-9)
    np.testing.assert_allclose(quat_to_matrix(quaternion), fitted, atol=1e-12)


def test_rigidity_tolerance_scales_with_the_pairs_noise() -> None:
    source, target, *_ = _random_problem(6, 40, noise=0.05)
    plain = rigidity_weights(source, target, 0.2)
    np.testing.assert_allclose(rigidity_weights(source, target, 0.2, np.ones(40)), plain, atol=1e-6)
    scales = np.ones(40)
    scales[0] = 3.0  # pair 0 is noisy: its tolerance grows by sqrt((9 + 1) / 2)
    loose = rigidity_weights(source, target, 0.2, scales)
    np.testing.assert_allclose(loose[1:, 1:], plain[1:, 1:], atol=1e-6)
    np.testing.assert_allclose(1.0 - loose[0, 1:], (1.0 - plain[0, 1:]) / 5.0, atol=1e-5)


# ----------------------------------------------------------------------------- compiled steps


def test_rigidity_scores_are_the_power_iteration_of_the_weights() -> None:
    source, target, *_ = _random_problem(11, 70, noise=0.02, outliers=0.4)
    weights = rigidity_weights(source, target, 0.2).astype(float)
    expected = weights.sum(axis=1)
    for _ in range(2):
        expected = weights @ expected
        expected = expected / expected.max()
    np.testing.assert_allclose(rigidity_scores(weights.astype(np.float32)), expected, rtol=1e-5)


def test_top_ranked_is_the_head_of_a_stable_descending_sort() -> None:
    rng = np.random.default_rng(15)
    for count in (1, 5, 32, 60):
        scores = rng.integers(0, 6, size=50).astype(np.float32)  # many ties
        expected = np.argsort(-scores, kind="stable")[:count]
        np.testing.assert_array_equal(rigidity.top_ranked(scores, count), expected)
    scores = rng.normal(size=300)
    np.testing.assert_array_equal(
        rigidity.top_ranked(scores, 32), np.argsort(-scores, kind="stable")[:32]
    )


def test_symmetric_eigen_matches_lapack_on_hard_cases() -> None:
    rng = np.random.default_rng(12)
    rotation, _ = np.linalg.qr(rng.normal(size=(4, 4)))
    cases = [
        np.zeros((3, 3)),
        np.outer([1.0, 2.0, 0.5], [1.0, 2.0, 0.5]),  # rank 1: a line's scatter
        rotation @ np.diag([1.0, 1.0, 2.0, 2.0]) @ rotation.T,  # repeated eigenvalues
        np.diag([3.0, -1.0, 2.0, 0.0]),  # already diagonal, unsorted
    ]
    for size in (3, 4):
        for scale in (1e-6, 1.0, 1e6):
            matrix = rng.normal(size=(size, size)) * scale
            cases.append(matrix + matrix.T)
    for matrix in cases:
        values, vectors = swarm_kernels.symmetric_eigen(matrix)
        expected = np.linalg.eigvalsh(matrix)
        norm = max(np.abs(expected).max(), 1e-300)
        np.testing.assert_allclose(values, expected, rtol=0, atol=1e-13 * norm)
        np.testing.assert_allclose(vectors.T @ vectors, np.eye(len(matrix)), atol=1e-13)
        np.testing.assert_allclose(
            vectors @ np.diag(values) @ vectors.T, matrix, rtol=0, atol=1e-13 * norm
        )


def test_compiled_degeneracy_check_agrees_with_geometry() -> None:
    rng = np.random.default_rng(13)
    line = np.outer(np.linspace(0.0, 4.0, 12), [1.0, 2.0, 0.5]) + np.array([0.0, 0.0, 5.0])
    sets = [
        line,
        line + 1e-9 * rng.normal(size=line.shape),  # a line up to rounding-sized noise
        line + 1e-3 * rng.normal(size=line.shape),  # thin but a proper cloud
        np.ones((12, 3)),
        rng.normal(size=(12, 3)),
        rng.normal(size=(2, 3)),
    ]
    for points in sets:
        rows = np.arange(len(points))
        assert swarm_kernels.degenerate_points(points, rows) == is_degenerate(points)
    # Only the listed rows count: two points of a cloud are degenerate, all of it is not.
    cloud = sets[4]
    assert swarm_kernels.degenerate_points(cloud, np.array([3, 7]))
    assert not swarm_kernels.degenerate_rows(cloud, cloud + 1.0, np.array([0, 3, 5, 7]))
    assert swarm_kernels.degenerate_rows(cloud, line, np.arange(12))


def test_swarm_objective_scores_match_explicit_rotations() -> None:
    """Compressed Horn forms give the residuals of rotating the anchored points outright."""
    source, target, *_ = _random_problem(14, 50, noise=0.05, outliers=0.3, max_angle=0.5)
    rng = np.random.default_rng(14)
    scales = rng.uniform(0.5, 2.0, size=50)
    anchor = np.array([2, 5, 11, 17, 23])
    seed_rotation, _ = kabsch(source[anchor], target[anchor])
    delta = 0.3
    objective = support_pairs.RotationObjective(
        source, target, anchor, seed_rotation, delta, 1.0 / scales
    )
    positions = rng.normal(0.0, 0.2, size=(7, 3))
    anchored_source = (source - source[anchor].mean(axis=0)) @ seed_rotation.T
    anchored_target = target - target[anchor].mean(axis=0)
    rotated = quat_rotate(rotation_vector_to_quat(positions)[:, None, :], anchored_source)
    expected = np.sum((anchored_target - rotated) ** 2, axis=-1) / scales**2
    np.testing.assert_allclose(objective.squared_residuals(positions), expected, atol=1e-10)
    support, truncated = objective.truncated(positions)
    np.testing.assert_array_equal(support, np.count_nonzero(expected < delta**2, axis=1))
    np.testing.assert_allclose(truncated, np.minimum(expected, delta**2).sum(axis=1), rtol=1e-9)
    _, plain = objective.sum_of_squares(positions)
    np.testing.assert_allclose(plain, expected.sum(axis=1), rtol=1e-9)
    np.testing.assert_array_equal(objective.supporters(positions[3]), expected[3] < delta**2)


def test_pso_robust_pose_is_the_least_squares_fit_of_its_inliers() -> None:
    """Without a ladder step (equal noise) the refit loop ends on Horn's fit of its set."""
    for trial in range(5):
        pair = simulate_pair(noise_sigma=0.02, outlier_ratio=0.5, rng=900 + trial)
        result = register(pair.source, pair.target, seed=trial)
        _, rotation, translation = horn(pair.source[result.inliers], pair.target[result.inliers])
        np.testing.assert_allclose(result.rotation, rotation, atol=1e-12)
        np.testing.assert_allclose(result.translation, translation, atol=1e-10)
        # ... and that set is exactly the pairs that fit within the final threshold.
        residual = residual_norms(rotation, translation, pair.source, pair.target)
        inside = np.sum(residual[result.inliers] ** 2)
        delta = np.sqrt((result.cost - inside) / np.count_nonzero(~result.inliers))
        np.testing.assert_array_equal(result.inliers, residual < delta * (1 + 1e-9))


def _plain_refine(source, target, supporters, delta, scales, residual=None, floor=None):
    """The refit loop written out with geometry.kabsch (weighted Arun) as the fit."""
    adapt = floor is None
    for _ in range(8):
        if np.count_nonzero(supporters) < 4:
            break
        weights = 1.0 / scales**2
        if floor is not None:
            weights = weights / np.maximum(residual, floor) ** 2
        rotation, translation = kabsch(source[supporters], target[supporters], weights[supporters])
        residual = residual_norms(rotation, translation, source, target) / scales
        if adapt:
            sigma = np.sqrt(np.mean(residual[supporters] ** 2) / 3.0)
            delta = min(max(4.0 * sigma, 0.005), 0.5)
        refreshed = residual < delta
        if np.array_equal(refreshed, supporters):
            return supporters, delta, (rotation, translation, residual)
        supporters = refreshed
    return supporters, delta, None


def test_compiled_refit_loop_matches_a_plain_reimplementation() -> None:
    """Adaptive and weighted (ladder) refits, with per-pair scales, against weighted Arun."""
    estimator = pso_support.PsoSupportEstimator()
    settled = 0
    for trial in range(4):
        pair = _stereo_like(trial)
        scales = pair.noise_sigmas / np.median(pair.noise_sigmas)
        pairs = support_pairs.Pairs.of(pair.source, pair.target, scales)
        truth = residual_norms(pair.rotation, pair.translation, pair.source, pair.target)
        start = truth / scales < 0.01
        for residual, floor in ((None, None), (truth / scales, 0.004)):
            expected = _plain_refine(pair.source, pair.target, start, 0.01, scales, residual, floor)
            found = estimator._refine(pairs, start, 0.01, floor is None, residual, floor)
            np.testing.assert_array_equal(found[0], expected[0])
            assert np.isclose(found[1], expected[1], rtol=1e-12)
            assert (found[2] is None) == (expected[2] is None)
            if found[2] is not None:
                settled += 1
                np.testing.assert_allclose(found[2][1], expected[2][0], atol=1e-10)
                np.testing.assert_allclose(found[2][2], expected[2][1], atol=1e-9)
                np.testing.assert_allclose(found[2][3], expected[2][2], atol=1e-9)
    assert settled >= 4  # the poses were compared, not only the unsettled sets
