"""Front end: grid detection, descriptor matching, stereo matching/triangulation, time matching.

The stereo and temporal checks run on rectified pairs rendered in-test: a random texture on
fronto-parallel planes at known depths, shifted by the exact (fractional) disparity, so every
depth and pixel shift has a known true value.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from estimator.config import FrontendConfig
from estimator.formats.calibration import StereoRig
from estimator.frontend.detection import FeatureDetector
from estimator.frontend.features import (
    Features,
    descriptor_distances,
    grid_select,
    match_candidates,
)
from estimator.frontend.photometric import normalise_contrast
from estimator.frontend.stereo import (
    StereoMatcher,
    point_covariances,
    row_band_pairs,
    triangulate,
    triangulation_jacobian,
)
from estimator.frontend.temporal import match_temporal, project
from estimator.geometry import invert_pose, make_pose
from estimator.rendered.camera import CAMERA, T_BS_CAM0, T_BS_CAM1
from estimator.rendered.trajectory import loop_for_length
from estimator.rendered.world import build_world

WIDTH, HEIGHT, FOCAL, BASELINE = 640, 480, 400.0, 0.12


def _rig() -> StereoRig:
    camera = {
        "width": WIDTH, "height": HEIGHT, "fx": FOCAL, "fy": FOCAL, "cx": 320.0, "cy": 240.0,
        "distortion_model": "none", "distortion": [],
    }  # fmt: skip
    return StereoRig.from_dict(
        {
            "left": {**camera, "T_BS": np.eye(4).tolist()},
            "right": {**camera, "T_BS": make_pose(np.eye(3), [BASELINE, 0, 0]).tolist()},
        }
    )


def _texture(seed: int, shape: tuple[int, int] = (HEIGHT, WIDTH + 200)) -> np.ndarray:
    """Multi-scale random blobs: many distinct, well-localised corners."""
    rng = np.random.default_rng(seed)
    image = np.zeros(shape, np.float32)
    for scale in (3, 7, 15):
        noise = rng.normal(size=(shape[0] // scale + 2, shape[1] // scale + 2)).astype(np.float32)
        image += cv2.resize(noise, (shape[1], shape[0]), interpolation=cv2.INTER_CUBIC)
    image = (image - image.min()) / (image.max() - image.min()) * 255.0
    return image.astype(np.float32)


def _shift(image: np.ndarray, dx: float, dy: float = 0.0) -> np.ndarray:
    """Sub-pixel translation of an image (content moves by +dx, +dy)."""
    warp = np.array([[1.0, 0.0, dx], [0.0, 1.0, dy]], dtype=np.float32)
    return cv2.warpAffine(image, warp, (image.shape[1], image.shape[0]), flags=cv2.INTER_CUBIC)


def _two_plane_pair(
    texture: np.ndarray, depths: tuple[float, float], dx: float = 0.0, dy: float = 0.0
) -> tuple[np.ndarray, np.ndarray]:
    """Left/right rectified views of two planes (left half near, right half far).

    The right camera sees each plane shifted left by its disparity f b / Z. ``dx, dy`` move
    the whole scene in both images (a sideways camera motion for a temporal pair).
    """
    left = np.zeros((HEIGHT, WIDTH), np.float32)
    right = np.zeros((HEIGHT, WIDTH), np.float32)
    half = WIDTH // 2
    moved = _shift(texture, dx, dy)
    for depth, columns in zip(depths, (slice(0, half), slice(half, WIDTH)), strict=True):
        disparity = FOCAL * BASELINE / depth
        left[:, columns] = moved[:, :WIDTH][:, columns]
        right[:, columns] = _shift(moved, -disparity)[:, :WIDTH][:, columns]
    return np.clip(left, 0, 255).astype(np.uint8), np.clip(right, 0, 255).astype(np.uint8)


def _stereo(config: FrontendConfig, left: np.ndarray, right: np.ndarray):
    rig = _rig()
    detector = FeatureDetector(config)
    matcher = StereoMatcher(config, rig.rectification)
    return matcher.match(detector.detect(left), detector.detect(right), left, right)


# ----------------------------------------------------------------------------- features


def test_grid_select_spreads_and_respects_budget() -> None:
    rng = np.random.default_rng(0)
    # 500 strong corners crowded into one cell, 40 weak ones spread over the others.
    crowded = rng.uniform([0, 0], [80, 80], size=(500, 2))
    spread = rng.uniform([170, 130], [640, 480], size=(40, 2))  # outside cell (0, 0)
    points = np.vstack([crowded, spread])
    response = np.r_[rng.uniform(10, 20, 500), rng.uniform(0, 1, 40)]
    keep = grid_select(points, response, (640, 480), (4, 4), budget=100)
    assert len(keep) == 100
    assert len(np.unique(keep)) == 100
    # Every weak but lonely corner survives; the crowded cell only gets the remaining budget.
    assert np.isin(np.arange(500, 540), keep).all()
    crowded_kept = keep[keep < 500]
    assert len(crowded_kept) == 60
    # ... and within the crowded cell the strongest ones are those kept.
    assert response[crowded_kept].min() >= np.sort(response[:500])[-60]


def test_grid_select_empty() -> None:
    assert len(grid_select(np.zeros((0, 2)), np.zeros(0), (10, 10), (2, 2), 5)) == 0


def test_detector_fills_the_image_within_budget() -> None:
    image = _texture(1)[:, :WIDTH].astype(np.uint8)
    config = FrontendConfig(max_features=300, grid_rows=3, grid_cols=4)
    features = FeatureDetector(config).detect(image)
    assert 250 <= len(features) <= 300
    assert features.descriptors.shape == (len(features), 32)
    counts = np.histogram2d(
        features.points[:, 1], features.points[:, 0], bins=(3, 4), range=((0, 480), (0, 640))
    )[0]
    assert counts.min() >= 10  # no empty cell on a uniformly textured image


def test_detector_sift_option() -> None:
    image = _texture(2)[:, :WIDTH].astype(np.uint8)
    features = FeatureDetector(FrontendConfig(detector="sift", max_features=200)).detect(image)
    assert 100 <= len(features) <= 200
    assert features.descriptors.shape[1] == 128 and not features.binary


def test_detector_on_black_image_returns_nothing() -> None:
    features = FeatureDetector(FrontendConfig()).detect(np.zeros((HEIGHT, WIDTH), np.uint8))
    assert len(features) == 0 and features.points.shape == (0, 2)


def test_hamming_distances_match_bit_count() -> None:
    rng = np.random.default_rng(3)
    a = rng.integers(0, 256, size=(6, 32), dtype=np.uint8)
    b = rng.integers(0, 256, size=(5, 32), dtype=np.uint8)
    ia, ib = np.array([0, 1, 5, 2]), np.array([4, 0, 3, 2])
    expected = [np.unpackbits(a[i] ^ b[j]).sum() for i, j in zip(ia, ib, strict=True)]
    np.testing.assert_array_equal(descriptor_distances(a, b, ia, ib, binary=True), expected)
    cv_distance = [cv2.norm(a[i], b[j], cv2.NORM_HAMMING) for i, j in zip(ia, ib, strict=True)]
    np.testing.assert_array_equal(descriptor_distances(a, b, ia, ib, binary=True), cv_distance)


def test_match_candidates_ratio_and_mutual() -> None:
    # a0: clear best b0. a1: ambiguous (b1 vs b2). a2: best is b0, but b0 prefers a0.
    ia = np.array([0, 0, 1, 1, 2, 2])
    ib = np.array([0, 1, 1, 2, 0, 3])
    distance = np.array([10.0, 40.0, 20.0, 21.0, 15.0, 50.0])
    matches = match_candidates(ia, ib, distance, ratio=0.8, max_distance=100, mutual=True)
    assert list(zip(matches.a, matches.b, strict=True)) == [(0, 0)]
    no_mutual = match_candidates(ia, ib, distance, ratio=0.8, max_distance=100, mutual=False)
    assert sorted(zip(no_mutual.a, no_mutual.b, strict=True)) == [(0, 0), (2, 0)]
    strict = match_candidates(ia, ib, distance, ratio=0.8, max_distance=5, mutual=False)
    assert len(strict) == 0


# ----------------------------------------------------------------------------- stereo


@settings(max_examples=40, deadline=None)
@given(
    seed=st.integers(0, 10_000),
    tolerance=st.floats(0.0, 3.0),
    disparity=st.tuples(st.floats(0.0, 30.0), st.floats(0.0, 80.0)),
)
def test_row_band_pairs_equals_brute_force(seed: int, tolerance: float, disparity) -> None:
    low, high = min(disparity), max(disparity)
    rng = np.random.default_rng(seed)
    left = np.round(rng.uniform(0, 100, size=(40, 2)), 1)
    right = np.round(rng.uniform(0, 100, size=(35, 2)), 1)
    ia, ib = row_band_pairs(left, right, tolerance, (low, high))
    found = set(zip(ia.tolist(), ib.tolist(), strict=True))
    assert len(found) == len(ia)  # no pair twice
    dy = np.abs(left[:, None, 1] - right[None, :, 1])
    dx = left[:, None, 0] - right[None, :, 0]

    def band(slack: float) -> set[tuple[int, int]]:
        inside = (dy <= tolerance + slack) & (dx >= low - slack) & (dx <= high + slack)
        return set(map(tuple, np.argwhere(inside).tolist()))

    # Pairs exactly on a band edge may fall either way by float rounding (y - tol vs |dy|);
    # every pair clearly inside must be found and none clearly outside.
    assert band(-1e-9) <= found <= band(1e-9)


def test_triangulate_recovers_projected_points() -> None:
    rect = _rig().rectification
    rng = np.random.default_rng(4)
    points = rng.uniform([-2, -1.5, 1.0], [2, 1.5, 12.0], size=(50, 3))
    u_left = FOCAL * points[:, 0] / points[:, 2] + 320.0
    u_right = FOCAL * (points[:, 0] - BASELINE) / points[:, 2] + 320.0
    v = FOCAL * points[:, 1] / points[:, 2] + 240.0
    recovered = triangulate(np.column_stack([u_left, v]), u_left - u_right, rect)
    np.testing.assert_allclose(recovered, points, rtol=1e-12, atol=1e-12)


def _random_stereo(seed: int, count: int):
    """The test rig's rectification with random pixels and disparities of 2-60 px."""
    rng = np.random.default_rng(seed)
    pixels = rng.uniform([0, 0], [WIDTH, HEIGHT], size=(count, 2))
    return _rig().rectification, pixels, rng.uniform(2.0, 60.0, count)


