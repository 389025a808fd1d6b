"""Driving: the rendered street scenario, rig-derived settings, KITTI outputs and metrics."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from estimator.cli.main import main
from estimator.config import SwarmvoConfig
from estimator.evaluation.metrics import kitti_segment_errors
from estimator.formats.calibration import CameraModel, StereoRig
from estimator.formats.datasets import open_sequence
from estimator.formats.trajectory_io import read_kitti, read_tum
from estimator.geometry import invert_pose, make_pose, rotation_angle_deg
from estimator.pipeline import build_config, load_config
from estimator.rendered.camera import KITTI_CAMERA
from estimator.rendered.synthetic import SynthOptions
from estimator.rendered.synthetic_driving import driving_for_length
from estimator.rig_settings import (
    MAX_DERIVED_FEATURES,
    MAX_RELATIVE_DEPTH_ERROR,
    SEARCH_RADIUS_PER_FOCAL_SECOND,
    apply_rig_settings,
    derive_rig_settings,
)

FRAMES = 30


def _rig(width: int, height: int, focal: float, baseline: float) -> StereoRig:
    """An ideal rectified pair (pinhole, right camera at +x)."""

    def camera(x: float) -> CameraModel:
        return CameraModel(
            width=width,
            height=height,
            fx=focal,
            fy=focal,
            cx=width / 2,
            cy=height / 2,
            distortion_model="none",
            distortion=(),
            T_BS=make_pose(np.eye(3), [x, 0.0, 0.0]),
        )

    return StereoRig(left=camera(0.0), right=camera(baseline))


# name: (width, height, focal px, baseline m, frame rate Hz)
RIGS = {
    "euroc": (752, 480, 436.2, 0.110, 20.0),
    "kitti": (1241, 376, 718.856, 0.54, 10.0),
    "realsense_d435": (848, 480, 425.0, 0.050, 30.0),
    "zed": (1280, 720, 700.0, 0.120, 30.0),
}


@pytest.mark.parametrize("name", sorted(RIGS))
def test_settings_follow_from_focal_baseline_and_frame_rate(name):
    width, height, focal, baseline, rate = RIGS[name]
    settings = {
        s.name: s.value
        for s in derive_rig_settings(
            _rig(width, height, focal, baseline), 1 / rate, SwarmvoConfig().frontend
        )
    }
    smallest_disparity = 0.5 / MAX_RELATIVE_DEPTH_ERROR  # default disparity_sigma_px
    assert settings["max_depth_m"] == pytest.approx(focal * baseline / smallest_disparity, abs=0.06)
    assert settings["search_radius_px"] == pytest.approx(
        SEARCH_RADIUS_PER_FOCAL_SECOND * focal / rate, abs=0.06
    )
    # EuRoC's density: 1200 features on 752 x 480 pixels.
    density = 1200 * width * height / (752 * 480)
    assert settings["max_features"] == pytest.approx(min(density, MAX_DERIVED_FEATURES), abs=0.5)


def test_known_rigs_get_the_expected_ranges():
    derived = {
        name: {
            s.name: s.value
            for s in derive_rig_settings(_rig(w, h, f, b), 1 / r, SwarmvoConfig().frontend)
        }
        for name, (w, h, f, b, r) in RIGS.items()
    }
    # The EuRoC rig keeps the defaults the project was tuned with.
    assert derived["euroc"]["max_depth_m"] == pytest.approx(30.0, rel=0.01)
    assert derived["euroc"]["search_radius_px"] == pytest.approx(40.0, rel=0.01)
    assert derived["euroc"]["max_features"] == SwarmvoConfig().frontend.max_features == 1200
    # A wide KITTI frame has 29 % more pixels than EuRoC's: as many more features.
    assert derived["kitti"]["max_features"] == 1551
    assert derived["zed"]["max_features"] == MAX_DERIVED_FEATURES  # 3064 at that density
    # KITTI's wide pair measures depth far beyond 80 m; 10 Hz frames need a wider search.
    assert derived["kitti"]["max_depth_m"] > 200.0
    assert derived["kitti"]["search_radius_px"] > 100.0
    # A 5 cm RealSense pair sees only a few metres; 30 Hz narrows the search.
    assert 5.0 < derived["realsense_d435"]["max_depth_m"] < 15.0
    assert derived["realsense_d435"]["search_radius_px"] < 30.0
    assert 40.0 < derived["zed"]["max_depth_m"] < 60.0


def test_explicit_config_values_win(tmp_path):
    path = tmp_path / "config.yaml"
    path.write_text("frontend:\n  max_depth_m: 55.0\n")
    config = build_config(estimator="msac", seed=3, base=load_config(path))
    rig = _rig(*RIGS["kitti"][:4])
    applied, settings = apply_rig_settings(config, rig, 0.1)
    assert applied.frontend.max_depth_m == 55.0
    by_name = {s.name: s for s in settings}
    assert by_name["max_depth_m"].overridden and not by_name["search_radius_px"].overridden
    assert applied.frontend.search_radius_px == by_name["search_radius_px"].value
    assert applied.registration.method == "msac" and applied.seed == 3
    # Derived values are not the user's: applying again to another rig re-derives them.
    again, _ = apply_rig_settings(applied, _rig(*RIGS["zed"][:4]), 1 / 30)
    assert again.frontend.max_depth_m == 55.0
    assert again.frontend.search_radius_px < applied.frontend.search_radius_px


def test_kitti_segment_errors_of_a_scale_error_and_a_heading_drift():
    """Hand-computed: 151 poses 1 m apart on a straight line (150 m)."""
    steps = np.arange(151, dtype=float)
    reference = np.stack([make_pose(np.eye(3), [0.0, 0.0, d]) for d in steps])
    # 1 % too long: each 100 m segment ends at the first frame beyond 100 m, 101 m on, so
    # the error is 1.01 m over the nominal 100 m: 1.01 %; from frames 0, 10, ..., 40 (5).
    scaled = reference.copy()
    scaled[:, :3, 3] *= 1.01
    result = kitti_segment_errors(scaled, reference)
    assert result["kitti_segments"] == 5
    assert result["kitti_trans_err_pct"] == pytest.approx(1.01, abs=1e-9)
    assert result["kitti_rot_err_deg_per_100m"] == pytest.approx(0.0, abs=1e-9)
    assert list(result["kitti_by_length_m"]) == ["100"]
    # Heading drifting by 1 mrad per frame: 0.101 rad over each segment -> 5.787 deg / 100 m.
    turned = reference.copy()
    for index, angle in enumerate(1e-3 * steps):
        c, s = math.cos(angle), math.sin(angle)
        turned[index, :3, :3] = [[c, 0, s], [0, 1, 0], [-s, 0, c]]
    result = kitti_segment_errors(turned, reference)
    assert result["kitti_rot_err_deg_per_100m"] == pytest.approx(math.degrees(0.101), rel=1e-9)
    # Under 100 m of path there is no segment at all.
    assert kitti_segment_errors(reference[:100], reference[:100]) is None


def test_driving_trajectory_has_consistent_derivatives():
    drive = driving_for_length(500.0, 50.0, np.random.default_rng(4))
    assert drive.path_length() == pytest.approx(500.0, rel=1e-9)
    dt = 1e-3
    t = np.linspace(0.0, 50.0, 400)
    before, now, after = (drive.state(t + offset) for offset in (-dt, 0.0, dt))
    speed = np.linalg.norm(now.velocities, axis=1)
    assert 7.5 < speed.min() and speed.max() < 15.5  # 8-15 m/s road vehicle
    velocity = (after.positions - before.positions) / (2 * dt)
    np.testing.assert_allclose(velocity, now.velocities, atol=1e-4)
    acceleration = (after.velocities - before.velocities) / (2 * dt)
    np.testing.assert_allclose(acceleration, now.accelerations, atol=1e-3)
    # Angular velocity (body frame) against the rotation change over 2 dt.
    delta = np.einsum("kji,kjl->kil", before.rotations, after.rotations)
    angles = np.array([math.radians(rotation_angle_deg(d)) for d in delta])
    np.testing.assert_allclose(
        angles / (2 * dt), np.linalg.norm(now.angular_velocities, axis=1), atol=1e-5
    )
    heading_change = np.degrees(abs(drive.heading(np.array([500.0]))[0][0]))
    assert heading_change > 20.0  # it turns


@pytest.fixture(scope="module")
def kitti_drive(tmp_path_factory) -> Path:
    """A short rendered drive (30 frames at 10 Hz, 33 m) in KITTI's layout, via the CLI."""
    root = tmp_path_factory.mktemp("drive") / "07"
    args = ["synth", str(root), "--scenario", "driving", "--layout", "kitti"]
    assert main([*args, "--frames", str(FRAMES), "--length-m", "33", "--seed", "1", "--quiet"]) == 0
    return root


