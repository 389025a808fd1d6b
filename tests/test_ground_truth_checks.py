"""Ground-truth checks: known clock offsets and lever arms are found on synthetic motion, and
on the real MH_01 clip the stored diagnostic matches a fresh computation."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from estimator.evaluation import ground_truth_checks as checks
from estimator.evaluation.ground_truth_checks import CorrectionKind
from estimator.evaluation.metrics import evaluate_trajectory
from estimator.formats.datasets import GroundTruth
from estimator.geometry import make_pose
from estimator.types import ImuBatch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))

import ground_truth_timing  # noqa: E402

SHIFTS = np.arange(-10, 11) * 1e-3
T_BS = make_pose(
    Rotation.from_euler("xyz", [90, 5, 80], degrees=True).as_matrix(), [-0.02, 0.06, 0.01]
)
LEVER_ARM = np.array([0.012, -0.020, 0.008])  # the camera's true offset from T_BS, body frame
SECOND = 1_000_000_000


def _orientation(t: np.ndarray) -> Rotation:
    """A hand-swung body: three axes turning at different rates, up to about 50 degrees."""
    angles = np.stack(
        [
            0.4 * np.sin(2 * np.pi * 0.5 * t),
            0.3 * np.sin(2 * np.pi * 0.7 * t + 1.0),
            0.8 * np.sin(2 * np.pi * 0.3 * t + 0.5),
        ],
        axis=-1,
    )
    return Rotation.from_rotvec(angles)


def _position(t: np.ndarray) -> np.ndarray:
    return np.stack(
        [np.sin(2 * np.pi * 0.2 * t), 0.5 * np.cos(2 * np.pi * 0.3 * t), 0.2 * np.sin(np.pi * t)],
        axis=-1,
    )


def _acceleration(t: np.ndarray) -> np.ndarray:
    """The second derivative of ``_position``."""
    w1, w2, w3 = 2 * np.pi * 0.2, 2 * np.pi * 0.3, np.pi
    return np.stack(
        [-(w1**2) * np.sin(w1 * t), -0.5 * w2**2 * np.cos(w2 * t), -0.2 * w3**2 * np.sin(w3 * t)],
        axis=-1,
    )


def _body_rate(t: np.ndarray) -> np.ndarray:
    """Body-frame angular rate (rad/s) by a fine central difference of the orientation."""
    step = 1e-5
    return (_orientation(t - step).inv() * _orientation(t + step)).as_rotvec() / (2 * step)


def _ground_truth(late_s: float, rotation_late_s: float | None = None) -> GroundTruth:
    """200 Hz body poses over [-0.5, 8.5] s whose stamps run ``late_s`` late (the rotations
    ``rotation_late_s`` late when given)."""
    stamps = np.arange(-100, 1701) * 5_000_000
    t = stamps * 1e-9 - late_s
    rotation_t = t if rotation_late_s is None else stamps * 1e-9 - rotation_late_s
    poses = np.tile(np.eye(4), (len(stamps), 1, 1))
    poses[:, :3, :3] = _orientation(rotation_t).as_matrix()
    poses[:, :3, 3] = _position(t)
    return GroundTruth(stamps, poses)


def _imu(rng: np.random.Generator, bias: np.ndarray) -> ImuBatch:
    """200 Hz IMU on the true clock (half a sample off the ground-truth rows): gyro biased
    by ``bias``, accelerometer by a fixed bias, both noisy."""
    stamps = np.arange(-90, 1690) * 5_000_000 + 2_500_000
    t = stamps * 1e-9
    gyro = _body_rate(t) + bias + rng.normal(0.0, 0.002, (len(stamps), 3))
    force = _orientation(t).inv().apply(_acceleration(t) + np.array([0.0, 0.0, 9.81]))
    accel = force + np.array([0.05, -0.1, 0.2]) + rng.normal(0.0, 0.02, (len(stamps), 3))
    return ImuBatch(stamps, gyro, accel)


def _camera_run(
    rng: np.random.Generator, late_s: float = 0.0, lever_arm: np.ndarray = LEVER_ARM * 0
) -> tuple[np.ndarray, np.ndarray]:
    """20 Hz left-camera poses (an arbitrary world frame, 0.3 mm position noise, 0.01 deg
    rotation noise) whose stamps run ``late_s`` late, the camera ``lever_arm`` off T_BS."""
    stamps = np.arange(10, 150) * 50_000_000
    t = stamps * 1e-9 - late_s
    body = np.tile(np.eye(4), (len(t), 1, 1))
    body[:, :3, :3] = _orientation(t).as_matrix()
    body[:, :3, 3] = _position(t)
    camera_in_body = T_BS.copy()
    camera_in_body[:3, 3] += lever_arm
    camera = body @ camera_in_body
    noise = Rotation.from_rotvec(rng.normal(0.0, np.radians(0.01), (len(t), 3))).as_matrix()
    camera[:, :3, :3] = camera[:, :3, :3] @ noise
    camera[:, :3, 3] += rng.normal(0.0, 0.0003, (len(t), 3))
    world = make_pose(Rotation.from_euler("zyx", [40, -10, 5], degrees=True).as_matrix(), [3, 1, 2])
    return stamps, world @ camera


def test_parabolic_minimum_is_exact_on_a_parabola_and_flags_edges() -> None:
    shifts = np.arange(-5, 6) * 1e-3
    scan = checks.parabolic_minimum(shifts, 2.0 + (shifts - 1.3e-3) ** 2 * 1e4)
    assert scan.best_shift_s == pytest.approx(1.3e-3, abs=1e-12)
    assert scan.best_value == pytest.approx(2.0, abs=1e-12)
    assert not scan.at_edge
    falling = checks.parabolic_minimum(shifts, -shifts)
    assert falling.at_edge and falling.best_shift_s == shifts[-1]
    with pytest.raises(ValueError, match="evenly spaced"):
        checks.parabolic_minimum(np.array([0.0, 1.0, 3.0]), np.zeros(3))
    with pytest.raises(ValueError, match="at least 3"):
        checks.parabolic_minimum(np.zeros(2), np.zeros(2))


@pytest.mark.parametrize("late_ms", [0.0, 3.0, -4.5])
def test_gyro_against_ground_truth_finds_its_clock_offset(late_ms: float) -> None:
    rng = np.random.default_rng(1)
    scan = checks.gyro_ground_truth_offset(
        _imu(rng, np.array([0.01, -0.02, 0.08])), _ground_truth(late_ms * 1e-3), SHIFTS
    )
    assert not scan.at_edge
    assert scan.best_shift_s == pytest.approx(late_ms * 1e-3, abs=0.3e-3)
    assert scan.best_value < scan.value_at(late_ms * 1e-3 + 3e-3)


@pytest.mark.parametrize("late_ms", [0.0, 7.0])
def test_accelerometer_against_ground_truth_positions_finds_their_clock(late_ms: float) -> None:
    rng = np.random.default_rng(7)
    truth = _ground_truth(late_ms * 1e-3, rotation_late_s=0.0)  # as the real one
    shifts = np.arange(-20, 21, 5) * 1e-3
    scan = checks.accelerometer_ground_truth_offset(_imu(rng, np.zeros(3)), truth, shifts)
    assert not scan.at_edge
    assert scan.best_shift_s == pytest.approx(late_ms * 1e-3, abs=1.5e-3)
    assert scan.best_value < 0.5 * scan.value_at(late_ms * 1e-3 + 10e-3)


@pytest.mark.parametrize("late_ms", [0.0, 4.0])
def test_vision_against_gyro_finds_the_camera_clock_without_ground_truth(late_ms: float) -> None:
    rng = np.random.default_rng(2)
    imu = _imu(rng, np.array([0.01, -0.02, 0.08]))  # the bias is fitted, not given
    stamps, poses = _camera_run(rng, late_s=late_ms * 1e-3)
    scan = checks.camera_gyro_offset(stamps, poses[:, :3, :3], imu, T_BS[:3, :3], SHIFTS)
    # Camera stamps late by c: the gyro matches read c earlier.
    assert scan.best_shift_s == pytest.approx(-late_ms * 1e-3, abs=0.5e-3)
    assert scan.best_value < 0.5 * scan.value_at(-late_ms * 1e-3 + 5e-3)


def test_ate_versus_shift_finds_a_late_ground_truth_and_is_the_headline_at_zero() -> None:
    rng = np.random.default_rng(3)
    stamps, poses = _camera_run(rng)
    truth = _ground_truth(6e-3)
    scan = checks.ate_versus_shift(stamps, poses[:, :3, 3], truth, T_BS, np.arange(-5, 16) * 1e-3)
    assert scan.best_shift_s == pytest.approx(6e-3, abs=0.3e-3)
    assert scan.best_value < 0.7e-3 < scan.value_at(0.0)
    headline = evaluate_trajectory(stamps, poses, truth, T_BS).metrics["ate_rmse_m"]
    at_zero = checks.corrected_ate(stamps, poses[:, :3, 3], truth, T_BS, 0.0, np.zeros(3))
    assert at_zero == pytest.approx(headline, rel=1e-9)


def test_lever_arm_fit_recovers_the_camera_offset() -> None:
    rng = np.random.default_rng(4)
    stamps, poses = _camera_run(rng, lever_arm=LEVER_ARM)
    fit = checks.fit_lever_arm(stamps, poses[:, :3, 3], _ground_truth(0.0), T_BS)
    np.testing.assert_allclose(fit.lever_arm_m, LEVER_ARM, atol=0.7e-3)
    plain = checks.corrected_ate(stamps, poses[:, :3, 3], _ground_truth(0.0), T_BS, 0, np.zeros(3))
    assert fit.ate_m < 0.7e-3 < 5e-3 < plain
    assert fit.iterations < 30  # converged


def test_shift_and_lever_arm_together_are_both_recovered_and_carry_over() -> None:
    rng = np.random.default_rng(5)
    stamps, poses = _camera_run(rng, lever_arm=LEVER_ARM)
    truth, shifts = _ground_truth(7e-3), np.arange(-4, 17) * 1e-3
    positions = poses[:, :3, 3]
    scan, fit = checks.fit_shift_and_lever_arm(stamps, positions, truth, T_BS, shifts)
    assert fit.kind is CorrectionKind.BOTH and not scan.at_edge
    assert fit.shift_s == pytest.approx(7e-3, abs=0.3e-3)
    np.testing.assert_allclose(fit.lever_arm_m, LEVER_ARM, atol=1e-3)
    assert fit.ate_m < 0.7e-3
    run = checks.RunPositions(stamps, positions, truth, T_BS)
    held = checks.held_out_check(run, CorrectionKind.BOTH, shifts)
    assert all(c < 0.7e-3 < p for c, p in zip(held.ate_corrected_m, held.ate_plain_m, strict=True))
    only_shift = checks.fit_correction(run, CorrectionKind.SHIFT, shifts)
    assert not np.any(only_shift.lever_arm_m) and only_shift.ate_m > fit.ate_m


def test_bad_inputs_are_clear_errors() -> None:
    rng = np.random.default_rng(6)
    stamps, poses = _camera_run(rng)
    truth = _ground_truth(0.0)
    with pytest.raises(ValueError, match="every shift"):
        checks.ate_versus_shift(stamps[:2], poses[:2, :3, 3], truth, T_BS, SHIFTS)
    with pytest.raises(ValueError, match="rotations"):
        checks.camera_gyro_offset(
            stamps[:3], poses[:3, :3, :3], _imu(rng, np.zeros(3)), T_BS[:3, :3], SHIFTS
        )
    with pytest.raises(ValueError, match="does not cover"):
        late = stamps + 20 * SECOND
        checks.camera_gyro_offset(
            late, poses[:, :3, :3], _imu(rng, np.zeros(3)), T_BS[:3, :3], SHIFTS
        )


def test_script_rejects_a_bad_path_with_one_line(
    capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    for flag, message in (("--results", "no run folders at"), ("--data", "no EuRoC clip at")):
        argv = ["ground_truth_timing.py", flag, str(tmp_path / "missing")]
        monkeypatch.setattr(sys, "argv", argv)
        with pytest.raises(SystemExit) as stop:
            ground_truth_timing.main()
        assert stop.value.code == 2
        assert f"error: {message} {tmp_path / 'missing'}" in capsys.readouterr().err


# ----------------------------------------------------------------------------- real data


@pytest.fixture(scope="module")
def mh01(euroc_mh01_moving: Path):
    return ground_truth_timing.open_clip(euroc_mh01_moving)


def test_real_ground_truth_rotation_runs_on_the_imu_clock(mh01) -> None:
    check = ground_truth_timing.gyro_check(mh01)
    assert not check["at_edge"]
    assert abs(check["best_shift_ms"]) < 2.0


def test_stored_diagnostic_matches_a_fresh_computation(mh01) -> None:
    stored_path = ROOT / "benchmarks/results/ground_truth/ground_truth.json"
    stored = json.loads(stored_path.read_text())
    assert stored["kind"].startswith("diagnostic")
    assert stored["sequence"] == "euroc_mh01_moving"
    assert len(stored["runs"]) == 8
    name = ground_truth_timing.run_name("pso-robust", "vision")
    folder = ground_truth_timing.DEFAULT_RESULTS / name
    fresh = {
        "gyro_vs_ground_truth": ground_truth_timing.gyro_check(mh01),
        "accelerometer_vs_ground_truth": ground_truth_timing.accelerometer_check(mh01),
        "camera_vs_gyro": {name: ground_truth_timing.camera_check(mh01, folder)},
        "runs": {name: ground_truth_timing.run_check(mh01, folder)},
    }
    for check in ("gyro_vs_ground_truth", "accelerometer_vs_ground_truth"):
        _assert_close(stored[check], fresh[check])
    _assert_close(stored["camera_vs_gyro"][name], fresh["camera_vs_gyro"][name])
    run = fresh["runs"][name]
    _assert_close(stored["runs"][name], run)
    assert run["ate_at_0_mm"] == pytest.approx(run["headline_ate_mm"], rel=1e-9)


def _assert_close(stored, fresh) -> None:
    if isinstance(fresh, dict):
        assert stored.keys() == fresh.keys()
        for key in fresh:
            _assert_close(stored[key], fresh[key])
    elif isinstance(fresh, list) and fresh and isinstance(fresh[0], dict):
        assert len(stored) == len(fresh)
        for stored_item, fresh_item in zip(stored, fresh, strict=True):
            _assert_close(stored_item, fresh_item)
    elif isinstance(fresh, list):
        np.testing.assert_allclose(np.asarray(stored, float), np.asarray(fresh, float), rtol=1e-6)
    elif isinstance(fresh, float):
        assert stored == pytest.approx(fresh, rel=1e-6, abs=1e-9)
    else:
        assert stored == fresh
