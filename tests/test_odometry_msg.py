"""Odometry messages (odom / base_link, covariances, twist) and their NEES on a rendered run."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from estimator.backend.imu import gravity_aligned_rotation
from estimator.evaluation.consistency import relative_nees
from estimator.formats.datasets import open_sequence
from estimator.formats.odometry_msg import OdometryMessage
from estimator.pipeline import (
    FIRST_FRAME_IMU_WINDOW_NS,
    build_config,
    odometry_messages,
    run_sequence,
)
from estimator.rendered.synthetic import SynthOptions, synthesize

MODES = {"fused": (True, True), "frontend": (False, False)}


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """A 2.2 s rendered flight (0.25 s at rest first), fused and front end only."""
    root = tmp_path_factory.mktemp("flight")
    synthesize(root, SynthOptions(frames=40, length_m=3.4, seed=3, standstill_s=0.25))
    sequence = open_sequence(root)
    results = {}
    # The rendered rig declares its calibration exact: no calibration error in the no-IMU
    # covariances (the gains derived from the rig are 0).
    for mode, (backend, imu) in MODES.items():
        config = build_config(backend=backend, imu=imu)
        result = run_sequence(sequence, config, use_imu=imu)
        results[mode] = (result, odometry_messages(result))
    return sequence, results


def _positive_definite(matrix: np.ndarray) -> bool:
    return bool(
        np.isfinite(matrix).all()
        and np.allclose(matrix, matrix.T, atol=1e-15)
        and np.linalg.eigvalsh(matrix).min() > 0
    )


@pytest.mark.slow
@pytest.mark.parametrize("mode", list(MODES))
def test_every_message_has_frames_and_proper_covariances(runs, mode):
    _, results = runs
    result, messages = results[mode]
    assert len(messages) == len(result.reports)
    for report, message in zip(result.reports, messages, strict=True):
        assert (message.frame_id, message.child_frame_id) == ("odom", "base_link")
        assert message.stamp_ns == report.timestamp_ns and message.status == report.status
        assert _positive_definite(message.pose_covariance)
        assert _positive_definite(message.twist_covariance)
    # Odometry drifts: the position uncertainty at the end exceeds the one after 1 s.
    variance = [np.trace(m.pose_covariance[:3, :3]) for m in messages]
    assert variance[-1] > variance[20] > variance[0]


@pytest.mark.slow
def test_odom_frame_is_one_rule_whatever_the_flags(runs):
    sequence, results = runs
    first_ns = sequence.timestamps_ns[0]
    accel = sequence.imu_between(first_ns - FIRST_FRAME_IMU_WINDOW_NS, first_ns).accel
    level = gravity_aligned_rotation(accel)
    for mode, (_, messages) in results.items():
        first = messages[0].pose
        assert np.allclose(first[:3, :3], level, atol=1e-9), mode
        assert np.allclose(first[:3, 3], 0.0, atol=1e-9), mode
    # At rest, levelled odom has z up: the body's view of up agrees with the ground truth.
    truth = sequence.ground_truth.interpolate(np.array([first_ns]))[0]
    up_truth = truth[:3, :3].T @ np.array([0.0, 0.0, 1.0])
    up_odom = level.T @ np.array([0.0, 0.0, 1.0])
    assert np.degrees(np.arccos(np.clip(up_truth @ up_odom, -1, 1))) < 1.0
    # The camera pose in odom is base_link's moved by T_BS.
    message = results["fused"][1][-1]
    assert np.allclose(message.camera_pose, message.pose @ sequence.rig.left.T_BS, atol=1e-9)


@pytest.mark.slow
def test_twist_follows_the_true_body_velocity(runs):
    sequence, results = runs
    truth = sequence.ground_truth
    for mode, (_, messages) in results.items():
        errors, speeds = [], []
        for message in messages[10:]:
            row = int(np.searchsorted(truth.timestamps_ns, message.stamp_ns))
            assert truth.timestamps_ns[row] == message.stamp_ns
            body_velocity = truth.poses[row, :3, :3].T @ truth.velocities[row]
            errors.append(np.linalg.norm(message.linear_velocity - body_velocity))
            speeds.append(np.linalg.norm(body_velocity))
        # The twist is the mean velocity over the last frame interval: close, not equal.
        assert np.median(errors) < 0.1 * np.median(speeds), mode


@pytest.mark.slow
def test_nees_on_a_short_rendered_flight_is_plausible(runs):
    sequence, results = runs
    for mode in ("fused", "frontend"):
        nees = relative_nees(results[mode][1], sequence.ground_truth, 1.0, "pose")
        assert nees.windows == 2
        # Two 6-DOF windows: the mean per DOF of a consistent estimate lies in
        # [0.15, 3] with 99.9 % probability (chi-square with 12 DOF, over 12).
        assert 0.15 <= nees.summary()["mean_nees_per_dof"] <= 3.0, mode


@pytest.mark.slow
def test_covariances_without_the_imu_are_consistent_on_a_rendered_flight(runs):
    sequence, results = runs
    messages = results["frontend"][1]
    for source in ("pose", "twist"):
        nees = relative_nees(messages, sequence.ground_truth, 1.0, source, stride=1)
        assert nees.windows == len(messages) - 20
        assert 0.5 <= nees.summary()["mean_nees_per_dof"] <= 2.0, source


@pytest.mark.slow
def test_calibration_error_widens_the_no_imu_covariances_with_the_motion(runs):
    _, results = runs
    result, exact = results["frontend"]
    backend = result.config.backend.model_copy(
        update={"calibration_rotation_gain": 0.01, "calibration_translation_gain": 0.02}
    )
    config = result.config.model_copy(update={"backend": backend})
    wider = odometry_messages(dataclasses.replace(result, config=config))
    # The drift over the flight: at least the calibration term of the path (~3.4 m at 2 %).
    growth = [np.trace(m.pose_covariance[:3, :3]) for m in (exact[-1], wider[-1])]
    assert growth[1] > 10 * growth[0]
    at_rest = [np.trace(m.pose_covariance) for m in (exact[3], wider[3])]
    assert at_rest[1] == pytest.approx(at_rest[0], rel=0.05)  # no motion yet, no term


@pytest.mark.slow
def test_calibrated_covariances_are_the_noise_models_times_the_online_scale(runs):
    _, results = runs
    result, messages = results["fused"]
    fixed = odometry_messages(result, calibrated=False)
    scales = np.array([report.covariance_scale for report in result.reports])
    assert scales[0] == 1.0 and np.all((scales >= 1 / 16) & (scales <= 16))
    assert not np.allclose(scales, 1.0)  # measured against the gyro once there are enough
    for scale, message, model in zip(scales, messages, fixed, strict=True):
        np.testing.assert_allclose(message.twist_covariance, scale * model.twist_covariance)
        np.testing.assert_array_equal(message.pose, model.pose)
    # The pose covariance is only ever inflated, by the scale of what each frame adds.
    for message, model in zip(messages, fixed, strict=True):
        assert np.linalg.eigvalsh(message.pose_covariance - model.pose_covariance).min() > -1e-12
    # Without the IMU there is nothing to measure the scale against.
    assert all(r.covariance_scale == 1.0 for r in results["frontend"][0].reports)


@pytest.mark.slow
def test_overlapping_windows_start_every_stride_frames(runs):
    sequence, results = runs
    messages = results["fused"][1]
    consecutive = relative_nees(messages, sequence.ground_truth, 1.0, "twist")
    every = relative_nees(messages, sequence.ground_truth, 1.0, "twist", stride=1)
    every_fifth = relative_nees(messages, sequence.ground_truth, 1.0, "twist", stride=5)
    assert consecutive.windows == 2
    # Frames at 20 Hz: a 1 s window (20 intervals) starts at every frame but the last 20.
    assert every.windows == len(messages) - 20
    assert every_fifth.windows == -(-every.windows // 5)
    assert every.values[0] == consecutive.values[0]
    np.testing.assert_allclose(every.values[::5], every_fifth.values)
    with pytest.raises(ValueError, match="stride"):
        relative_nees(messages, sequence.ground_truth, 1.0, "twist", stride=0)


def test_message_json_round_trip_is_exact():
    rng = np.random.default_rng(0)
    from scipy.spatial.transform import Rotation

    from estimator.geometry import make_pose

    pose = make_pose(Rotation.random(random_state=1).as_matrix(), rng.normal(size=3))
    covariance = np.cov(rng.normal(size=(6, 20)))
    message = OdometryMessage(
        stamp_ns=1_403_636_584_763_555_584,
        frame_id="odom",
        child_frame_id="base_link",
        pose=pose,
        pose_covariance=covariance,
        linear_velocity=rng.normal(size=3),
        angular_velocity=rng.normal(size=3),
        twist_covariance=covariance * 2,
        status="degraded",
        camera_pose=pose,
    )
    data = json.loads(json.dumps(message.to_dict()))
    again = OdometryMessage.from_dict(data)
    assert again.stamp_ns == message.stamp_ns and again.status == "degraded"
    assert np.allclose(again.pose, pose, atol=1e-12)
    assert np.array_equal(again.pose_covariance, covariance)
    assert data["pose"]["covariance"][7] == covariance[1, 1]  # row-major, as ROS


def test_a_first_measurement_after_frames_without_one_is_reported() -> None:
    """Frames without a measurement (no keyframe yet), then one measured against the first
    frame: the previous frame's chain is still there for the motion (it was dropped before)."""
    from estimator.config import BackendConfig
    from estimator.formats.odometry_msg import OdometryBuilder
    from estimator.geometry import make_pose
    from estimator.types import FrameReport, FrameStatus

    builder = OdometryBuilder(np.eye(4), BackendConfig(enabled=False), gyro_calibrated=False)
    step = make_pose(np.eye(3), [0.0, 0.0, 0.05])
    messages = []
    for index in range(4):
        pose = np.linalg.matrix_power(step, index)
        measured = index == 3
        messages.append(builder.build(FrameReport(
            index=index, timestamp_ns=index * 50_000_000, pose=pose, frontend_pose=pose,
            relative_pose=step if index else np.eye(4),
            status=FrameStatus.OK if measured or index == 0 else FrameStatus.DEGRADED,
            measurement_covariance=np.eye(6) * 1e-6 if measured else None,
            reference_timestamp_ns=0 if measured else None,
        )))
    assert all(np.isfinite(m.twist_covariance).all() for m in messages)
    assert np.linalg.eigvalsh(messages[-1].pose_covariance).min() > 0
