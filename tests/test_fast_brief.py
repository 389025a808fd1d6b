"""The compiled detector: FAST, Harris, orientation and descriptors against slow references
and against OpenCV's ORB (the same features to the bit), the rotation behaviour of the
descriptor, and the seeded test pairs of fast-brief."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from estimator.config import FrontendConfig
from estimator.frontend import steered_brief
from estimator.frontend.detection import FeatureDetector
from estimator.frontend.fast_kernels import CIRCLE, HARRIS_K, fast_corners, harris_response
from estimator.frontend.orb_pattern import measure_orb_pattern
from estimator.frontend.steered_brief import (
    PATCH_RADIUS,
    PATTERN,
    describe,
    orb_pattern,
    orientation,
    seeded_pattern,
    smoothed,
)


def _texture(shape: tuple[int, int], seed: int, blur: float = 1.5) -> np.ndarray:
    """Smoothed random blocks with contrast: many corners, grey values from 0 to 255."""
    rng = np.random.default_rng(seed)
    small = rng.integers(0, 256, size=(shape[0] // 4 + 1, shape[1] // 4 + 1)).astype(np.uint8)
    image = cv2.resize(small, (shape[1], shape[0]), interpolation=cv2.INTER_NEAREST)
    image = cv2.GaussianBlur(image, (0, 0), blur)
    return cv2.normalize(image, None, 0, 255, cv2.NORM_MINMAX)


def _slow_fast(image: np.ndarray, threshold: int, border: int) -> dict[tuple[int, int], int]:
    """FAST-9 by its definition: score = largest t with a 9-arc beyond t, minus one; kept
    when above all 8 neighbours' scores (0 for no corner)."""
    height, width = image.shape
    score = np.zeros((height, width), dtype=int)
    for y in range(3, height - 3):
        for x in range(3, width - 3):
            centre = int(image[y, x])
            diff = [int(image[y + dy, x + dx]) - centre for dx, dy in CIRCLE]
            best = max(
                min(sign * diff[(start + k) % 16] for k in range(9))
                for start in range(16)
                for sign in (1, -1)
            )
            if best - 1 >= threshold:
                score[y, x] = best - 1
    kept = {}
    for y in range(border, height - border):
        for x in range(border, width - border):
            around = score[y - 1 : y + 2, x - 1 : x + 2].copy()
            around[1, 1] = -1
            if score[y, x] > 0 and score[y, x] > around.max():
                kept[(x, y)] = int(score[y, x])
    return kept


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("threshold", [5, 12, 40])
def test_fast_matches_the_definition(seed: int, threshold: int) -> None:
    image = _texture((48, 56), seed)
    image[10:14, 20:24] = 255  # saturated bright and dark spots: the bounds clip at 0 and 255
    image[30:33, 8:11] = 0
    xs, ys, score = fast_corners(image, threshold, 4)
    found = dict(zip(zip(xs.tolist(), ys.tolist(), strict=True), score.tolist(), strict=True))
    expected = _slow_fast(image, threshold, 4)
    assert found == expected
    assert len(expected) > 5  # the test image has corners to compare
    raster = list(zip(ys.tolist(), xs.tolist(), strict=True))
    assert raster == sorted(raster)


def test_fast_matches_opencv_on_a_large_image() -> None:
    image = _texture((240, 320), 7, blur=1.0)
    xs, ys, score = fast_corners(image, 12, 31)
    reference = cv2.FastFeatureDetector_create(12, True).detect(image)
    expected = {
        (round(k.pt[0]), round(k.pt[1])): round(k.response)
        for k in reference
        if 31 <= k.pt[0] < 320 - 31 and 31 <= k.pt[1] < 240 - 31
    }
    assert len(expected) > 200
    corners = zip(xs.tolist(), ys.tolist(), strict=True)
    assert dict(zip(corners, score.tolist(), strict=True)) == expected


def test_fast_rejects_bad_input() -> None:
    with pytest.raises(ValueError, match="8-bit grey"):
        fast_corners(np.zeros((40, 40), dtype=np.float32), 12, 4)
    with pytest.raises(ValueError, match="threshold"):
        fast_corners(np.zeros((40, 40), dtype=np.uint8), 0, 4)
    xs, _, _ = fast_corners(np.zeros((5, 5), dtype=np.uint8), 12, 3)  # too small: no corner
    assert len(xs) == 0