def test_triangulation_jacobian_matches_finite_differences() -> None:
    rect, pixels, disparity = _random_stereo(11, 40)
    jacobian = triangulation_jacobian(pixels, disparity, rect)
    step = 1e-4
    numeric = np.empty_like(jacobian)
    for column, (du, dv, dd) in enumerate(np.eye(3) * step):  # three central differences
        shift = np.array([du, dv])
        plus = triangulate(pixels + shift, disparity + dd, rect)
        minus = triangulate(pixels - shift, disparity - dd, rect)
        numeric[:, :, column] = (plus - minus) / (2 * step)
    np.testing.assert_allclose(jacobian, numeric, rtol=1e-6, atol=1e-9)


def test_point_covariances_propagate_pixel_and_disparity_noise() -> None:
    rect, pixels, disparity = _random_stereo(12, 30)
    points = triangulate(pixels, disparity, rect)
    sigmas = (0.3, 0.2, 0.5)
    covariance = point_covariances(points, rect, *sigmas)
    jacobian = triangulation_jacobian(pixels, disparity, rect)
    expected = jacobian @ np.diag(np.square(sigmas)) @ jacobian.transpose(0, 2, 1)
    np.testing.assert_allclose(covariance, expected, rtol=1e-10, atol=1e-15)
    # The depth variance is the scalar depth sigma the matcher reports, Z^2 sigma_d / (f b).
    depth_sigma = points[:, 2] ** 2 * sigmas[2] / (FOCAL * BASELINE)
    np.testing.assert_allclose(np.sqrt(covariance[:, 2, 2]), depth_sigma, rtol=1e-12)
    # Uncertain along the viewing ray: the largest axis is the ray, tens of times the others.
    values, vectors = np.linalg.eigh(covariance)
    rays = points / np.linalg.norm(points, axis=1, keepdims=True)
    assert np.all(np.abs(np.einsum("ni,ni->n", vectors[:, :, 2], rays)) > 0.99)
    far = points[:, 2] > 3.0
    assert np.all(np.sqrt(values[far, 2] / values[far, 1]) > 20.0)