def test_driving_kitti_layout_opens_with_the_kitti_rig(kitti_drive):
    for name in ("image_0", "image_1", "calib.txt", "times.txt", "poses.txt"):
        assert (kitti_drive / name).exists()
    sequence = open_sequence(kitti_drive, "kitti")
    assert len(sequence) == FRAMES and sequence.imu is None
    assert sequence.rig.size == (KITTI_CAMERA.width, KITTI_CAMERA.height)
    assert sequence.rig.baseline == pytest.approx(KITTI_CAMERA.baseline, abs=1e-9)
    assert sequence.rig.left.fx == pytest.approx(KITTI_CAMERA.f)
    np.testing.assert_array_equal(np.diff(sequence.timestamps_ns), 100_000_000)
    poses = sequence.ground_truth.poses
    np.testing.assert_allclose(poses[0], np.eye(4), atol=1e-12)
    # The camera looks along its z axis and drives forward at 8-15 m/s.
    steps = np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1)
    assert np.all((steps > 0.8) & (steps < 1.5))
    assert poses[-1][2, 3] > 25.0


def test_short_rendered_drive_is_tracked_and_written_in_kitti_format(kitti_drive, tmp_path, capsys):
    out = tmp_path / "run"
    args = ["run", str(kitti_drive), "--estimator", "msac", "--out", str(out), "--quiet"]
    assert main(args) == 0
    printed = capsys.readouterr().out
    assert "frontend.max_depth_m = " in printed and "frontend.search_radius_px = " in printed
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["frames"] == FRAMES and metrics["frames_failed"] == 0
    assert metrics["rig_settings"]["frontend.max_depth_m"]["value"] > 200.0
    assert metrics["matches_median"] >= 150
    assert metrics["final_drift_pct"] < 2.0
    assert metrics["kitti_segments"] == 0  # 33 m: no 100 m segment
    # The KITTI file holds the answered poses relative to the first, one per image.
    kitti = read_kitti(out / "kitti" / "07.txt")
    _, tum = read_tum(out / "trajectory.tum")
    assert kitti.shape == (FRAMES, 4, 4)
    np.testing.assert_allclose(kitti[0], np.eye(4), atol=1e-12)
    np.testing.assert_allclose(kitti, invert_pose(tum[0]) @ tum, atol=1e-9)