def test_kernels_refuse_points_near_the_edge() -> None:
    image = _texture((80, 80), 8)
    with pytest.raises(ValueError, match="inside"):
        harris_response(image, np.array([2]), np.array([40]))
    with pytest.raises(ValueError, match="edge"):
        orientation(image, np.array([40]), np.array([70]))
    with pytest.raises(ValueError, match="edge"):
        describe(smoothed(image), np.array([10]), np.array([40]), np.zeros(1))


def test_harris_matches_a_slow_reference() -> None:
    image = _texture((60, 60), 3)
    xs, ys = np.array([10, 30, 45, 20]), np.array([12, 30, 20, 47])
    gx = cv2.Sobel(image.astype(np.float64), cv2.CV_64F, 1, 0, ksize=3)
    gy = cv2.Sobel(image.astype(np.float64), cv2.CV_64F, 0, 1, ksize=3)
    expected = []
    for x, y in zip(xs, ys, strict=True):
        bx, by = gx[y - 3 : y + 4, x - 3 : x + 4], gy[y - 3 : y + 4, x - 3 : x + 4]
        a, b, c = (bx * bx).sum(), (by * by).sum(), (bx * by).sum()
        expected.append((a * b - c * c - HARRIS_K * (a + b) ** 2) / (4 * 7 * 255.0) ** 4)
    # Formed in float32 as ORB forms it: a few units in the last place of float32.
    np.testing.assert_allclose(harris_response(image, xs, ys), expected, rtol=1e-5)


def _slow_angle(image: np.ndarray, x: int, y: int) -> float:
    """Degrees of the intensity centroid over ORB's disc: rows |v| <= 15 of half width
    round(sqrt(15^2 - v^2)), the rows past the diagonal mirrored from the columns."""
    widths = [round(math.sqrt(PATCH_RADIUS**2 - v * v)) for v in range(PATCH_RADIUS + 1)]
    for v in range(11, PATCH_RADIUS + 1):  # past the diagonal: the disc is symmetric in u, v
        widths[v] = max(u for u in range(PATCH_RADIUS + 1) if widths[u] >= v)
    m10 = m01 = 0.0
    for v in range(-PATCH_RADIUS, PATCH_RADIUS + 1):
        for u in range(-widths[abs(v)], widths[abs(v)] + 1):
            m10 += u * float(image[y + v, x + u])
            m01 += v * float(image[y + v, x + u])
    return math.degrees(math.atan2(m01, m10)) % 360.0


def _slow_descriptor(
    smooth: np.ndarray, x: int, y: int, degrees: float, pattern: np.ndarray
) -> np.ndarray:
    theta = math.radians(degrees)
    cos, sin = math.cos(theta), math.sin(theta)
    bits = []
    for x1, y1, x2, y2 in pattern.tolist():
        u1, v1 = round(x1 * cos - y1 * sin), round(x1 * sin + y1 * cos)
        u2, v2 = round(x2 * cos - y2 * sin), round(x2 * sin + y2 * cos)
        bits.append(int(smooth[y + v1, x + u1] < smooth[y + v2, x + u2]))
    return np.packbits(np.array(bits, dtype=np.uint8), bitorder="little")


def test_orientation_and_descriptor_match_slow_references() -> None:
    image = _texture((90, 100), 4)
    xs, ys = np.array([30, 50, 66, 40]), np.array([30, 45, 58, 60])
    angle = orientation(image, xs, ys)
    assert angle.dtype == np.float32
    expected = [_slow_angle(image, x, y) for x, y in zip(xs, ys, strict=True)]
    # OpenCV's polynomial arctangent: within 0.01 deg of the exact angle.
    np.testing.assert_allclose(angle, expected, atol=0.01)
    smooth = smoothed(image)
    for pattern in (PATTERN, orb_pattern()):
        descriptors = describe(smooth, xs, ys, angle, pattern)
        assert descriptors.shape == (4, 32) and descriptors.dtype == np.uint8
        for k in range(4):
            slow = _slow_descriptor(smooth, int(xs[k]), int(ys[k]), float(angle[k]), pattern)
            # A test point exactly half-way between pixels may round the other way.
            assert _hamming(descriptors[k], slow) <= 2


def _orb_reference(image: np.ndarray, count: int) -> tuple[list, np.ndarray]:
    orb = cv2.ORB_create(nfeatures=count, nlevels=1)
    return orb.detectAndCompute(image, None)