def test_point_covariances_match_monte_carlo_triangulation() -> None:
    rect = _rig().rectification
    rng = np.random.default_rng(13)
    pixel, disparity = np.array([[410.0, 180.0]]), np.array([12.0])
    sigmas = np.array([0.3, 0.3, 0.5])
    noise = rng.normal(size=(20000, 3)) * sigmas
    samples = triangulate(pixel + noise[:, :2], disparity + noise[:, 2], rect)
    predicted = point_covariances(triangulate(pixel, disparity, rect), rect, *sigmas)[0]
    # First order: exact across the ray; along it the 1/d curvature adds ~3 (sigma_d / d)^2
    # relative (0.5 %), below the 1 % sampling error of 20000 draws.
    np.testing.assert_allclose(np.cov(samples.T), predicted, rtol=0.1, atol=1e-7)


@pytest.mark.parametrize("subpixel", ["sad", "lk"])
def test_stereo_depth_accuracy_on_rendered_planes(subpixel: str) -> None:
    depths = (1.7, 4.3)  # disparities 28.24 px and 11.16 px: both fractional
    left, right = _two_plane_pair(_texture(5), depths)
    config = FrontendConfig(subpixel=subpixel, max_features=600)
    points = _stereo(config, left, right)
    near = points.pixels[:, 0] < WIDTH // 2 - 20
    far = points.pixels[:, 0] > WIDTH // 2 + 20
    assert near.sum() > 100 and far.sum() > 100
    for mask, depth in ((near, depths[0]), (far, depths[1])):
        true_disparity = FOCAL * BASELINE / depth
        error = points.disparity[mask] - true_disparity
        assert np.median(np.abs(error)) < 0.1  # sub-pixel
        assert np.mean(np.abs(error) < 0.5) > 0.9
        assert abs(np.median(points.points[mask, 2]) - depth) < 0.01 * depth
    # Uncertainty follows sigma_Z = Z^2 sigma_d / (f b).
    expected_sigma = points.points[:, 2] ** 2 * config.disparity_sigma_px / (FOCAL * BASELINE)
    np.testing.assert_allclose(points.depth_sigma, expected_sigma)


