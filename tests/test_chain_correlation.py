"""Two registrations of one frame that share its points: their cross-covariance and the best
linear unbiased combination (registration/sensitivity.py, odometry/chains.py)."""

from __future__ import annotations

import numpy as np

from estimator.geometry import make_pose, quat_to_matrix, rotation_vector_to_quat
from estimator.odometry.chains import (
    Measured,
    PointSensitivity,
    chain_covariance,
    combine_chain,
    fuse_correlated,
    fuse_poses,
    fused_sensitivity,
    link_bias_covariance,
    pose_difference,
    shared_covariance,
)
from estimator.registration.refine import refine_pose_mahalanobis
from estimator.registration.sensitivity import point_sensitivities


def _pose(rotvec: list[float], translation: list[float]) -> np.ndarray:
    return make_pose(quat_to_matrix(rotation_vector_to_quat(np.array(rotvec))), translation)


def _stereo_covariances(points: np.ndarray, pixel: float, depth: float) -> np.ndarray:
    """Uncertain mostly along each point's viewing ray, growing with depth."""
    covariances = np.empty((len(points), 3, 3))
    for n, point in enumerate(points):
        ray = point / np.linalg.norm(point)
        z = point[2]
        lateral = (pixel * z) ** 2 * (np.eye(3) - np.outer(ray, ray))
        covariances[n] = lateral + (depth * z * z) ** 2 * np.outer(ray, ray)
    return covariances


def _points(rng: np.random.Generator, count: int) -> np.ndarray:
    return rng.uniform([-3.0, -2.0, 2.0], [3.0, 2.0, 9.0], (count, 3))


def _refined(source, target, source_cov, target_cov, pose, robust="none"):
    result = refine_pose_mahalanobis(
        source, target, source_cov, target_cov, pose[:3, :3], pose[:3, 3],
        iterations=30, robust=robust,
    )  # fmt: skip
    assert result.success
    return result


def test_sensitivity_predicts_how_the_refined_pose_moves_with_a_point() -> None:
    rng = np.random.default_rng(1)
    # Few points, so that one moves the estimate well beyond the refinement's step tolerance.
    source = _points(rng, 25)
    covariance = _stereo_covariances(source, 2e-3, 2e-3)
    truth = _pose([0.02, -0.05, 0.01], [0.1, 0.0, 0.05])
    target = source @ truth[:3, :3].T + truth[:3, 3]
    target += np.einsum("nij,nj->ni", np.linalg.cholesky(covariance), rng.normal(size=(25, 3)))
    base = _refined(source, target, covariance, covariance, truth)
    both = point_sensitivities(
        source, target, covariance, covariance, base.rotation, base.translation, robust="none"
    )
    assert both is not None and both[0].shape == both[1].shape == (25, 6, 3)
    gains, target_gains = both
    start = make_pose(base.rotation, base.translation)
    misses = []
    for point in range(25):
        # 1.6 sigma: small enough to stay linear, large enough for the refinement's tolerance
        offset = np.linalg.cholesky(covariance[point]) @ np.array([0.9, -0.6, 1.2])
        for moved_source, moved_target, gain in (
            (source + np.eye(25)[point][:, None] * offset, target, gains[point]),
            (source, target + np.eye(25)[point][:, None] * offset, target_gains[point]),
        ):
            moved = _refined(moved_source, moved_target, covariance, covariance, start)
            change = pose_difference(start, make_pose(moved.rotation, moved.translation))
            predicted = gain @ offset
            misses.append(np.linalg.norm(change - predicted) / np.linalg.norm(predicted))
    # Measured over seeds: median below 1 %, worst 13 % (the refinement stops at a 1e-6 step);
    # without the [[W r]x; 0] term single points miss by 15-35 %, a wrong sign by 200 %.
    assert np.median(misses) < 0.05 and max(misses) < 0.15, np.round(misses, 3)