@pytest.mark.parametrize("seed", [0, 1])
def test_compiled_kernels_equal_opencvs_orb(seed: int) -> None:
    """Angles, Harris responses and descriptors of ORB's own corners, to the bit."""
    image = _texture((240, 320), 10 + seed, blur=1.0)
    keypoints, expected = _orb_reference(image, 500)
    assert len(keypoints) > 300
    xs = np.array([round(k.pt[0]) for k in keypoints])
    ys = np.array([round(k.pt[1]) for k in keypoints])
    angle = orientation(image, xs, ys)
    np.testing.assert_array_equal(angle, np.array([k.angle for k in keypoints], np.float32))
    response = harris_response(image, xs, ys)
    np.testing.assert_array_equal(response, [k.response for k in keypoints])
    np.testing.assert_array_equal(describe(smoothed(image), xs, ys, angle, orb_pattern()), expected)


def test_measured_orb_pattern() -> None:
    """ORB's tests read back from OpenCV: 256 distinct pairs of distinct points in the patch,
    and ORB's descriptors depend on exactly those pixels (a fresh measurement agrees)."""
    pattern = orb_pattern()
    assert pattern is not None and pattern.shape == (256, 4)
    np.testing.assert_array_equal(measure_orb_pattern(), pattern)
    assert np.abs(pattern).max() <= PATCH_RADIUS
    assert not np.any((pattern[:, 0] == pattern[:, 2]) & (pattern[:, 1] == pattern[:, 3]))
    assert len({tuple(row) for row in pattern.tolist()}) == 256
    assert not np.array_equal(pattern, PATTERN)


