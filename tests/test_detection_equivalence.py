"""The cheaper detection paths give exactly what the straightforward ones give."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from estimator.config import FrontendConfig
from estimator.frontend.detection import FeatureDetector
from estimator.frontend.features import (
    descriptor_distances,
    grid_select,
    match_candidates,
    strongest_first,
)
from estimator.frontend.match_kernels import (
    as_words,
    band_matches,
    window_matches,
    zero_mean_sad,
)
from estimator.frontend.stereo import row_band_pairs


def _lexsort_grid_select(points, response, image_size, grid, budget):
    """Reference: round-robin over cells by rank with two lexsorts."""
    if len(points) <= budget:
        return np.arange(len(points))
    width, height = image_size
    rows, cols = grid
    col = np.clip((points[:, 0] * cols / width).astype(np.intp), 0, cols - 1)
    row = np.clip((points[:, 1] * rows / height).astype(np.intp), 0, rows - 1)
    cell = row * cols + col
    by_cell = np.lexsort((-response, cell))
    rank = np.empty(len(points), dtype=np.intp)
    for position, index in enumerate(by_cell):
        same = cell[by_cell[:position]] == cell[index]
        rank[index] = int(same.sum())
    return np.sort(np.lexsort((-response, rank))[:budget])


def test_grid_select_matches_the_lexsort_order_with_ties() -> None:
    rng = np.random.default_rng(3)
    for _ in range(20):
        count = int(rng.integers(50, 400))
        points = rng.uniform(0, 1, (count, 2)) * [752, 480]
        response = np.round(rng.exponential(1.0, count), 1)  # many equal strengths
        expected = _lexsort_grid_select(points, response, (752, 480), (6, 8), 40)
        chosen = grid_select(points, response, (752, 480), (6, 8), 40)
        np.testing.assert_array_equal(chosen, expected)


def test_strongest_first_orders_by_response_then_row_then_column() -> None:
    rng = np.random.default_rng(5)
    for raster in (True, False):
        for _ in range(20):
            count = int(rng.integers(2, 600))
            cells = rng.choice(752 * 480, count, replace=False)
            points = np.column_stack((cells % 752, cells // 752)).astype(float)
            if raster:
                points = points[np.lexsort((points[:, 0], points[:, 1]))]
            response = np.round(rng.exponential(1.0, count), 1).astype(np.float32)  # ties
            expected = sorted(
                range(count), key=lambda i: (-response[i], points[i, 1], points[i, 0])
            )
            np.testing.assert_array_equal(strongest_first(points, response), expected)


def _textured(seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    noise = (rng.random((480, 752)) * 255).astype(np.uint8)
    image = cv2.GaussianBlur(noise, (0, 0), 1.5)
    return cv2.normalize(image, None, 0, 255, cv2.NORM_MINMAX)


@pytest.mark.parametrize("levels", [1, 3])
def test_orb_detection_equals_joint_detect_and_compute(levels: int) -> None:
    image = _textured(0)
    config = FrontendConfig(max_features=300, orb_levels=levels)
    detector = FeatureDetector(config, opencv_orb=True)
    features = detector.detect(image)

    keypoints, descriptors = detector._detector.detectAndCompute(image, None)
    points = cv2.KeyPoint_convert(keypoints).astype(float)
    raster = np.lexsort((points[:, 0], points[:, 1]))  # the detector's order
    points, descriptors = points[raster], descriptors[raster]
    response = np.array([k.response for k in keypoints])[raster]
    assert len(keypoints) > config.max_features  # the grid has to drop candidates
    keep = grid_select(points, response, (752, 480), (config.grid_rows, config.grid_cols), 300)
    # Handed out strongest first, equal responses by row, then column.
    keep = keep[np.lexsort((points[keep, 0], points[keep, 1], -response[keep]))]
    np.testing.assert_array_equal(features.points, points[keep])
    np.testing.assert_array_equal(features.descriptors, descriptors[keep])
    np.testing.assert_array_equal(features.response, response[keep])


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_band_matches_equal_pairs_distances_and_ratio_test(seed: int) -> None:
    """The compiled stereo matching gives the matches of the three NumPy steps, ties included
    (few distinct descriptors: many equal distances)."""
    rng = np.random.default_rng(seed)
    count = 400
    left = rng.uniform(0, 1, (count, 2)) * [752, 60]
    right = left + np.column_stack([-rng.uniform(-5, 80, count), rng.normal(0, 1.0, count)])
    right = np.round(right[rng.permutation(count)], 1)
    palette = rng.integers(0, 256, (12, 32), dtype=np.uint8)
    left_descriptors = palette[rng.integers(0, 12, count)]
    right_descriptors = palette[rng.integers(0, 12, count)]
    ia, ib = row_band_pairs(left, right, 1.5, (1.0, 60.0))
    distance = descriptor_distances(left_descriptors, right_descriptors, ia, ib, True)
    expected = match_candidates(ia, ib, distance, ratio=0.9, max_distance=110)

    order = np.argsort(right[:, 1], kind="stable")
    low = np.searchsorted(right[order, 1], left[:, 1] - 1.5, side="left")
    high = np.searchsorted(right[order, 1], left[:, 1] + 1.5, side="right")
    a, b, found = band_matches(
        left[:, 0].copy(), right[:, 0].copy(), as_words(left_descriptors),
        as_words(right_descriptors), order, low, high, (1.0, 60.0), 0.9, 110.0,
    )  # fmt: skip
    assert len(expected) > 20
    np.testing.assert_array_equal(a, expected.a)
    np.testing.assert_array_equal(b, expected.b)
    np.testing.assert_array_equal(found, expected.distance)


def test_zero_mean_sad_equals_patch_arithmetic() -> None:
    rng = np.random.default_rng(4)
    left = rng.integers(0, 256, (60, 80), dtype=np.uint8)
    right = rng.integers(0, 256, (60, 80), dtype=np.uint8)
    u, v, right_u = (rng.integers(10, 50, 30) for _ in range(3))
    shifts = np.arange(-2, 3)
    costs = zero_mean_sad(left, right, u, v, right_u, 5, shifts)
    for index in range(30):
        patch = left[v[index] - 5 : v[index] + 6, u[index] - 5 : u[index] + 6].astype(int)
        for k, shift in enumerate(shifts):
            x = right_u[index] + shift
            other = right[v[index] - 5 : v[index] + 6, x - 5 : x + 6].astype(int)
            expected = np.abs((other - other.sum() // 121) - (patch - patch.sum() // 121)).sum()
            assert costs[index, k] == expected


def _brute_force_window_matches(expected, observed, da, db, radius, ratio, max_distance):
    """Reference: every pair within each expected point's radius, nearest + ratio test, mutual
    with ties of a current point going to the smallest reference index."""
    distance = np.unpackbits(da[:, None, :] ^ db[None, :, :], axis=2).sum(axis=2).astype(float)
    gaps = np.linalg.norm(expected[:, None, :] - observed[None, :, :], axis=2)
    near = gaps <= np.asarray(radius)[:, None]
    distance[~near] = np.inf
    matches = []
    for i in range(len(expected)):
        row = np.sort(distance[i])
        if not np.isfinite(row[0]) or row[0] > max_distance or not row[0] < ratio * row[1]:
            continue
        j = int(np.argmin(distance[i]))
        if int(np.argmin(distance[:, j])) == i:  # argmin: the smallest index on ties
            matches.append((i, j, row[0]))
    return matches


@pytest.mark.parametrize(("seed", "per_point"), [(0, False), (1, False), (2, True), (3, True)])
def test_window_matches_equal_brute_force(seed: int, per_point: bool) -> None:
    rng = np.random.default_rng(seed)
    expected = rng.uniform(0, 200, (150, 2))
    observed = np.round(expected[rng.permutation(150)] + rng.normal(0, 3, (150, 2)), 1)
    palette = rng.integers(0, 256, (20, 32), dtype=np.uint8)
    da, db = palette[rng.integers(0, 20, 150)], palette[rng.integers(0, 20, 150)]
    radii = rng.uniform(4.0, 30.0, 150) if per_point else np.full(150, 15.0)
    order = np.argsort(observed[:, 1], kind="stable")
    low = np.searchsorted(observed[order, 1], expected[:, 1] - radii, side="left")
    high = np.searchsorted(observed[order, 1], expected[:, 1] + radii, side="right")
    a, b, distance = window_matches(
        expected, observed, as_words(da), as_words(db), order, low, high, radii, 0.85, 100.0
    )
    reference = _brute_force_window_matches(expected, observed, da, db, radii, 0.85, 100.0)
    assert len(reference) > 10
    assert list(zip(a.tolist(), b.tolist(), distance.tolist(), strict=True)) == reference
