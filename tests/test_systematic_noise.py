"""Covariances reported without the gyro (estimator.backend.systematic_noise)."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest

from estimator.backend.systematic_noise import (
    calibration_covariance,
    drift_growth,
    reported_measurement_covariance,
)
from estimator.config import BackendConfig
from estimator.geometry import make_pose


def _motion(rotation: np.ndarray, translation: list[float]) -> np.ndarray:
    return make_pose(gtsam.Rot3.Expmap(rotation).matrix(), translation)


def test_calibration_term_is_proportional_to_the_motion() -> None:
    motion = _motion(np.array([0.0, 0.03, 0.04]), [0.3, 0.0, 0.4])  # 0.05 rad, 0.5 m
    sigmas = np.sqrt(np.diag(calibration_covariance(motion, 0.01, 0.02)))
    np.testing.assert_allclose(sigmas[:3], 0.01 * 0.05, rtol=1e-9)
    np.testing.assert_allclose(sigmas[3:], 0.02 * 0.5, rtol=1e-9)
    doubled = _motion(np.array([0.0, 0.06, 0.08]), [0.6, 0.0, 0.8])
    np.testing.assert_allclose(np.sqrt(np.diag(calibration_covariance(doubled, 0.01, 0.02))),
                               2 * sigmas, rtol=1e-9)
    assert not calibration_covariance(np.eye(4), 0.01, 0.02).any()  # at rest: nothing


def test_reported_covariance_swaps_the_floor_and_adds_the_calibration_term() -> None:
    config = BackendConfig()
    fit = np.diag([1e-10] * 3 + [4e-8] * 3)
    # Unset floors (a rig not known to be exact): the real-rig ones, 0.1 mrad and 0.5 mm.
    graph_floor = np.diag([1e-4**2] * 3 + [5e-4**2] * 3)
    report_floor = np.diag([config.report_min_rotation_sigma_rad**2] * 3
                           + [config.report_min_translation_sigma_m**2] * 3)
    motion = _motion(np.array([0.02, 0.0, 0.0]), [0.0, 0.1, 0.0])
    reported = reported_measurement_covariance(fit + graph_floor, motion, config)
    # Unset gains (a rig not known to be exact): the real-rig defaults, 1 % and 2 %.
    expected = fit + report_floor + calibration_covariance(motion, 0.01, 0.02)
    np.testing.assert_allclose(reported, expected, rtol=1e-9, atol=1e-20)
    exact = config.model_copy(
        update={"calibration_rotation_gain": 0.0, "calibration_translation_gain": 0.0}
    )
    np.testing.assert_allclose(
        reported_measurement_covariance(fit + graph_floor, motion, exact), fit + report_floor,
        rtol=1e-9, atol=1e-20,
    )


def test_drift_growth_sums_to_the_growth_of_the_chain() -> None:
    rng = np.random.default_rng(4)
    motions = [_motion(rng.normal(size=3) * 0.02, rng.normal(size=3) * 0.05) for _ in range(5)]
    chain = [np.diag([1e-8] * 3 + [1e-6] * 3)]
    for motion in motions:  # a growing chain: each step adds a positive covariance
        adjoint = np.asarray(gtsam.Pose3(np.linalg.inv(motion)).AdjointMap())
        step = np.diag(rng.uniform(1e-9, 1e-8, 6))
        chain.append(adjoint @ chain[-1] @ adjoint.T + step)
        growth = drift_growth(chain[-1], chain[-2], motion)
        np.testing.assert_allclose(growth, step, rtol=1e-6, atol=1e-18)
    # A chain that shrinks (a better measurement against the same keyframe) grows by nothing.
    shrunk = drift_growth(0.5 * chain[-1], chain[-1], np.eye(4))
    assert np.linalg.eigvalsh(shrunk).min() >= 0 and not shrunk.any()


@pytest.mark.parametrize("gain", [-0.01])
def test_negative_gains_are_rejected(gain: float) -> None:
    with pytest.raises(ValueError):
        BackendConfig(calibration_rotation_gain=gain)