def _two_registrations(rng: np.random.Generator, trials: int):
    """One current frame (its points' noise shared) registered against two references that
    see overlapping parts of it; the second estimate is carried to the first's reference by
    an exact transform, so both estimate the same pose."""
    count = 90
    current = _points(rng, count)
    current_cov = _stereo_covariances(current, 2e-3, 1.5e-3)
    first_truth = _pose([0.03, -0.1, 0.02], [0.2, -0.05, 0.1])
    first_from_second = _pose([0.01, 0.04, -0.02], [-0.1, 0.02, 0.05])
    second_truth = np.linalg.inv(first_from_second) @ first_truth
    first_part, second_part = np.arange(0, 70), np.arange(20, 90)
    samples = []
    for _ in range(trials):
        noisy = current + np.einsum(
            "nij,nj->ni", np.linalg.cholesky(current_cov), rng.normal(size=(count, 3))
        )
        estimates = []
        for truth, part in ((first_truth, first_part), (second_truth, second_part)):
            target = current[part] @ truth[:3, :3].T + truth[:3, 3]
            target_cov = _stereo_covariances(target, 1e-3, 1e-3)
            target += np.einsum(
                "nij,nj->ni", np.linalg.cholesky(target_cov), rng.normal(size=(len(part), 3))
            )
            result = _refined(noisy[part], target, current_cov[part], target_cov, truth)
            gains = point_sensitivities(
                noisy[part], target, current_cov[part], target_cov, result.rotation,
                result.translation, robust="none",
            )  # fmt: skip
            assert gains is not None
            estimates.append(
                (
                    make_pose(result.rotation, result.translation),
                    result.covariance / result.variance_factor,  # the model's own covariance
                    PointSensitivity(part, gains[0], current_cov[part]),
                )
            )
        (first, first_cov, first_gains), (second, second_cov, second_gains) = estimates
        samples.append(
            (first, first_cov, first_from_second @ second, second_cov, first_gains, second_gains)
        )
    return first_truth, samples


def test_shared_points_give_the_sampled_cross_covariance_and_a_better_combination() -> None:
    rng = np.random.default_rng(4)
    truth, samples = _two_registrations(rng, 600)
    first_errors = np.array([pose_difference(truth, s[0]) for s in samples])
    second_errors = np.array([pose_difference(truth, s[2]) for s in samples])
    cross = shared_covariance(samples[0][4], samples[0][5])
    sampled_cross = (first_errors.T @ second_errors) / len(samples)
    scale = np.sqrt(np.outer(np.diag(samples[0][1]), np.diag(samples[0][3])))
    # 600 samples: a covariance entry is known to about 4-6 % of the scale
    assert np.abs(sampled_cross - cross).max() / scale.max() < 0.15
    assert np.abs(cross).max() / scale.max() > 0.3  # the correlation is not negligible

    fused_errors, independent_errors = [], []
    for first, first_cov, second, second_cov, _, _ in samples:
        fused = fuse_correlated(first, first_cov, second, second_cov, cross)
        independent = fuse_poses(first, first_cov, second, second_cov)
        assert fused is not None and independent is not None
        fused_errors.append(pose_difference(truth, fused[0]))
        independent_errors.append(pose_difference(truth, independent[0]))
    predicted = fused[1]
    sampled = np.cov(np.array(fused_errors).T)
    # Within 6 % at this seed; up to 22 % on one axis at others (one sample of gains and
    # covariances stands for all, and the model is linearised).
    assert np.abs(np.diag(sampled) / np.diag(predicted) - 1).max() < 0.25
    for other in (first_errors, second_errors, np.array(independent_errors)):
        assert (np.diag(sampled) < 1.05 * np.diag(np.cov(other.T))).all()
    # Counting the shared points twice claims a covariance smaller than the errors show.
    assert (np.diag(independent[1]) < 0.8 * np.diag(np.cov(np.array(independent_errors).T))).any()
    # The combination's own sensitivity accounts for the shared points' share of its covariance.
    combined = fused_sensitivity(samples[-1][4], samples[-1][5], fused[2])
    assert np.array_equal(combined.current_index, np.arange(90))
    points_share = shared_covariance(combined, combined)
    assert (np.diag(points_share) <= np.diag(predicted) * 1.001).all()


