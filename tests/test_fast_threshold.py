"""The adaptive FAST threshold of OpenCV's ORB (run when the compiled detector is not): ORB
keeps the same corners, found among far fewer."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from estimator.config import FrontendConfig
from estimator.formats.datasets import open_sequence
from estimator.frontend import fast_threshold
from estimator.frontend.detection import FeatureDetector
from estimator.frontend.fast_threshold import COUNT_MARGIN, AdaptiveFastThreshold
from estimator.rendered.synthetic import SynthOptions, synthesize


@pytest.fixture(scope="module")
def street_images(tmp_path_factory) -> list[np.ndarray]:
    """Left and right images of a short rendered drive (1241 x 376, street texture)."""
    root = tmp_path_factory.mktemp("street")
    synthesize(root, SynthOptions.driving(frames=3, length_m=3.0, seed=3, imu_noise_scale=0.0))
    sequence = open_sequence(root)
    frames = [sequence.load(index) for index in range(len(sequence))]
    return [image for frame in frames for image in (frame.left, frame.right)]


def _fast_scores_kept_by_orb(image: np.ndarray, threshold: int, edge: int) -> np.ndarray:
    """Scores of FAST corners over the whole image, in the area ORB keeps (the reference)."""
    corners = cv2.FastFeatureDetector_create(threshold, True).detect(image)
    position = cv2.KeyPoint_convert(corners)
    height, width = image.shape
    inside = (
        (position[:, 0] >= edge)
        & (position[:, 0] < width - edge)
        & (position[:, 1] >= edge)
        & (position[:, 1] < height - edge)
    )
    return np.array([c.response for c in corners])[inside], position[inside]


def _sorted(points: np.ndarray, descriptors: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    order = np.lexsort(points.T)
    return points[order], descriptors[order]


def test_strip_scores_are_exactly_those_of_fast_over_the_whole_image(street_images) -> None:
    """Stacking the strips changes no corner and no suppression (the seams are padded)."""
    image = street_images[0]
    counter = AdaptiveFastThreshold(12, 4800, 31)
    scores, scale = counter.estimate_counts(image, 12)
    reference, position = _fast_scores_kept_by_orb(image, 12, 31)
    starts = counter.strip_starts(image.shape[0])
    row = position[:, 1].astype(int)
    in_strips = np.zeros(len(row), dtype=bool)
    for start in starts:
        in_strips |= (row >= start) & (row < start + fast_threshold.STRIP_ROWS)
    assert len(reference[in_strips]) > 100
    np.testing.assert_array_equal(np.sort(scores), np.sort(reference[in_strips]))
    assert scale == pytest.approx((376 - 62) / (len(starts) * fast_threshold.STRIP_ROWS))


def test_threshold_converges_to_the_wanted_count_on_a_street(street_images) -> None:
    """Each image's threshold leaves between 2 n and 1.5 x COUNT_MARGIN x 2 n FAST corners."""
    config = FrontendConfig(max_features=1200)
    wanted = 2 * round(config.max_features * config.detection_oversampling)
    counter = AdaptiveFastThreshold(config.fast_threshold, wanted, 31)
    for image in street_images:
        threshold = counter.choose(image)
        scores, _ = _fast_scores_kept_by_orb(image, config.fast_threshold, 31)
        assert len(scores) > 2 * wanted  # the configured threshold finds far too many
        count = int((scores >= threshold).sum())
        assert threshold > config.fast_threshold + 10
        assert wanted <= count <= 1.5 * COUNT_MARGIN * wanted, (threshold, count)


def test_adaptive_detection_keeps_the_same_corners_and_descriptors(street_images) -> None:
    fixed = FeatureDetector(FrontendConfig(adaptive_fast_threshold=False), opencv_orb=True)
    adaptive = FeatureDetector(FrontendConfig(), opencv_orb=True)
    assert fixed.fast_threshold is None and adaptive.fast_threshold is not None
    for image in street_images:
        expected = fixed.detect(image)
        features = adaptive.detect(image)
        assert adaptive.fast_threshold.last > adaptive.fast_threshold.base
        for mine, theirs in zip(
            _sorted(features.points, features.descriptors),
            _sorted(expected.points, expected.descriptors),
            strict=True,
        ):
            np.testing.assert_array_equal(mine, theirs)


def test_sparse_images_keep_the_configured_threshold_and_are_rechecked(street_images) -> None:
    counter = AdaptiveFastThreshold(12, 4800, 31)
    flat = cv2.GaussianBlur(street_images[0], (0, 0), 6.0)  # too few corners to raise it
    assert counter.choose(flat) == 12
    dense = street_images[1]
    # Sampled again only after RECHECK_EVERY images: until then the base, unsampled.
    chosen = [counter.choose(dense) for _ in range(fast_threshold.RECHECK_EVERY)]
    assert chosen[:-1] == [12] * (fast_threshold.RECHECK_EVERY - 1)
    assert chosen[-1] > 20


def test_an_overestimate_falls_back_to_the_configured_threshold(street_images, monkeypatch) -> None:
    """Should the strips promise corners that the image does not have, ORB runs again at the
    configured threshold: the result is the fixed threshold's."""
    image = street_images[2]
    fixed_config = FrontendConfig(adaptive_fast_threshold=False)
    fixed = FeatureDetector(fixed_config, opencv_orb=True).detect(image)
    detector = FeatureDetector(FrontendConfig(), opencv_orb=True)
    monkeypatch.setattr(detector.fast_threshold, "choose", lambda _image: 120)
    features = detector.detect(image)
    np.testing.assert_array_equal(features.points, fixed.points)
    np.testing.assert_array_equal(features.descriptors, fixed.descriptors)


def test_several_orb_levels_keep_the_fixed_threshold() -> None:
    assert FeatureDetector(FrontendConfig(orb_levels=3), opencv_orb=True).fast_threshold is None
    assert FeatureDetector(FrontendConfig(detector="sift"), opencv_orb=True).fast_threshold is None


def test_right_image_at_the_left_threshold_keeps_the_base_thresholds_corners(
    street_images,
) -> None:
    """The right image, detected at the threshold the left one chose (no sampling), keeps
    exactly the corners and descriptors of a detection at the configured threshold."""
    config = FrontendConfig(max_features=1551)
    adaptive = FeatureDetector(config, opencv_orb=True)
    plain_config = config.model_copy(update={"adaptive_fast_threshold": False})
    plain = FeatureDetector(plain_config, opencv_orb=True)
    raised = 0
    for left, right in zip(street_images[0::2], street_images[1::2], strict=True):
        adaptive.detect(left)
        raised += adaptive.fast_threshold.last > config.fast_threshold
        reused = adaptive.detect(right, same_scene=True)
        base = plain.detect(right)
        for ours, theirs in zip(
            _sorted(reused.points, reused.descriptors),
            _sorted(base.points, base.descriptors),
            strict=True,
        ):
            np.testing.assert_array_equal(ours, theirs)
    assert raised == len(street_images) // 2  # the street is dense: the threshold did rise
