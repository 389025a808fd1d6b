"""Trajectory metrics: known perturbations give known numbers; evo agrees where it applies."""

from __future__ import annotations

import numpy as np
import pytest
from evo.core import metrics
from evo.core.trajectory import PoseTrajectory3D
from scipy.spatial.transform import Rotation

from estimator.evaluation.metrics import eq20_errors, evaluate_trajectory, similarity_scale
from estimator.formats.datasets import GroundTruth
from estimator.geometry import invert_pose, kabsch, make_pose

START = 1_500_000_000_000_000_000
STEP = 50_000_000  # 20 Hz


def _circle(count: int = 100, radius: float = 5.0) -> tuple[np.ndarray, np.ndarray]:
    """Poses on a horizontal circle, yawing with the tangent and rolling a little."""
    angle = np.linspace(0.0, 1.5 * np.pi, count)
    poses = np.tile(np.eye(4), (count, 1, 1))
    poses[:, :3, 3] = np.stack(
        [radius * np.cos(angle), radius * np.sin(angle), 0.3 * np.sin(3 * angle)], 1
    )
    euler = np.stack([angle + np.pi / 2, 0.1 * np.sin(angle), 0.05 * np.cos(2 * angle)], 1)
    poses[:, :3, :3] = Rotation.from_euler("zyx", euler).as_matrix()
    return START + np.arange(count, dtype=np.int64) * STEP, poses


def test_perfect_estimate_in_another_world_frame_has_zero_error():
    timestamps, poses = _circle()
    offset = make_pose(Rotation.from_rotvec([0.3, -0.2, 1.0]).as_matrix(), [10.0, -4.0, 2.0])
    result = evaluate_trajectory(timestamps, offset @ poses, GroundTruth(timestamps, poses))
    m = result.metrics
    for key in ("ate_rmse_m", "rpe_trans_rmse_m", "rpe_rot_rmse_deg", "eq20_rms", "final_drift_m"):
        assert m[key] == pytest.approx(0.0, abs=1e-9), key
    assert m["frames"] == 100
    assert m["path_length_m"] == pytest.approx(
        np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1).sum()
    )


def test_constant_per_frame_rotation_error_gives_known_rpe_and_eq20():
    """Every relative motion is off by 0.2 deg about a fixed axis: RPE = 0.2 deg per frame,
    and on a pure translation the error after k frames is 0.2 k deg, so eq. 20 is exact."""
    count = 50
    timestamps = START + np.arange(count, dtype=np.int64) * STEP
    truth = np.tile(np.eye(4), (count, 1, 1))
    truth[:, 0, 3] = np.arange(count) * 0.1
    step_error = make_pose(Rotation.from_rotvec(np.radians([0.0, 0.0, 0.2])).as_matrix(), [0, 0, 0])
    estimate = [truth[0]]
    for k in range(1, count):
        estimate.append(estimate[-1] @ invert_pose(truth[k - 1]) @ truth[k] @ step_error)
    result = evaluate_trajectory(timestamps, np.array(estimate), GroundTruth(timestamps, truth))
    np.testing.assert_allclose(result.rpe_rot_deg, 0.2, atol=1e-9)
    assert result.metrics["rpe_rot_rmse_deg"] == pytest.approx(0.2, abs=1e-9)
    expected_eq20 = 2 * np.sqrt(2) * np.abs(np.sin(np.radians(0.2 * np.arange(count)) / 2))
    np.testing.assert_allclose(result.eq20, expected_eq20, atol=1e-12)
    assert result.metrics["eq20_rms"] == pytest.approx(np.sqrt(np.mean(expected_eq20**2)))
    assert result.metrics["final_rot_drift_deg"] == pytest.approx(0.2 * (count - 1), abs=1e-9)


def test_eq20_matches_evo_rotation_part_on_first_relative_trajectories():
    _, truth = _circle(60)
    rng = np.random.default_rng(4)
    noise = Rotation.from_rotvec(rng.normal(0.0, 0.02, (60, 3))).as_matrix()
    estimate = truth.copy()
    estimate[:, :3, :3] = truth[:, :3, :3] @ noise
    ours = eq20_errors(estimate, truth)

    def relative(poses):
        return PoseTrajectory3D(
            poses_se3=list(invert_pose(poses[0]) @ poses), timestamps=np.arange(60.0)
        )

    ape = metrics.APE(metrics.PoseRelation.rotation_part)
    ape.process_data((relative(truth), relative(estimate)))
    np.testing.assert_allclose(ours, ape.error, atol=1e-10)
    assert ours.max() > 0.01  # the check is not vacuous


def test_ate_equals_an_independent_umeyama_fit():
    timestamps, truth = _circle(80)
    rng = np.random.default_rng(7)
    estimate = truth.copy()
    estimate[:, :3, 3] += rng.normal(0.0, 0.05, (80, 3))
    world = make_pose(Rotation.from_rotvec([0.0, 0.4, -0.3]).as_matrix(), [1.0, 2.0, 3.0])
    result = evaluate_trajectory(timestamps, world @ estimate, GroundTruth(timestamps, truth))
    rotation, translation = kabsch((world @ estimate)[:, :3, 3], truth[:, :3, 3])
    aligned = (world @ estimate)[:, :3, 3] @ rotation.T + translation
    expected = np.sqrt(np.mean(np.sum((aligned - truth[:, :3, 3]) ** 2, axis=1)))
    assert result.metrics["ate_rmse_m"] == pytest.approx(expected, rel=1e-9)
    assert 0.06 < expected < 0.1  # ~ sqrt(3) * 0.05 minus what the fit absorbs