def test_stereo_without_refinement_is_whole_pixel_but_close() -> None:
    left, right = _two_plane_pair(_texture(5), (1.7, 4.3))
    points = _stereo(FrontendConfig(subpixel="none"), left, right)
    near = points.pixels[:, 0] < WIDTH // 2 - 20
    error = points.disparity[near] - FOCAL * BASELINE / 1.7
    assert np.median(np.abs(error)) < 1.0


@pytest.mark.parametrize("subpixel", ["sad", "lk"])
def test_stereo_disparities_in_a_rendered_hall_are_unbiased(subpixel: str) -> None:
    """Disparities of slanted, occluding, mipmapped surfaces against the renderer's depth.

    A mean disparity offset scales all depths (Z = f b / d) and, depending on how the scene is
    spread, tilts the estimated motion; the sub-pixel fit also must not lock onto whole pixels
    (mean error per quarter of the true fractional disparity). Measured: mean ~0.002 px,
    quarter means within 0.015 px, spread ~0.05 px.
    """
    trajectory = loop_for_length(4.0, 2.0)
    world = build_world(trajectory, np.random.default_rng(2), px_per_m=96.0)
    camera = {
        "width": CAMERA["width"], "height": CAMERA["height"], "fx": CAMERA["f"],
        "fy": CAMERA["f"], "cx": CAMERA["cx"], "cy": CAMERA["cy"],
        "distortion_model": "none", "distortion": [],
    }  # fmt: skip
    rig = StereoRig.from_dict(
        {
            "left": {**camera, "T_BS": T_BS_CAM0.tolist()},
            "right": {**camera, "T_BS": T_BS_CAM1.tolist()},
        }
    )
    config = FrontendConfig(subpixel=subpixel)
    detector = FeatureDetector(config)
    matcher = StereoMatcher(config, rig.rectification)
    f_b = CAMERA["f"] * CAMERA["baseline"]
    errors, truths = [], []
    for pose in trajectory.state(np.linspace(0.0, 2.0, 6)).poses() @ T_BS_CAM0:
        left, inv_depth = world.render(pose)
        right, _ = world.render(pose @ invert_pose(T_BS_CAM0) @ T_BS_CAM1)
        points = matcher.match(detector.detect(left), detector.detect(right), left, right)
        u, v = np.rint(points.pixels).astype(int).T
        # Away from depth edges only: there the patch mixes two surfaces.
        edges = cv2.dilate(
            (cv2.Laplacian(inv_depth, cv2.CV_32F) ** 2 > 1e-8).astype(np.uint8), np.ones((15, 15))
        )
        smooth = edges[v, u] == 0
        truth = f_b * inv_depth[v, u].astype(float)
        errors.append((points.disparity - truth)[smooth])
        truths.append(truth[smooth])
    error, truth = np.concatenate(errors), np.concatenate(truths)
    assert len(error) > 1500
    assert np.mean(np.abs(error) < 0.5) > 0.98
    error, truth = error[np.abs(error) < 0.5], truth[np.abs(error) < 0.5]
    assert abs(error.mean()) < 0.01
    assert error.std() < 0.15
    quarter = np.floor((truth % 1.0) * 4).astype(int)
    for q in range(4):
        assert abs(error[quarter == q].mean()) < 0.03, q


