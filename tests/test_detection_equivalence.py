"""The cheaper detection paths give exactly what the straightforward ones give."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from estimator.config import FrontendConfig
from estimator.frontend.features import FeatureDetector, grid_select


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


@pytest.mark.parametrize("levels", [1, 3])
def test_orb_detection_equals_joint_detect_and_compute(levels: int) -> None:
    rng = np.random.default_rng(0)
    noise = (rng.random((480, 752)) * 255).astype(np.uint8)
    image = cv2.GaussianBlur(noise, (0, 0), 1.5)
    image = cv2.normalize(image, None, 0, 255, cv2.NORM_MINMAX)
    config = FrontendConfig(max_features=300, orb_levels=levels)
    detector = FeatureDetector(config)
    features = detector.detect(image)

    keypoints, descriptors = detector._detector.detectAndCompute(image, None)
    points = cv2.KeyPoint_convert(keypoints).astype(float)
    response = np.array([k.response for k in keypoints])
    assert len(keypoints) > config.max_features  # the grid has to drop candidates
    keep = grid_select(points, response, (752, 480), (config.grid_rows, config.grid_cols), 300)
    np.testing.assert_array_equal(features.points, points[keep])
    np.testing.assert_array_equal(features.descriptors, descriptors[keep])
    np.testing.assert_array_equal(features.response, response[keep])
