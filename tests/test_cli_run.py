"""``swarmvo synth`` + ``swarmvo run`` end to end, on a rendered sequence and on real EuRoC."""

from __future__ import annotations

import json
import shutil
import warnings
from pathlib import Path

import numpy as np
import pytest

from estimator.cli.main import main
from estimator.formats.datasets import open_sequence
from estimator.formats.trajectory_io import read_tum, write_kitti
from estimator.geometry import invert_pose

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
REQUIRED_KEYS = (
    "ate_rmse_m",
    "rpe_trans_rmse_m",
    "rpe_rot_rmse_deg",
    "final_drift_pct",
    "final_drift_m",
    "eq20_rms",
    "path_length_m",
    "frames",
    "frames_failed",
    "median_stage_time_s",
)


@pytest.fixture(scope="module")
def rendered(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("cli") / "seq"
    code = main(["synth", str(root), "--frames", "24", "--length-m", "2.4", "--quiet"])
    assert code == 0
    return root


@pytest.mark.slow
def test_synth_then_run_writes_trajectory_metrics_and_plot(rendered, tmp_path, capsys):
    out = tmp_path / "out"
    assert main(["run", str(rendered), "--out", str(out), "--quiet"]) == 0
    printed = capsys.readouterr().out
    assert "ATE RMSE" in printed and "tracked" in printed and "path length" in printed
    timestamps, poses = read_tum(out / "trajectory.tum")
    assert len(timestamps) == 24 and poses.shape == (24, 4, 4)
    metrics = json.loads((out / "metrics.json").read_text())
    for key in REQUIRED_KEYS:
        assert key in metrics, key
    assert metrics["frames"] == 24 and metrics["estimator"] == "pso-robust"
    assert 2.0 < metrics["path_length_m"] < 2.6  # camera path of the 2.4 m body path
    # Sane, not a target: the estimate follows the rendered motion far better than standing
    # still would (which would give an ATE of about a third of the path length).
    assert np.isfinite(metrics["ate_rmse_m"])
    assert metrics["ate_rmse_m"] < 0.1 * metrics["path_length_m"]
    assert metrics["frames_failed"] <= 4
    for section in ("fused", "smoothed", "frontend"):
        assert set(metrics[section]) >= {"ate_rmse_m", "rpe_rot_rmse_deg"}, section
    smoothed_times, smoothed = read_tum(out / "trajectory_smoothed.tum")
    np.testing.assert_array_equal(smoothed_times, timestamps)  # every frame, once, in order
    # The newest frame's smoothed estimate is the smoother's pose when its answer was given
    # (nothing came after it); on this exact rig the answer takes the smoother's revisions over
    # its lag (docs/backend.md, Smoothed output), so it stays within a millimetre of it. The
    # earlier ones were revised by later frames.
    np.testing.assert_allclose(smoothed[-1], poses[-1], atol=1e-3)
    assert not np.allclose(smoothed[:-2], poses[:-2], atol=1e-6)
    assert metrics["median_stage_time_s"]["total"] > 0
    assert (out / "trajectory.png").read_bytes().startswith(PNG_MAGIC)


@pytest.mark.slow
def test_same_seed_gives_the_same_trajectory(rendered, tmp_path):
    for name in ("a", "b"):
        args = ["run", str(rendered), "--out", str(tmp_path / name), "--limit", "6", "--quiet"]
        assert main([*args, "--estimator", "pso", "--seed", "3", "--no-backend"]) == 0
    first = (tmp_path / "a" / "trajectory.tum").read_text()
    assert first == (tmp_path / "b" / "trajectory.tum").read_text()
    assert len(first.splitlines()) == 7  # header + 6 poses


def test_run_without_ground_truth_still_writes_outputs(rendered, tmp_path):
    copy = tmp_path / "nogt"
    shutil.copytree(rendered, copy)
    shutil.rmtree(copy / "mav0" / "state_groundtruth_estimate0")
    out = tmp_path / "out"
    args = ["run", str(copy), "--out", str(out), "--limit", "4", "--quiet", "--estimator", "svd"]
    assert main(args) == 0
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["frames"] == 4 and "ate_rmse_m" not in metrics
    assert (out / "trajectory.png").read_bytes().startswith(PNG_MAGIC)


@pytest.mark.euroc
@pytest.mark.slow
def test_run_on_euroc_micro_standstill(euroc_v101_micro, tmp_path):
    out = tmp_path / "euroc"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the 4 unpaired cam1 rows
        code = main(["run", str(euroc_v101_micro), "--out", str(out), "--limit", "20", "--quiet"])
    assert code == 0
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["frames"] == 20 and metrics["format"] == "euroc" and metrics["imu"]
    assert metrics["path_length_m"] < 0.02  # the drone stands still
    assert metrics["final_drift_pct"] is None  # undefined for a 1 cm path
    # Standing still: the estimate must not wander off (a wrong T_BS or time association
    # would show up as centimetres of error here).
    assert metrics["ate_rmse_m"] < 0.03
    assert metrics["final_rot_drift_deg"] < 1.0
    assert len(read_tum(out / "trajectory.tum")[0]) == 20


@pytest.mark.parametrize("imu", [True, False])
def test_a_run_levels_its_world_with_gravity_from_the_imu_before_the_first_frame(rendered, imu):
    from estimator.pipeline import build_config, run_sequence

    sequence = open_sequence(rendered)
    assert sequence.imu is not None
    assert sequence.imu.timestamps_ns[0] < sequence.frames[0].timestamp_ns  # a lead-in to use
    result = run_sequence(sequence, build_config(imu=imu), limit=2, use_imu=imu)
    first = result.reports[0]
    body = first.pose @ invert_pose(sequence.rig.left.T_BS)
    truth = sequence.ground_truth.interpolate(sequence.timestamps_ns[:1])[0]
    # World "up" seen from the body: estimated vs true (the rendered world is z-up).
    up, true_up = body[:3, :3].T @ [0.0, 0.0, 1.0], truth[:3, :3].T @ [0.0, 0.0, 1.0]
    tilt_deg = np.degrees(np.arccos(np.clip(up @ true_up, -1.0, 1.0)))
    if imu:
        assert "gravity-aligned from 20 accelerometer samples" in first.message
        # Not exact: the body accelerates at the first frame, which tilts the mean force.
        assert tilt_deg < 10.0
    else:
        assert "gravity-aligned" not in first.message
        assert tilt_deg > 45.0  # the camera's own axes: the alignment above is not for free


def test_bad_input_gives_a_clean_error(tmp_path, capsys, rendered):
    assert main(["run", str(tmp_path / "missing"), "--out", str(tmp_path / "o")]) == 2
    assert "swarmvo run: error: dataset folder not found" in capsys.readouterr().err
    (tmp_path / "empty").mkdir()
    assert main(["run", str(tmp_path / "empty")]) == 2
    assert "cannot tell the dataset format" in capsys.readouterr().err
    assert main(["run", str(rendered), "--format", "kitti"]) == 2
    assert "no KITTI image folders" in capsys.readouterr().err
    assert main(["run", str(rendered), "--limit", "1"]) == 2
    captured = capsys.readouterr()
    assert "at least 2 frames" in captured.err
    assert "settings derived" not in captured.out  # refused before the dataset is read
    out = tmp_path / "negative-seed"
    assert main(["run", str(rendered), "--seed", "-1", "--out", str(out), "--quiet"]) == 2
    captured = capsys.readouterr()
    assert captured.err.strip().splitlines()[-1] == (
        "swarmvo run: error: invalid configuration: seed: Input should be greater than or "
        "equal to 0 (got -1)"
    )
    assert not out.exists()
    with pytest.raises(SystemExit) as exit_info:
        main(["run", str(rendered), "--format", "tum"])
    assert exit_info.value.code == 2
    assert "invalid choice" in capsys.readouterr().err


def test_swapped_cameras_are_refused_with_what_to_do(tmp_path, capsys, rendered):
    """cam0 and cam1 exchanged (folders or topics): one line naming the swap, before any
    frame, instead of a run without a single stereo point that coasts on the IMU."""
    swapped = tmp_path / "swapped" / "mav0"
    swapped.mkdir(parents=True)
    for entry in (rendered / "mav0").iterdir():
        name = {"cam0": "cam1", "cam1": "cam0"}.get(entry.name, entry.name)
        (swapped / name).symlink_to(entry)
    assert main(["run", str(swapped.parent), "--quiet", "--out", str(tmp_path / "o")]) == 2
    captured = capsys.readouterr()
    lines = captured.err.strip().splitlines()
    assert lines[-1].startswith("swarmvo run: error: the right camera sits to the left"), lines
    assert "swapped" in lines[-1] and "results:" not in captured.out
    assert not (tmp_path / "o" / "trajectory.tum").exists()


def test_an_output_path_that_cannot_take_files_is_refused_before_the_run(
    tmp_path, capsys, rendered
):
    blocker = tmp_path / "a-file"
    blocker.write_text("")
    for flags, named in (
        (["--out", str(blocker)], str(blocker)),
        (["--out", str(blocker / "run")], str(blocker / "run")),
        (["--out", str(tmp_path / "o"), "--export-bag", str(blocker / "x.bag")], str(blocker)),
    ):
        assert main(["run", str(rendered), "--quiet", *flags]) == 2
        err = capsys.readouterr()
        assert f"swarmvo run: error: cannot write into {named}" in err.err, err.err
        assert "results:" not in err.out  # refused before a frame was computed


def test_synth_bad_options_give_a_clean_error(tmp_path, capsys):
    assert main(["synth", str(tmp_path / "s"), "--frames", "1"]) == 2
    assert "swarmvo synth: error: frames must be >= 2" in capsys.readouterr().err
    assert main(["synth", str(tmp_path / "s"), "--broken-fraction", "0.9"]) == 2
    assert "broken_fraction" in capsys.readouterr().err


@pytest.mark.slow
def test_run_on_the_rendered_sequence_in_kitti_layout(rendered, tmp_path):
    """The same frames as a KITTI odometry folder (calib.txt, times.txt, poses.txt)."""
    sequence = open_sequence(rendered)
    root = tmp_path / "sequences" / "00"
    for folder in ("image_0", "image_1"):
        (root / folder).mkdir(parents=True)
    frames = sequence.frames[:12]
    for i, record in enumerate(frames):
        shutil.copy(record.left_path, root / "image_0" / f"{i:06d}.png")
        shutil.copy(record.right_path, root / "image_1" / f"{i:06d}.png")
    camera = sequence.rig.left
    left = f"{camera.fx} 0 {camera.cx} 0 0 {camera.fy} {camera.cy} 0 0 0 1 0"
    right = left.replace(" 0 0 ", f" {-camera.fx * sequence.rig.baseline} 0 ", 1)
    (root / "calib.txt").write_text(f"P0: {left}\nP1: {right}\n")
    timestamps = np.array([record.timestamp_ns for record in frames])
    (root / "times.txt").write_text(
        "".join(f"{(t - timestamps[0]) * 1e-9:.6e}\n" for t in timestamps)
    )
    cameras = sequence.ground_truth.interpolate(timestamps) @ camera.T_BS
    write_kitti(root / "poses.txt", invert_pose(cameras[0]) @ cameras)
    out = tmp_path / "out"
    assert main(["run", str(root), "--out", str(out), "--quiet"]) == 0
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["format"] == "kitti" and metrics["imu"] is False and metrics["frames"] == 12
    assert metrics["path_length_m"] > 0.5
    assert metrics["ate_rmse_m"] < 0.1 * metrics["path_length_m"]


def test_ground_truth_outside_the_frames_is_reported_not_fatal(rendered, tmp_path):
    copy = tmp_path / "late_gt"
    shutil.copytree(rendered, copy)
    csv = copy / "mav0" / "state_groundtruth_estimate0" / "data.csv"
    header, *rows = csv.read_text().splitlines()
    late = [f"{int(row.split(',', 1)[0]) + 10**12},{row.split(',', 1)[1]}" for row in rows]
    csv.write_text("\n".join([header, *late]) + "\n")
    out = tmp_path / "out"
    args = ["run", str(copy), "--out", str(out), "--limit", "3", "--quiet", "--no-backend"]
    assert main([*args, "--estimator", "svd"]) == 0
    metrics = json.loads((out / "metrics.json").read_text())
    assert "ate_rmse_m" not in metrics
    assert "only 0 of 3 frames fall inside" in metrics["evaluation_error"]
    assert (out / "trajectory.tum").is_file() and (out / "trajectory.png").is_file()


def test_config_file_is_applied_and_flags_override_it(rendered, tmp_path, capsys):
    config = tmp_path / "config.yaml"
    config.write_text("seed: 5\nregistration:\n  method: svd\nbackend:\n  enabled: false\n")
    base = ["run", str(rendered), "--limit", "3", "--quiet", "--config", str(config)]
    assert main([*base, "--out", str(tmp_path / "a")]) == 0
    metrics = json.loads((tmp_path / "a" / "metrics.json").read_text())
    assert (metrics["estimator"], metrics["seed"], metrics["backend"]) == ("svd", 5, False)
    assert main([*base, "--out", str(tmp_path / "b"), "--estimator", "msac", "--seed", "1"]) == 0
    metrics = json.loads((tmp_path / "b" / "metrics.json").read_text())
    assert (metrics["estimator"], metrics["seed"], metrics["backend"]) == ("msac", 1, False)
    config.write_text('{"registration": {"method": "simplex"}}')
    assert main(base) == 2
    assert "invalid configuration" in capsys.readouterr().err


def test_a_corrupt_image_is_skipped_with_one_warning_unless_strict(rendered, tmp_path, capsys):
    copy = tmp_path / "corrupt"
    shutil.copytree(rendered, copy)
    broken = sorted((copy / "mav0" / "cam1" / "data").glob("*.png"))[2]
    broken.write_bytes(b"not a png")
    out = tmp_path / "out"
    args = ["run", str(copy), "--limit", "6", "--quiet", "--estimator", "svd", "--no-backend"]
    assert main([*args, "--out", str(out)]) == 0
    error = capsys.readouterr().err
    assert error.count("frame 2 skipped") == 1 and "Traceback" not in error
    metrics = json.loads((out / "metrics.json").read_text())
    assert (metrics["frames"], metrics["frames_skipped"]) == (5, 1)
    rows = [row for row in (out / "trajectory.tum").read_text().splitlines() if row[:1] != "#"]
    assert len(rows) == 5
    assert main([*args, "--out", str(tmp_path / "strict"), "--strict"]) == 2
    assert "cannot read image" in capsys.readouterr().err
    assert not (tmp_path / "strict" / "trajectory.tum").exists()


def test_a_missing_image_is_counted_as_skipped_unless_strict(rendered, tmp_path, capsys):
    """A pair the CSVs list without its file: one warning, counted in the table and metrics;
    --strict stops on it before any output is written."""
    copy = tmp_path / "missing"
    shutil.copytree(rendered, copy)
    sorted((copy / "mav0" / "cam0" / "data").glob("*.png"))[3].unlink()
    out = tmp_path / "out"
    args = ["run", str(copy), "--limit", "6", "--estimator", "svd", "--no-backend", "--quiet"]
    assert main([*args, "--out", str(out)]) == 0
    captured = capsys.readouterr()
    assert captured.err.count("image file is missing") == 1 and "Traceback" not in captured.err
    assert "(1 skipped: image missing or unreadable)" in captured.out
    metrics = json.loads((out / "metrics.json").read_text())
    assert (metrics["frames"], metrics["frames_skipped"]) == (6, 1)
    assert main([*args, "--out", str(tmp_path / "strict"), "--strict"]) == 2
    assert "listed without an image file" in capsys.readouterr().err
    assert not (tmp_path / "strict" / "trajectory.tum").exists()