def test_stereo_respects_rows_disparity_and_depth_limits() -> None:
    left, right = _two_plane_pair(_texture(6), (1.7, 4.3))
    config = FrontendConfig(max_depth_m=3.0, subpixel="none", stereo_row_tolerance_px=1.0)
    points = _stereo(config, left, right)
    assert len(points) > 100
    assert points.points[:, 2].max() <= 3.0  # the far plane is filtered out entirely
    assert (points.disparity >= config.min_disparity_px).all()
    assert (points.disparity <= config.max_disparity_px).all()
    # A right image moved down by 5 px has no partner within the row band.
    shifted = _shift(right.astype(np.float32), 0.0, 5.0).astype(np.uint8)
    assert len(_stereo(config, left, shifted)) < 0.05 * len(points)


def test_stereo_config_errors() -> None:
    rect = _rig().rectification
    with pytest.raises(ValueError, match="min_disparity_px"):
        StereoMatcher(FrontendConfig(min_disparity_px=50, max_disparity_px=20), rect)
    with pytest.raises(ValueError, match="min_depth_m"):
        StereoMatcher(FrontendConfig(min_depth_m=5, max_depth_m=1), rect)


def test_stereo_on_empty_features() -> None:
    config = FrontendConfig()
    image = np.zeros((HEIGHT, WIDTH), np.uint8)
    empty = Features(np.zeros((0, 2)), np.zeros((0, 32), np.uint8), np.zeros(0), True)
    points = StereoMatcher(config, _rig().rectification).match(empty, empty, image, image)
    assert len(points) == 0 and points.points.shape == (0, 3)


# ----------------------------------------------------------------------------- temporal


@pytest.mark.parametrize("refine", [True, False])
def test_temporal_matches_follow_a_known_shift(refine: bool) -> None:
    texture = _texture(7)
    shift = (3.4, -1.7)  # the scene moves by a fractional pixel amount
    depths = (2.0, 5.0)
    reference_images = _two_plane_pair(texture, depths)
    current_images = _two_plane_pair(texture, depths, *shift)
    config = FrontendConfig(temporal_refine=refine)
    reference = _stereo(config, *reference_images)
    current = _stereo(config, *current_images)
    rect = _rig().rectification
    pairs = match_temporal(
        reference, current, config, rect, images=(reference_images[0], current_images[0])
    )
    assert len(pairs) > 0.5 * min(len(reference), len(current))
    # Each current point must project where its reference pixel went (pixel + shift), and lie
    # at the plane's depth.
    seen_at = project(pairs.current_points, rect.fx, rect.cx, rect.cy)
    expected = reference.pixels[pairs.reference_index] + shift
    pixel_error = np.linalg.norm(seen_at - expected, axis=1)
    # Refined positions are sub-pixel; unrefined ones carry the keypoint grid's rounding.
    assert np.median(pixel_error) < (0.1 if refine else 1.0)
    if not refine:
        assert np.median(pixel_error) > 0.2  # the rounding is really there to be removed
    depth_error = np.minimum(
        *(np.abs(pairs.current_points[:, 2] - depth) / depth for depth in depths)
    )
    assert np.median(depth_error) < 0.01


