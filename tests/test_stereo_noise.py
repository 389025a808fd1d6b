"""The session's stereo noise model: recovers a known pixel / disparity noise, measures tails."""

from __future__ import annotations

import numpy as np
import pytest

from estimator.formats.calibration import StereoRig
from estimator.frontend.stereo import point_covariances
from estimator.frontend.stereo_noise import NoiseLevel, StereoNoiseModel
from estimator.geometry import quat_to_matrix, rotation_vector_to_quat
from estimator.registration.refine import CHI2_3_MEDIAN

F, CX, CY, BASELINE = 450.0, 376.0, 240.0, 0.11
PRIOR = NoiseLevel(1.0, 1.0, 0.5)


def _rectification():
    camera = {
        "width": 752, "height": 480, "fx": F, "fy": F, "cx": CX, "cy": CY,
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


def _triangulate(uvd: np.ndarray) -> np.ndarray:
    depth = F * BASELINE / uvd[:, 2]
    return np.column_stack([(uvd[:, 0] - CX) * depth / F, (uvd[:, 1] - CY) * depth / F, depth])


def _measured(points: np.ndarray, sigmas: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Stereo points re-triangulated from (u, v, d) with Gaussian noise of per-point sigmas."""
    uvd = np.column_stack(
        [F * points[:, 0] / points[:, 2] + CX, F * points[:, 1] / points[:, 2] + CY,
         F * BASELINE / points[:, 2]]
    )  # fmt: skip
    return _triangulate(uvd + rng.normal(size=uvd.shape) * sigmas)


def _frame(level: NoiseLevel, rng: np.random.Generator, count: int = 300, wild: float = 0.0):
    """Inlier pairs of one frame: reference ~ R current + t, both measured with ``level``;
    a fraction ``wild`` of the points has ten times the noise (blur, edges)."""
    depth = rng.uniform(1.5, 20.0, count)
    pixels = rng.uniform([20, 20], [732, 460], size=(count, 2))
    reference = np.column_stack([(pixels - [CX, CY]) * depth[:, None] / F, depth])
    rotation = quat_to_matrix(rotation_vector_to_quat(rng.normal(0, np.radians(1.5), 3)))
    translation = rng.normal(0, 0.03, 3)
    current = (reference - translation) @ rotation  # R^T (p - t)
    sigmas = np.tile(level.as_tuple(), (count, 1))
    sigmas[rng.random(count) < wild] *= 10.0
    return _measured(reference, sigmas, rng), _measured(current, sigmas, rng), rotation, translation


def test_a_known_noise_level_is_recovered() -> None:
    rng = np.random.default_rng(4)
    truth = NoiseLevel(0.3, 0.2, 0.15)
    model = StereoNoiseModel(_rectification(), PRIOR)
    for _ in range(20):
        model.update(*_frame(truth, rng))
    # Within 15 %: the point covariances linearise Z = f b / d (far points are skewed).
    np.testing.assert_allclose(model.level.as_tuple(), truth.as_tuple(), rtol=0.15)
    summary = model.summary()
    assert abs(summary["median_squared_mahalanobis"] / CHI2_3_MEDIAN - 1.0) < 0.15
    assert model.tail < 1.3  # Gaussian noise: the measured tail is the Gaussian one ...
    # ... and the gate stays at the prior's (the tail, truncated by the gate, cannot narrow it).
    assert model.gate_chi2 == pytest.approx(16.266 * model.prior_tail**2)


def test_heavy_tails_widen_the_gate_but_not_the_level() -> None:
    rng = np.random.default_rng(5)
    truth = NoiseLevel(0.2, 0.2, 0.1)
    gaussian = StereoNoiseModel(_rectification(), PRIOR)
    heavy = StereoNoiseModel(_rectification(), PRIOR)
    for _ in range(15):
        gaussian.update(*_frame(truth, rng))
        heavy.update(*_frame(truth, rng, wild=0.05))
    assert heavy.gate_chi2 > 3.0 * gaussian.gate_chi2
    # The level is the typical feature's, not inflated by the wild 5 %.
    np.testing.assert_allclose(heavy.level.as_tuple(), truth.as_tuple(), rtol=0.3)


def test_the_prior_holds_until_there_are_enough_pairs() -> None:
    rng = np.random.default_rng(6)
    model = StereoNoiseModel(_rectification(), PRIOR)
    reference, current, rotation, translation = _frame(NoiseLevel(0.3, 0.3, 0.3), rng, count=5)
    assert model.update(reference, current, rotation, translation) is None
    assert model.level == PRIOR
    assert model.summary()["median_squared_mahalanobis"] is None


@pytest.mark.parametrize(
    ("option", "value"), [("memory", 1.0), ("memory", -0.1), ("prior_pairs", 0)]
)
def test_bad_settings_are_rejected(option: str, value: float) -> None:
    with pytest.raises(ValueError, match=option):
        StereoNoiseModel(_rectification(), PRIOR, **{option: value})


def _moving_frame(level: NoiseLevel, gain: float, turn_deg: float, rng: np.random.Generator):
    """Inlier pairs of a frame that turns by ``turn_deg``; each pair's sigmas grow with its
    image flow as level * (1 + gain * flow)."""
    count = 300
    depth = rng.uniform(1.5, 20.0, count)
    pixels = rng.uniform([20, 20], [732, 460], size=(count, 2))
    reference = np.column_stack([(pixels - [CX, CY]) * depth[:, None] / F, depth])
    axis = rng.normal(size=3)
    axis *= np.radians(turn_deg) / np.linalg.norm(axis)
    rotation = quat_to_matrix(rotation_vector_to_quat(axis))
    translation = rng.normal(0, 0.02, 3)
    current = (reference - translation) @ rotation  # R^T (p - t)
    flow = np.linalg.norm(F * current[:, :2] / current[:, 2:] + [CX, CY] - pixels, axis=1)
    sigmas = np.outer(1.0 + gain * flow, level.as_tuple())
    return _measured(reference, sigmas, rng), _measured(current, sigmas, rng), rotation, translation


def test_the_growth_of_the_noise_with_the_image_flow_is_measured() -> None:
    rng = np.random.default_rng(7)
    level, gain = NoiseLevel(0.06, 0.06, 0.05), 0.05
    model = StereoNoiseModel(_rectification(), PRIOR)
    for turn in np.tile([0.5, 2.0, 4.0, 6.0], 5):
        model.update(*_moving_frame(level, gain, float(turn), rng))
    assert model.gain == pytest.approx(gain, rel=0.3)
    # A frame that moves far more than the recent ones gets a wider gate; a slow one does not
    # get a narrower one than the session's.
    fast = _moving_frame(level, gain, 12.0, rng)
    slow = _moving_frame(level, gain, 0.2, rng)
    assert model.gate_for(fast[1], fast[0]) > 1.5 * model.gate_chi2
    assert model.gate_for(slow[1], slow[0]) == model.gate_chi2


def test_noise_that_does_not_grow_with_the_flow_gives_no_gain() -> None:
    rng = np.random.default_rng(8)
    model = StereoNoiseModel(_rectification(), PRIOR)
    for turn in np.tile([0.5, 2.0, 4.0, 6.0], 5):
        model.update(*_moving_frame(NoiseLevel(0.2, 0.2, 0.1), 0.0, float(turn), rng))
    assert model.gain < 0.005


def test_the_compiled_covariances_are_the_array_formula_bit_for_bit() -> None:
    """The model's covariances (one compiled pass) equal ``stereo.point_covariances``."""
    rng = np.random.default_rng(11)
    rectification = _rectification()
    uvd = np.column_stack([rng.uniform(0, 752, 300), rng.uniform(0, 480, 300),
                           rng.uniform(0.5, 90.0, 300)])  # fmt: skip
    points = _triangulate(uvd)
    for level in (PRIOR, NoiseLevel(0.137, 0.0912, 0.3141)):
        model = StereoNoiseModel(rectification, level)
        expected = point_covariances(points, rectification, *level.as_tuple())
        np.testing.assert_array_equal(model.covariances(points), expected)
        np.testing.assert_array_equal(model.covariances(points[:0]), expected[:0])


def _growing_frame(level: NoiseLevel, gain: float, rng: np.random.Generator, count: int = 300):
    """Inlier pairs of one frame whose disparity noise grows with the disparity:
    sigma_d x (1 + gain x d) for each point (pixel noise as ``level``)."""
    depth = rng.uniform(0.6, 20.0, count)  # disparities of 2.5-80 px
    pixels = rng.uniform([20, 20], [732, 460], size=(count, 2))
    reference = np.column_stack([(pixels - [CX, CY]) * depth[:, None] / F, depth])
    rotation = quat_to_matrix(rotation_vector_to_quat(rng.normal(0, np.radians(1.0), 3)))
    translation = rng.normal(0, 0.02, 3)
    current = (reference - translation) @ rotation  # R^T (p - t)

    def sigmas(points: np.ndarray) -> np.ndarray:
        disparity = F * BASELINE / points[:, 2]
        result = np.tile(level.as_tuple(), (len(points), 1))
        result[:, 2] *= 1.0 + gain * disparity
        return result

    measured = (_measured(points, sigmas(points), rng) for points in (reference, current))
    return *measured, rotation, translation


def test_the_growth_of_the_disparity_noise_with_the_disparity_is_measured() -> None:
    rng = np.random.default_rng(12)
    level, gain = NoiseLevel(0.08, 0.08, 0.03), 0.04
    model = StereoNoiseModel(_rectification(), PRIOR)
    for _ in range(25):
        model.update(*_growing_frame(level, gain, rng))
    assert model.disparity_gain == pytest.approx(gain, rel=0.3)
    # The level's disparity noise is the one at the typical disparity, and each point's
    # covariance then has the noise of its own disparity along the ray.
    typical = model.typical_disparity
    assert model.level.sigma_d_px == pytest.approx(0.03 * (1.0 + gain * typical), rel=0.2)
    near, far = _triangulate(np.array([[376.0, 240.0, 70.0], [376.0, 240.0, 4.0]]))
    for point, disparity in ((near, 70.0), (far, 4.0)):
        depth_sigma = np.sqrt(model.covariances(point[None])[0, 2, 2])
        expected = point[2] / disparity * 0.03 * (1.0 + gain * disparity)  # Z sigma_d / d
        assert depth_sigma == pytest.approx(expected, rel=0.25)
    assert abs(model.summary()["median_squared_mahalanobis"] / CHI2_3_MEDIAN - 1.0) < 0.15


def test_a_disparity_noise_that_does_not_grow_gives_no_gain() -> None:
    rng = np.random.default_rng(13)
    model = StereoNoiseModel(_rectification(), PRIOR)
    fixed = StereoNoiseModel(_rectification(), PRIOR, disparity_growth=False)
    for _ in range(25):
        model.update(*_growing_frame(NoiseLevel(0.08, 0.08, 0.1), 0.0, rng))
        fixed.update(*_growing_frame(NoiseLevel(0.08, 0.08, 0.03), 0.04, rng))
    assert model.disparity_gain < 0.003
    assert fixed.disparity_gain == 0.0  # switched off: one disparity noise at every depth


def test_the_compiled_covariances_with_a_growing_disparity_noise_are_the_array_formula() -> None:
    rng = np.random.default_rng(14)
    rectification = _rectification()
    model = StereoNoiseModel(rectification, PRIOR)
    for _ in range(10):
        model.update(*_growing_frame(NoiseLevel(0.08, 0.08, 0.03), 0.04, rng))
    assert model.disparity_gain > 0.0 and model.typical_disparity > 0.0
    points = _triangulate(np.column_stack([rng.uniform(0, 752, 300), rng.uniform(0, 480, 300),
                                           rng.uniform(0.5, 90.0, 300)]))  # fmt: skip
    expected = point_covariances(
        points, rectification, *model.level.as_tuple(), model.disparity_gain,
        model.typical_disparity,
    )  # fmt: skip
    np.testing.assert_array_equal(model.covariances(points), expected)