def test_bad_driving_options_are_rejected(tmp_path):
    with pytest.raises(ValueError, match="m/s"):
        SynthOptions.driving(frames=10, length_m=1000.0).validate()
    with pytest.raises(ValueError, match="layout"):
        SynthOptions.driving(layout="tum").validate()
    assert (
        main(
            [
                "synth",
                str(tmp_path / "x"),
                "--scenario",
                "driving",
                "--frames",
                "10",
                "--length-m",
                "900",
                "--quiet",
            ]
        )
        != 0
    )


def test_driving_in_the_euroc_layout_has_a_100_hz_imu_consistent_with_the_motion(tmp_path):
    from estimator.rendered.synthetic import synthesize

    options = SynthOptions.driving(frames=4, length_m=3.3, seed=2, imu_noise_scale=0.0)
    result = synthesize(tmp_path / "drive", options)
    sequence = open_sequence(tmp_path / "drive")
    assert sequence.format == "euroc" and sequence.imu_noise.rate_hz == 100.0
    assert sequence.rig.size == (KITTI_CAMERA.width, KITTI_CAMERA.height)
    # The left camera rides 1.65 m above the road, looking along the body's x axis.
    camera = sequence.ground_truth.poses[0] @ sequence.rig.left.T_BS
    assert camera[2, 3] == pytest.approx(1.65, abs=0.05)
    assert camera[:3, 2] @ sequence.ground_truth.poses[0][:3, 0] > 0.99
    # A perfect IMU: the gyro integrates to the ground-truth rotation over the drive.
    imu = sequence.imu_between(
        int(result.frame_timestamps_ns[0]), int(result.frame_timestamps_ns[-1])
    )
    rotation = np.eye(3)
    midpoints = 0.5 * (imu.gyro[1:] + imu.gyro[:-1])
    for gyro, dt in zip(midpoints, np.diff(imu.timestamps_ns) * 1e-9, strict=True):
        rotation = rotation @ Rotation.from_rotvec(gyro * dt).as_matrix()
    poses = sequence.ground_truth.interpolate(imu.timestamps_ns[[0, -1]])
    truth = poses[0][:3, :3].T @ poses[1][:3, :3]
    assert rotation_angle_deg(rotation.T @ truth) < 0.01
