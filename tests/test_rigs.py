"""Other stereo rigs: rendered RealSense- and ZED-like pairs, tracked without a configuration."""

from __future__ import annotations

import numpy as np
import pytest

from estimator.bench.rigs import FRAME_RATES, rendered_flight, seed_mean, table
from estimator.cli.main import main
from estimator.formats.datasets import open_sequence
from estimator.pipeline import build_config, run_sequence, summarize
from estimator.rendered.camera import CAMERAS
from estimator.rendered.synthetic import SynthOptions, synthesize
from estimator.types import FrameStatus


@pytest.mark.parametrize("name", ["realsense", "zed"])
def test_a_rendered_camera_is_written_as_its_calibration(tmp_path, name):
    camera = CAMERAS[name]
    options = SynthOptions(frames=3, length_m=0.5, fps=30.0, imu_rate_hz=300.0, camera=name)
    synthesize(tmp_path / name, options)
    sequence = open_sequence(tmp_path / name)
    left = sequence.rig.left
    assert (left.width, left.height) == (camera.width, camera.height)
    assert (left.fx, left.fy, left.cx, left.cy) == (camera.f, camera.f, camera.cx, camera.cy)
    assert np.linalg.norm(sequence.rig.T_left_right[:3, 3]) == pytest.approx(camera.baseline)
    frame = sequence.load(1)
    assert frame.left.shape == frame.right.shape == (camera.height, camera.width)


def test_texture_density_follows_the_focal_length_of_another_camera():
    flight, drive = SynthOptions(), SynthOptions.driving()
    assert flight.sim_camera is CAMERAS["euroc"] and drive.sim_camera is CAMERAS["kitti"]
    assert flight.texture_density == flight.texture_px_per_m  # the scenario's own camera
    assert drive.texture_density == drive.texture_px_per_m
    zed = SynthOptions(camera="zed")
    assert zed.texture_density == pytest.approx(96.0 * 700.0 / CAMERAS["euroc"].f)


def test_an_unknown_camera_is_refused(tmp_path, capsys):
    with pytest.raises(ValueError, match="camera must be one of"):
        SynthOptions(camera="gopro").validate()  # type: ignore[arg-type]
    with pytest.raises(SystemExit) as stop:
        main(["synth", str(tmp_path / "out"), "--camera", "gopro"])
    assert stop.value.code == 2
    assert "invalid choice: 'gopro'" in capsys.readouterr().err
    assert not (tmp_path / "out").exists()


def test_the_bench_refuses_a_negative_seed_by_name(tmp_path, capsys):
    assert main(["bench", "rigs", "--seeds", "-1", "--data", str(tmp_path / "d"),
                 "--out", str(tmp_path / "o")]) == 2  # fmt: skip
    assert capsys.readouterr().err.strip() == "swarmvo bench: error: seed must be >= 0, got -1"
    assert not (tmp_path / "d").exists() or not any((tmp_path / "d").iterdir())


@pytest.mark.slow
@pytest.mark.parametrize("name", ["realsense", "zed"])
def test_a_hand_held_flight_is_tracked_with_no_configuration(tmp_path, name):
    """1.5 s of the bench's noisy, blurred flight at the rig's frame rate, vision alone, the
    default configuration: the settings follow from the rig and no frame is lost."""
    sequence = open_sequence(rendered_flight(tmp_path, name, seed=0, frames=45))
    result = run_sequence(sequence, build_config(imu=False), use_imu=False)
    assert all(report.status == FrameStatus.OK for report in result.reports)
    derived = {setting.name: setting.value for setting in result.derived}
    camera = CAMERAS[name]
    # Depth range from the pair, search window from the focal length and the frame rate.
    assert derived["max_depth_m"] == pytest.approx(camera.f * camera.baseline / 1.6, rel=0.01)
    assert derived["search_radius_px"] < 45.0
    metrics, _ = summarize(result)
    assert metrics["path_length_m"] > 2.5
    # Measured (seed 0, 2.8 m): RealSense 0.20 %, ZED 0.09 % final drift; 0.0070 / 0.0091 deg
    # per frame.
    assert metrics["final_drift_pct"] < 1.0
    assert metrics["rpe_rot_rmse_deg"] < 0.02


def test_the_bench_table_names_each_rig_and_averages_its_flights():
    first = {
        "ate_rmse_m": 0.00123, "final_drift_pct": 0.05, "rpe_rot_rmse_deg": 0.0031,
        "frames_failed": 0, "matches_median": 312.0, "fps": 30.25,
    }  # fmt: skip
    second = {**first, "ate_rmse_m": 0.00223, "frames_failed": 2, "matches_median": 300.0}
    runs = {"zed": {"derived": {"vision": {"0": first, "1": second}}}}
    text = table(runs)
    name = "zed (1280x720, 12 cm, 30 Hz) / derived / vision"
    assert f"| {name} / 0 | 1.23 | 0.05 | 0.0031 | 0 | 312 | 30.2 |" in text
    assert f"| {name} / 1 | 2.23 | 0.05 | 0.0031 | 2 | 300 |" in text
    # The mean row: means, the lost frames of both flights summed.
    assert f"| **{name} / mean** (lost: total) | 1.73 | 0.05 | 0.0031 | 2 | 306 |" in text
    assert seed_mean(runs["zed"]["derived"]["vision"])["frames_failed"] == 2
    assert FRAME_RATES["zed"] == 30.0
