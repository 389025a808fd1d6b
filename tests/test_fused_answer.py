"""The fused answer on a rig with consistent covariances: its smoothing, the kernel's scale
and the pose covariance's allowance for the keyframe-shared error."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest
from test_backend import BODY_FROM_CAMERA, _perfect_measurements, _run

from estimator.backend.answer import SmoothedAnswer, answer_time_constant, offset_kept
from estimator.backend.noise import CHI2_6DOF_99, kernel_scale, robust
from estimator.backend.systematic_noise import shared_error_growth
from estimator.config import BackendConfig
from estimator.geometry import invert_pose, make_pose, rotation_angle_deg
from estimator.rendered.scenario import PERFECT_IMU, smooth_trajectory


def _cauchy_weight(scale: float, squared_norm: float) -> float:
    return gtsam.noiseModel.mEstimator.Cauchy.Create(scale).weight(np.sqrt(squared_norm))


def test_the_exact_rig_kernel_keeps_consistent_measurements_and_drops_outliers():
    scale = kernel_scale("cauchy", None, calibration_exact=True)
    assert _cauchy_weight(scale, 6.0) > 0.95  # the chi-square(6) mean
    assert _cauchy_weight(scale, CHI2_6DOF_99) == pytest.approx(0.9, abs=1e-3)
    assert _cauchy_weight(scale, 30.0**2) < 0.15  # a 30-sigma error
    # The real rig's scale of 3 weighed the mean consistent measurement 0.6.
    assert kernel_scale("cauchy") == 3.0
    assert _cauchy_weight(3.0, 6.0) == pytest.approx(0.6)
    huber = kernel_scale("huber", None, calibration_exact=True)
    assert huber**2 == pytest.approx(CHI2_6DOF_99)
    assert kernel_scale("cauchy", 5.0, calibration_exact=True) == 5.0  # configured wins
    assert robust(gtsam.noiseModel.Unit.Create(6), "none") is not None


def test_the_answer_time_constant_follows_the_rig():
    config = BackendConfig()
    assert answer_time_constant(config, calibration_exact=True) == config.smoother_lag_s
    assert answer_time_constant(config, calibration_exact=False) == 0.0
    assert answer_time_constant(BackendConfig(answer_smoothing_s=0.1), True) == 0.1
    assert offset_kept(0.1, 0.0) == 0.0
    assert offset_kept(0.1, 0.4) == pytest.approx(np.exp(-0.25))


def _step(angle_rad: float) -> np.ndarray:
    return make_pose(gtsam.Rot3.Yaw(angle_rad).matrix(), [1.0, 0.0, 0.0])


def test_a_revision_reaches_the_answer_gradually_and_the_offset_decays():
    dt, tau = 0.1, 0.4
    answer = SmoothedAnswer(tau)
    motion = _step(0.01)
    pose = np.eye(4)
    for _ in range(6):  # past the first tau: the answer is the smoother's pose
        pose = pose @ motion
        assert np.allclose(answer.update(pose, motion, dt), pose)
    # The smoother revises the past by 1 mrad of yaw: its newest pose jumps by that much.
    revision = make_pose(gtsam.Rot3.Yaw(1e-3).matrix(), np.zeros(3))
    pose = revision @ pose @ motion
    first = answer.update(pose, motion, dt)
    offset = rotation_angle_deg((invert_pose(pose) @ first)[:3, :3])
    assert offset == pytest.approx(np.degrees(1e-3) * np.exp(-dt / tau), rel=0.05)
    previous = first
    for _ in range(40):
        pose = pose @ motion
        previous = answer.update(pose, motion, dt)
    assert rotation_angle_deg((invert_pose(pose) @ previous)[:3, :3]) < 1e-5  # 1 mrad x e^-10
    # Without smoothing the answer is the smoother's pose itself.
    assert np.allclose(SmoothedAnswer(0.0).update(pose, motion, dt), pose)


def test_the_fused_pose_covariance_allows_for_the_keyframe_shared_error():
    assert shared_error_growth(BackendConfig(keyframe_error_correlation=0.5)) == 2.0
    assert shared_error_growth(BackendConfig(keyframe_error_correlation=0.0)) == 1.0
    # Unset: a real rig's (its fit floor and placement priors cover the shared error).
    assert shared_error_growth(BackendConfig()) == 1.0
    scenario = smooth_trajectory(20, seed=2, noise=PERFECT_IMU, initial_bias=(0.0, 0.0, 0.0))
    measurements = _perfect_measurements(scenario.body_poses)
    independent = _run(scenario, measurements, BackendConfig(keyframe_error_correlation=0.0))
    shared = _run(scenario, measurements, BackendConfig(keyframe_error_correlation=0.5))
    assert shared[-1].body_covariance is not None
    np.testing.assert_allclose(shared[-1].body_covariance, 2.0 * independent[-1].body_covariance)
    # The motion's covariance (the twist) is the graph's own.
    np.testing.assert_allclose(
        shared[-1].body_motion_covariance, independent[-1].body_motion_covariance
    )
    # Without the IMU the graph is the keyframe chain itself: nothing to widen.
    alone = _run(
        scenario, measurements, BackendConfig(keyframe_error_correlation=0.5), imu=False
    )
    alone_independent = _run(
        scenario, measurements, BackendConfig(keyframe_error_correlation=0.0), imu=False
    )
    np.testing.assert_allclose(alone[-1].body_covariance, alone_independent[-1].body_covariance)
    assert BODY_FROM_CAMERA.shape == (4, 4)
