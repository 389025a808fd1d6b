"""``backend.covariance_scale_factors``: the gyro-measured factor on the graph's vision factors."""

from __future__ import annotations

import gtsam
import numpy as np

from estimator.config import BackendConfig
from estimator.geometry import invert_pose

VISION_SIGMAS = np.array([1e-3] * 3 + [4e-3] * 3)  # rotation rad, translation m
FRAMES = 120


def _flight(vision_flight, factor: float, config: BackendConfig) -> tuple[list, np.ndarray]:
    """The fused answers and true body poses of the conftest flight (noise seed 5)."""
    return vision_flight(factor, config, FRAMES, 5, VISION_SIGMAS)


def _rotation_error_per_frame(answers: list, truth: np.ndarray) -> float:
    """RMS (rad) of the online answers' frame-to-frame rotation error after the factor has
    been measured (the last two thirds of the flight)."""
    errors = []
    for k in range(FRAMES // 3, FRAMES):
        estimated = invert_pose(answers[k - 1].body_pose) @ answers[k].body_pose
        true = invert_pose(truth[k - 1]) @ truth[k]
        rotation = true[:3, :3].T @ estimated[:3, :3]
        errors.append(np.linalg.norm(gtsam.Rot3.Logmap(gtsam.Rot3(rotation))))
    return float(np.sqrt(np.mean(np.square(errors))))


def test_an_under_stated_vision_noise_is_weighed_as_measured(vision_flight) -> None:
    """Vision errors 16x their stated variance: with the factor on the vision factors the
    gyro carries the rotation, and the fused rotation per frame is clearly better."""
    plain, truth = _flight(vision_flight, 16.0, BackendConfig())
    scaled, _ = _flight(vision_flight, 16.0, BackendConfig(covariance_scale_factors=True))
    assert scaled[-1].covariance_scale > 4.0  # measured, and the same as without the option
    assert scaled[-1].covariance_scale == plain[-1].covariance_scale
    assert _rotation_error_per_frame(scaled, truth) < 0.8 * _rotation_error_per_frame(plain, truth)


def test_a_conservative_noise_model_is_not_shrunk(vision_flight) -> None:
    """Vision errors a quarter of their stated variance: the factor (< 1) leaves the graph's
    noise as it is, so the answers are those without the option."""
    plain, _ = _flight(vision_flight, 0.25, BackendConfig())
    scaled, _ = _flight(vision_flight, 0.25, BackendConfig(covariance_scale_factors=True))
    assert scaled[-1].covariance_scale < 1.0
    np.testing.assert_allclose([e.pose for e in scaled], [e.pose for e in plain], atol=1e-12)


def test_without_the_gyro_factor_the_option_changes_nothing(vision_flight) -> None:
    plain, _ = _flight(vision_flight, 16.0, BackendConfig(covariance_scale="off"))
    scaled, _ = _flight(
        vision_flight, 16.0, BackendConfig(covariance_scale="off", covariance_scale_factors=True)
    )
    np.testing.assert_allclose([e.pose for e in scaled], [e.pose for e in plain], atol=1e-12)