def test_uncorrelated_combination_is_the_independent_one_and_bad_input_is_refused() -> None:
    rng = np.random.default_rng(2)
    truth = _pose([0.1, 0.2, -0.1], [0.5, 0.1, 2.0])
    first_cov = np.diag([1e-6, 2e-6, 1e-6, 1e-4, 2e-4, 3e-4])
    second_cov = np.diag([3e-6, 1e-6, 2e-6, 2e-4, 1e-4, 1e-4])
    first = truth @ _pose(list(rng.normal(0, 1e-3, 3)), list(rng.normal(0, 1e-2, 3)))
    second = truth @ _pose(list(rng.normal(0, 1e-3, 3)), list(rng.normal(0, 1e-2, 3)))
    correlated = fuse_correlated(first, first_cov, second, second_cov, np.zeros((6, 6)))
    independent = fuse_poses(first, first_cov, second, second_cov)
    assert correlated is not None and independent is not None
    assert np.allclose(correlated[0], independent[0], atol=1e-12)
    assert np.allclose(correlated[1], independent[1], rtol=1e-9, atol=1e-15)
    # Fully shared errors (cross = first = second) leave nothing to combine.
    assert fuse_correlated(first, first_cov, second, first_cov, first_cov) is None
    assert fuse_correlated(first, -first_cov, second, second_cov, np.zeros((6, 6))) is None


def _noisy(rng: np.random.Generator, views: list, factors: list) -> list[np.ndarray]:
    """Each frame's camera-frame points with their stereo noise drawn."""
    return [
        view + np.einsum("nij,nj->ni", factor, rng.normal(size=view.shape))
        for view, factor in zip(views, factors, strict=True)
    ]


def _chain_links(frames: list, covariances: list, poses: list) -> tuple[Measured, Measured]:
    """keyframe -> previous and previous -> current, measured on shared and own points."""
    link = _measured(frames, covariances, 1, 0, poses[1], np.arange(0, 60))
    between = np.linalg.inv(poses[1]) @ poses[2]
    return link, _measured(frames, covariances, 2, 1, between, np.arange(15, 80))


def _measured(frames, covariances, current: int, reference: int, truth, ids) -> Measured:
    """T_reference_current registered from the noisy points ``ids`` of two frames (a frame's
    point index = the point's id), with its sensitivities to both frames' points."""
    source, target = frames[current][ids], frames[reference][ids]
    source_cov, target_cov = covariances[current][ids], covariances[reference][ids]
    result = _refined(source, target, source_cov, target_cov, truth)
    gains = point_sensitivities(
        source, target, source_cov, target_cov, result.rotation, result.translation,
        robust="none",
    )  # fmt: skip
    assert gains is not None
    return Measured(
        make_pose(result.rotation, result.translation),
        result.covariance / result.variance_factor,
        PointSensitivity(ids, gains[0], source_cov),
        PointSensitivity(ids, gains[1], target_cov),
    )