def test_klt_matcher_follows_a_known_shift() -> None:
    texture = _texture(7)
    shift = (3.4, -1.7)
    depths = (2.0, 5.0)
    reference_images = _two_plane_pair(texture, depths)
    current_images = _two_plane_pair(texture, depths, *shift)
    config = FrontendConfig(temporal_matcher="klt")
    reference = _stereo(config, *reference_images)
    current = _stereo(config, *current_images)
    rect = _rig().rectification
    pairs = match_temporal(
        reference, current, config, rect, images=(reference_images[0], current_images[0])
    )
    assert len(pairs) > 0.5 * min(len(reference), len(current))
    assert len(np.unique(pairs.current_index)) == len(pairs)  # one track per stereo point
    seen_at = project(pairs.current_points, rect.fx, rect.cx, rect.cy)
    expected = reference.pixels[pairs.reference_index] + shift
    assert np.median(np.linalg.norm(seen_at - expected, axis=1)) < 0.1
    with pytest.raises(ValueError, match="needs the reference and current images"):
        match_temporal(reference, current, config, rect)


def test_temporal_search_radius_uses_prediction() -> None:
    texture = _texture(8)
    reference_images = _two_plane_pair(texture, (2.0, 5.0))
    current_images = _two_plane_pair(texture, (2.0, 5.0), 60.0, 0.0)  # a large image motion
    config = FrontendConfig(search_radius_px=20.0)
    reference = _stereo(config, *reference_images)
    current = _stereo(config, *current_images)
    rect = _rig().rectification
    blind = match_temporal(reference, current, config, rect)
    # Predicting the true motion (camera moved -x so points move +x in the image): the
    # near plane moves 60 px, i.e. 60 * 2.0 / 400 = 0.3 m sideways.
    predicted = make_pose(np.eye(3), [60.0 * 2.0 / FOCAL, 0.0, 0.0])
    guided = match_temporal(reference, current, config, rect, predicted)
    assert len(guided) > 100
    assert len(blind) < 0.1 * len(guided)


# ----------------------------------------------------------------------------- benchmark


@pytest.mark.slow
@pytest.mark.euroc
def test_frontend_benchmark_writes_its_report(euroc_v101_micro, tmp_path) -> None:
    import json

    from estimator.cli.main import main

    out = tmp_path / "bench"
    arguments = ["--data", str(euroc_v101_micro), "--frames", "8", "--repeat", "1"]
    code = main(["bench", "frontend", *arguments, "--out", str(out)])
    assert code == 0
    result = json.loads((out / "frontend.json").read_text())
    assert result["frames"] == 8
    stages = result["stages"]
    assert set(stages) == {"rectify", "detect", "stereo", "temporal", "estimate", "fuse", "total"}
    assert stages["total"]["median_ms"] >= stages["detect"]["median_ms"] > 0
    assert result["fps_from_cpu_time"] > 0
    assert result["drift"]["frontend_pose_final_translation_error_m"] < 0.05
    assert (out / "frontend.md").read_text().startswith("Front end on 8 frames 752x480")


# ----------------------------------------------------------------------------- exposure


def _exposed(image: np.ndarray, gain: float, offset: float = 0.0) -> np.ndarray:
    """The image as a camera with another gain and black level records it (8 bits, clipped)."""
    return np.clip(np.rint(image.astype(np.float32) * gain + offset), 0, 255).astype(np.uint8)