def _hamming(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.unpackbits(np.bitwise_xor(a, b), axis=-1).sum(axis=-1)


@pytest.mark.parametrize("degrees", [90, 30, -135])
def test_descriptor_follows_a_rotated_patch(degrees: int) -> None:
    """Rotating the image about a corner turns its angle by as much and keeps its descriptor
    close; unrelated corners stay far apart."""
    size = 161
    image = _texture((size, size), 5, blur=2.0)
    centre = size // 2
    rotation = cv2.getRotationMatrix2D((centre, centre), degrees, 1.0)  # counter-clockwise
    turned = cv2.warpAffine(image, rotation, (size, size), flags=cv2.INTER_LINEAR)
    offsets = [(-12, -8), (0, 0), (10, 14), (-15, 11), (13, -12), (5, -3)]
    xs = np.array([centre + dx for dx, _ in offsets])
    ys = np.array([centre + dy for _, dy in offsets])
    a = rotation[:, :2]
    moved = (a @ np.stack([xs - centre, ys - centre])).round().astype(int) + centre
    before = orientation(image, xs, ys)
    after = orientation(turned, moved[0], moved[1])
    # Image rows point down: a counter-clockwise turn on screen lowers the angle.
    turn = np.angle(np.exp(1j * np.radians(before - after - degrees)))
    # Off the right angles the turned corner lands up to 0.7 px off a pixel and is resampled.
    assert np.abs(turn).max() < np.radians(0.01 if degrees == 90 else 10)
    d_before = describe(smoothed(image), xs, ys, before)
    d_after = describe(smoothed(turned), moved[0], moved[1], after)
    same = _hamming(d_before, d_after)
    unrelated = _hamming(d_before, np.roll(d_after, 1, axis=0))
    assert same.max() <= (0 if degrees == 90 else 40)  # a right angle moves pixels exactly
    assert unrelated.min() > 64


def test_pattern_is_seeded_and_inside_the_patch() -> None:
    np.testing.assert_array_equal(seeded_pattern(), PATTERN)
    assert not np.array_equal(seeded_pattern(seed=1), PATTERN)
    assert PATTERN.shape == (256, 4)
    assert np.abs(PATTERN).max() <= PATCH_RADIUS
    assert not np.any((PATTERN[:, 0] == PATTERN[:, 2]) & (PATTERN[:, 1] == PATTERN[:, 3]))
    # Rotated, every test point stays within the descriptor border (smoothing included).
    radius = np.hypot(PATTERN[:, [0, 2]], PATTERN[:, [1, 3]]).max()
    assert radius + 0.5 + steered_brief.SMOOTHING_KERNEL // 2 <= steered_brief.DESCRIPTOR_BORDER


def _assert_same_features(a, b) -> None:
    np.testing.assert_array_equal(a.points, b.points)
    np.testing.assert_array_equal(a.response, b.response)
    np.testing.assert_array_equal(a.descriptors, b.descriptors)


@pytest.mark.parametrize("shape", [(480, 752), (376, 1241)])
def test_compiled_orb_gives_opencvs_features(shape: tuple[int, int]) -> None:
    """The default detector runs compiled and gives what OpenCV's ORB gives, strongest
    first, image after image (the adaptive thresholds of both at work on wide images)."""
    config = FrontendConfig(max_features=600 if shape[1] > 1000 else 1200)
    compiled, reference = FeatureDetector(config), FeatureDetector(config, opencv_orb=True)
    assert compiled.compiled and not reference.compiled
    for index in range(4):  # two stereo-like pairs: the second image is the first shifted
        image = _texture(shape, 6 + index // 2, blur=1.0 + 0.3 * (index // 2))
        same_scene = index % 2 == 1
        if same_scene:
            image = np.roll(image, -4, axis=1)
        ours, theirs = compiled.detect(image, same_scene), reference.detect(image, same_scene)
        assert len(ours) == config.max_features
        _assert_same_features(ours, theirs)
        order = list(zip((-ours.response).tolist(), ours.points[:, 1].tolist(),
                         ours.points[:, 0].tolist(), strict=True))  # fmt: skip
        assert order == sorted(order)  # strongest first, ties by row, then column


def test_opencvs_orb_runs_for_pyramids_and_fast_brief_keeps_orbs_corners() -> None:
    assert not FeatureDetector(FrontendConfig(orb_levels=3)).compiled
    image = _texture((480, 752), 6, blur=1.2)
    orb = FeatureDetector(FrontendConfig()).detect(image)
    compiled = FeatureDetector(FrontendConfig(detector="fast-brief"))
    first, second = compiled.detect(image), compiled.detect(image.copy())
    assert first.binary and first.descriptors.shape == (len(first), 32)
    assert len(first) == FrontendConfig().max_features
    np.testing.assert_array_equal(first.points, orb.points)
    assert (first.descriptors != orb.descriptors).any(axis=1).mean() > 0.9  # its own tests
    _assert_same_features(first, second)
    blank = compiled.detect(np.full((480, 752), 128, dtype=np.uint8))
    assert len(blank) == 0 and blank.descriptors.shape == (0, 32)


def test_raised_threshold_keeps_the_same_corners() -> None:
    """On wide street images (a surplus of corners) the threshold is raised from the last
    image's cut; every image gives what a fresh detector at the configured threshold gives."""
    root_images = []
    for seed in (0, 1, 2):
        image = _texture((376, 1241), seed, blur=0.8)
        root_images += [image, np.roll(image, 3, axis=1)]
    config = FrontendConfig(detector="fast-brief", max_features=600)
    running = FeatureDetector(config)
    raised = 0
    for index, image in enumerate(root_images):
        features = running.detect(image, same_scene=index % 2 == 1)
        raised += running.compiled_orb.threshold > config.fast_threshold
        fresh = FeatureDetector(config).detect(image)
        np.testing.assert_array_equal(features.points, fresh.points)
        np.testing.assert_array_equal(features.descriptors, fresh.descriptors)
    assert raised >= 4  # the raised threshold was in use for most images


def test_compiled_detector_without_the_adaptive_threshold_keeps_the_configured_one() -> None:
    image = _texture((376, 1241), 3, blur=0.8)
    fixed = FeatureDetector(FrontendConfig(adaptive_fast_threshold=False, max_features=600))
    adaptive = FeatureDetector(FrontendConfig(max_features=600))
    for _ in range(2):
        _assert_same_features(fixed.detect(image), adaptive.detect(image))
    assert fixed.compiled_orb.threshold == 12 and adaptive.compiled_orb.threshold > 12



def test_an_opencv_whose_orb_cannot_be_reproduced_runs_opencvs_orb(monkeypatch, caplog) -> None:
    """Should the measured tests or the check against OpenCV fail (another OpenCV build), the
    detector says so once and runs OpenCV's ORB itself, with the same answers' shape."""

    def refuse() -> np.ndarray:
        raise steered_brief.OrbPatternError("probe failed")

    monkeypatch.setattr(steered_brief, "measure_orb_pattern", refuse)
    orb_pattern.cache_clear()
    try:
        with caplog.at_level("WARNING"):
            detector = FeatureDetector(FrontendConfig())
        assert not detector.compiled
        assert "compiled ORB unavailable" in caplog.text
        features = detector.detect(_texture((480, 752), 6, blur=1.2))
        assert len(features) == FrontendConfig().max_features
    finally:
        monkeypatch.undo()
        orb_pattern.cache_clear()
    assert FeatureDetector(FrontendConfig()).compiled