def test_chain_through_the_previous_frame_counts_every_shared_point() -> None:
    """Keyframe k, previous frame p and current frame c see overlapping sets of points, each
    frame with its own noise: the combination's covariance matches the sampled errors and it
    beats both inputs and the combination that takes them as independent."""
    rng = np.random.default_rng(11)
    world = _points(rng, 90)
    poses = [np.eye(4), _pose([0.01, -0.03, 0.0], [0.05, 0.0, 0.02])]
    poses.append(_pose([0.02, -0.06, 0.01], [0.1, 0.01, 0.04]))
    views = [(world - pose[:3, 3]) @ pose[:3, :3] for pose in poses]  # camera-frame points
    covariances = [_stereo_covariances(view, 2e-3, 2e-3) for view in views]
    factors = [np.linalg.cholesky(covariance) for covariance in covariances]
    truth = poses[2]  # T_kc with k = identity
    errors: dict[str, list[np.ndarray]] = {"fused": [], "measured": [], "chain": [], "naive": []}
    for _ in range(600):
        frames = _noisy(rng, views, factors)
        link, step = _chain_links(frames, covariances, poses)
        measured = _measured(frames, covariances, 2, 0, truth, np.arange(30, 90))
        fused = combine_chain(measured, link, step)
        assert fused is not None
        chain_cov = chain_covariance(link.covariance, step.pose, step.covariance)
        naive = fuse_poses(measured.pose, measured.covariance, link.pose @ step.pose, chain_cov)
        assert naive is not None
        for name, pose in (
            ("fused", fused.pose), ("measured", measured.pose),
            ("chain", link.pose @ step.pose), ("naive", naive[0]),
        ):  # fmt: skip
            errors[name].append(pose_difference(truth, pose))
    sampled = {name: np.cov(np.array(values).T) for name, values in errors.items()}
    # 600 samples: a variance is known to about 6 %; the worst of six axes within 3.5 sigma.
    ratio = np.diag(sampled["fused"]) / np.diag(fused.covariance)
    assert np.abs(ratio - 1).max() < 0.2, ratio
    for other in ("measured", "chain", "naive"):
        assert (np.diag(sampled["fused"]) < 1.05 * np.diag(sampled[other])).all(), other
    # Counted as independent, the shared points make the naive covariance too small
    # (measured: 0.74-0.90 of the sampled variance).
    assert (np.diag(naive[1]) < 0.8 * np.diag(sampled["naive"])).any()


def test_link_bias_grows_with_the_links_image_motion() -> None:
    covariance = link_bias_covariance(0.005, np.array([1.0, 3.0, 100.0]), 400.0)
    sigma = 0.005 * 3.0 / 400.0  # the median flow over the focal length
    np.testing.assert_allclose(covariance[:3, :3], np.eye(3) * sigma**2)
    assert not covariance[3:].any() and not covariance[:, 3:].any()
    assert not link_bias_covariance(0.0, np.array([5.0]), 400.0).any()
    assert not link_bias_covariance(0.005, np.array([]), 400.0).any()


def test_a_biased_link_weighed_with_its_bias_pulls_the_combination_less() -> None:
    """The step previous -> current carries a rotation bias (the same in every sample, as
    blur gives consecutive frames): counted in the step's covariance, the combination leans
    on the keyframe measurement and its error is smaller, bias and spread together."""
    rng = np.random.default_rng(5)
    world = _points(rng, 90)
    poses = [np.eye(4), _pose([0.01, -0.03, 0.0], [0.05, 0.0, 0.02])]
    poses.append(_pose([0.02, -0.06, 0.01], [0.1, 0.01, 0.04]))
    views = [(world - pose[:3, 3]) @ pose[:3, :3] for pose in poses]
    covariances = [_stereo_covariances(view, 2e-3, 2e-3) for view in views]
    factors = [np.linalg.cholesky(covariance) for covariance in covariances]
    bias = _pose([1.5e-3, 0.0, 0.0], [0.0, 0.0, 0.0])  # about x, as on the noisy loop
    motion = 0.03  # the step's image motion over the focal length
    extra = link_bias_covariance(1.5e-3 / motion, np.array([motion]), 1.0)
    errors: dict[str, list[np.ndarray]] = {"plain": [], "bias counted": []}
    for _ in range(150):
        frames = _noisy(rng, views, factors)
        link, step = _chain_links(frames, covariances, poses)
        step.pose = step.pose @ bias
        measured = _measured(frames, covariances, 2, 0, poses[2], np.arange(30, 90))
        for name, added in (("plain", np.zeros((6, 6))), ("bias counted", extra)):
            biased = Measured(step.pose, step.covariance + added, step.current, step.reference)
            fused = combine_chain(measured, link, biased)
            assert fused is not None
            errors[name].append(pose_difference(poses[2], fused.pose)[:3])
    plain, counted = np.array(errors["plain"]), np.array(errors["bias counted"])
    assert abs(counted[:, 0].mean()) < 0.8 * abs(plain[:, 0].mean())
    assert np.mean(counted**2) < np.mean(plain**2)