def _frontend_stages(config: FrontendConfig, reference_images, current_images) -> dict:
    """Each stage's output for a reference and a current pair, normalised as Odometry does."""
    if config.normalise_contrast:
        reference_images, current_images = (
            tuple(normalise_contrast(i, config.normalised_mean, config.normalised_std) for i in p)
            for p in (reference_images, current_images)
        )
    detector = FeatureDetector(config)
    detections = [len(detector.detect(image)) for image in current_images]
    reference = _stereo(config, *reference_images)
    current = _stereo(config, *current_images)
    rect = _rig().rectification
    pairs = match_temporal(
        reference, current, config, rect, images=(reference_images[0], current_images[0])
    )
    return {"detections": detections, "current": current, "reference": reference, "pairs": pairs}


def test_normalisation_undoes_gain_and_offset() -> None:
    image = _texture(11).astype(np.uint8)[:, :WIDTH]
    darker = _exposed(image, 0.55, 12.0)
    mean, std = 128.0, 64.0
    normalised, normalised_darker = (normalise_contrast(i, mean, std) for i in (image, darker))
    # (The tails of this wide texture clip at 0 and 255, which narrows the spread a little.)
    assert abs(normalised.mean() - mean) < 1.0 and abs(normalised.std() - std) < 4.0
    # Rounding 0.55 I to whole grey levels costs about one level after the stretch back.
    difference = np.abs(normalised.astype(int) - normalised_darker)
    assert np.percentile(difference, 99) <= 2
    # A black (or covered) frame stays flat: its noise is not amplified into texture.
    rng = np.random.default_rng(0)
    dark = np.clip(rng.normal(2.0, 1.0, image.shape), 0, 255).astype(np.uint8)
    assert normalise_contrast(dark, mean, std).std() <= 4.0 * dark.std() + 1e-9


@pytest.mark.parametrize(("left_gain", "right_gain"), [(0.6, 1.3), (1.3, 0.6), (0.6, 0.6)])
def test_exposure_changes_leave_every_stage_unchanged(left_gain: float, right_gain: float) -> None:
    """The current frame's cameras change exposure (not in step): detection counts, stereo
    matches and their disparities, and temporal matches stay as without the change."""
    texture = _texture(7)
    shift, depths = (3.4, -1.7), (2.0, 5.0)
    reference_images = _two_plane_pair(texture, depths)
    current_images = _two_plane_pair(texture, depths, *shift)
    changed = (_exposed(current_images[0], left_gain, 5.0), _exposed(current_images[1], right_gain))
    config = FrontendConfig()
    same = _frontend_stages(config, reference_images, current_images)
    exposed = _frontend_stages(config, reference_images, changed)
    for count, expected in zip(exposed["detections"], same["detections"], strict=True):
        assert abs(count - expected) <= 0.1 * expected
    assert len(exposed["current"]) >= 0.85 * len(same["current"])
    # Stereo points found in both runs (same left pixel) have the same sub-pixel disparity.
    unchanged, changed = same["current"], exposed["current"]
    key = {tuple(p): d for p, d in zip(unchanged.pixels, unchanged.disparity, strict=True)}
    common = [
        (key[tuple(p)], d)
        for p, d in zip(changed.pixels, changed.disparity, strict=True)
        if tuple(p) in key
    ]
    assert len(common) >= 0.7 * len(same["current"])
    before, after = np.array(common).T
    assert np.median(np.abs(after - before)) < 0.05
    pairs = exposed["pairs"]
    assert len(pairs) >= 0.8 * len(same["pairs"])
    rect = _rig().rectification
    seen_at = project(pairs.current_points, rect.fx, rect.cx, rect.cy)
    expected_at = exposed["reference"].pixels[pairs.reference_index] + shift
    assert np.median(np.linalg.norm(seen_at - expected_at, axis=1)) < 0.1


def test_without_normalisation_exposure_changes_break_the_temporal_matches() -> None:
    """Why the normalisation is on: Lucas-Kanade refinement assumes constant brightness."""
    texture = _texture(7)
    reference_images = _two_plane_pair(texture, (2.0, 5.0))
    current_images = _two_plane_pair(texture, (2.0, 5.0), 3.4, -1.7)
    changed = tuple(_exposed(image, 0.6) for image in current_images)
    config = FrontendConfig(normalise_contrast=False)
    same = _frontend_stages(config, reference_images, current_images)
    exposed = _frontend_stages(config, reference_images, changed)
    assert len(exposed["pairs"]) < 0.5 * len(same["pairs"])