def test_scale_drift_gives_known_final_drift_percentage():
    count = 101
    timestamps = START + np.arange(count, dtype=np.int64) * STEP
    truth = np.tile(np.eye(4), (count, 1, 1))
    truth[:, 0, 3] = np.linspace(0.0, 10.0, count)
    estimate = truth.copy()
    estimate[:, 0, 3] *= 1.01
    m = evaluate_trajectory(timestamps, estimate, GroundTruth(timestamps, truth)).metrics
    assert m["path_length_m"] == pytest.approx(10.0)
    assert m["final_drift_m"] == pytest.approx(0.1)
    assert m["final_drift_pct"] == pytest.approx(1.0)
    assert m["rpe_trans_rmse_m"] == pytest.approx(0.001)
    assert m["rpe_dist_trans_pct"] == pytest.approx(1.0, rel=1e-6)


def test_short_path_reports_drift_in_metres_but_no_percentage():
    count = 20
    timestamps = START + np.arange(count, dtype=np.int64) * STEP
    truth = np.tile(np.eye(4), (count, 1, 1))
    truth[:, 1, 3] = np.linspace(0.0, 0.02, count)  # 2 cm, like a drone standing still
    estimate = truth.copy()
    estimate[-1, 1, 3] += 0.005
    m = evaluate_trajectory(timestamps, estimate, GroundTruth(timestamps, truth)).metrics
    assert m["final_drift_pct"] is None and m["rpe_dist_trans_pct"] is None
    assert m["final_drift_m"] == pytest.approx(0.005)


def test_camera_poses_come_from_body_ground_truth_through_T_BS_with_interpolation():
    """GT at 10 Hz on a smooth arc; camera frames at 20 Hz in between rows; the estimate is
    the exact camera trajectory (body @ T_BS) -> zero error only when T_BS is applied."""
    body_t = START + np.arange(21, dtype=np.int64) * 2 * STEP
    angle = np.linspace(0, 0.5, 21)
    body = np.tile(np.eye(4), (21, 1, 1))
    body[:, :3, :3] = Rotation.from_euler("z", angle[:, None]).as_matrix()
    body[:, :3, 3] = np.stack([np.linspace(0, 4, 21), np.zeros(21), np.zeros(21)], 1)
    ground_truth = GroundTruth(body_t, body)
    T_BS = make_pose(Rotation.from_euler("xz", [-90, -90], degrees=True).as_matrix(), [0.1, 0, 0])
    camera_t = START + np.arange(41, dtype=np.int64) * STEP
    camera_angle = np.linspace(0, 0.5, 41)
    truth_body = np.tile(np.eye(4), (41, 1, 1))
    truth_body[:, :3, :3] = Rotation.from_euler("z", camera_angle[:, None]).as_matrix()
    truth_body[:, 0, 3] = np.linspace(0, 4, 41)
    estimate = truth_body @ T_BS
    good = evaluate_trajectory(camera_t, estimate, ground_truth, T_BS).metrics
    assert good["ate_rmse_m"] < 1e-9 and good["rpe_rot_rmse_deg"] < 1e-6
    assert good["eq20_rms"] < 1e-9
    wrong = evaluate_trajectory(camera_t, estimate, ground_truth).metrics  # T_BS forgotten
    assert wrong["rpe_trans_rmse_m"] > 0.05 and wrong["eq20_rms"] > 0.1


def test_frames_outside_ground_truth_are_left_out_and_counted():
    timestamps, truth = _circle(30)
    ground_truth = GroundTruth(timestamps[5:], truth[5:])
    m = evaluate_trajectory(timestamps, truth, ground_truth).metrics
    assert m["frames"] == 25 and m["frames_without_gt"] == 5
    assert m["ate_rmse_m"] < 1e-9
    with pytest.raises(ValueError, match="need at least 2"):
        evaluate_trajectory(timestamps[:6], truth[:6], ground_truth)


def test_bad_input_is_rejected():
    timestamps, truth = _circle(10)
    ground_truth = GroundTruth(timestamps, truth)
    with pytest.raises(ValueError, match="poses"):
        evaluate_trajectory(timestamps, truth[:, :3], ground_truth)
    broken = truth.copy()
    broken[3, 0, 3] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        evaluate_trajectory(timestamps, broken, ground_truth)


@pytest.mark.parametrize("shrink", [0.98, 1.0, 1.03])
def test_similarity_scale_recovers_a_shrunk_path_in_another_world_frame(shrink: float) -> None:
    timestamps, poses = _circle()
    estimate = poses.copy()
    estimate[:, :3, 3] *= shrink
    offset = make_pose(Rotation.from_rotvec([0.2, 0.1, -0.7]).as_matrix(), [3.0, 1.0, -2.0])
    scale = similarity_scale(timestamps, offset @ estimate, poses)
    assert scale == pytest.approx(1.0 / shrink, rel=1e-9)

