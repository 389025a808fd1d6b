"""Describing only the corners with a possible stereo partner changes no stereo match."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from estimator.config import FrontendConfig
from estimator.formats.calibration import Rectification
from estimator.frontend.features import FeatureDetector
from estimator.frontend.stereo import StereoMatcher, band_partners, row_band_pairs


def _rectification() -> Rectification:
    eye = np.eye(3)
    projection = np.array([[450.0, 0, 376, 0], [0, 450.0, 240, 0], [0, 0, 1, 0]])
    return Rectification(
        (752, 480), 450.0, 376.0, 240.0, 0.11, eye, eye, projection, projection, np.eye(4),
        None, None,
    )  # fmt: skip


def _stereo_pair(seed: int) -> tuple[np.ndarray, np.ndarray]:
    """A textured left image and a right one shifted by a disparity that varies with the row
    (a slanted plane), with a band of texture the other image lacks."""
    rng = np.random.default_rng(seed)
    noise = (rng.random((480, 900)) * 255).astype(np.uint8)
    scene = cv2.normalize(cv2.GaussianBlur(noise, (0, 0), 1.5), None, 0, 255, cv2.NORM_MINMAX)
    left = np.ascontiguousarray(scene[:, 100:852])
    right = np.empty_like(left)
    for row in range(480):
        shift = 10 + row // 20
        right[row] = scene[row, 100 + shift : 852 + shift]
    right[:, 600:] = 128  # right has no texture there: left corners with no partner
    return left, right


def test_band_partners_are_the_points_of_the_candidate_pairs() -> None:
    rng = np.random.default_rng(5)
    for _ in range(20):
        left = rng.uniform(0, 1, (int(rng.integers(0, 300)), 2)) * [752, 480]
        right = rng.uniform(0, 1, (int(rng.integers(0, 300)), 2)) * [752, 480]
        right[::3, 1] = np.round(right[::3, 1])  # rows on the band edges too
        left[::4, 1] = np.round(left[::4, 1]) + 1.5
        ia, ib = row_band_pairs(left, right, 1.5, (1.0, 160.0))
        left_subset, right_subset = band_partners(left, right, 1.5, (1.0, 160.0))
        np.testing.assert_array_equal(left_subset, np.unique(ia))
        np.testing.assert_array_equal(right_subset, np.unique(ib))


@pytest.mark.parametrize("seed", [0, 1])
def test_stereo_points_equal_those_of_describing_every_corner(seed: int) -> None:
    config = FrontendConfig()
    left, right = _stereo_pair(seed)
    matcher = StereoMatcher(config, _rectification())
    detector = FeatureDetector(config)
    everything = matcher.match(detector.detect(left), detector.detect(right), left, right)
    left_features, right_features = matcher.features(detector, left, right)
    subset = matcher.match(left_features, right_features, left, right)
    assert len(everything) > 100
    # The untextured band leaves corners without partners: fewer are described.
    assert len(left_features) < len(detector.corners(left))
    for name in ("pixels", "disparity", "points", "depth_sigma", "descriptors"):
        np.testing.assert_array_equal(getattr(subset, name), getattr(everything, name))


def test_a_subset_is_described_as_in_the_whole_set() -> None:
    detector = FeatureDetector(FrontendConfig())
    image = _stereo_pair(2)[0]
    corners = detector.corners(image)
    whole = detector.describe(image, corners)
    subset = np.arange(0, len(corners), 3)
    part = detector.describe(image, corners, subset)
    np.testing.assert_array_equal(part.points, whole.points[subset])
    np.testing.assert_array_equal(part.descriptors, whole.descriptors[subset])
    assert len(detector.describe(image, corners, np.zeros(0, np.intp))) == 0


def test_sift_has_no_separate_corners_and_still_matches() -> None:
    config = FrontendConfig(detector="sift", max_features=300)
    detector = FeatureDetector(config)
    left, right = _stereo_pair(3)
    with pytest.raises(ValueError, match="ORB"):
        detector.corners(left)
    left_features, right_features = StereoMatcher(config, _rectification()).features(
        detector, left, right
    )
    assert not left_features.binary and len(left_features) > 0 and len(right_features) > 0
