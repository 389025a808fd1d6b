"""Moving vehicles in the rendered street: where they are, that the street stays the same, that
bad options are refused, and that a drive with a lead vehicle and traffic is still tracked."""

from __future__ import annotations

import json
import re

import cv2
import numpy as np
import pytest

from estimator.cli.main import main
from estimator.geometry import make_pose, quat_to_matrix, rotation_vector_to_quat
from estimator.rendered.render import Plane
from estimator.rendered.synthetic import SynthOptions, synthesize
from estimator.rendered.synthetic_driving import driving_for_length
from estimator.rendered.traffic import LANE_OFFSET_M, VehicleKind, build_traffic
from estimator.rendered.world import make_texture


def _drive(seed: int = 0):
    return driving_for_length(300.0, 30.0, np.random.default_rng(seed))


def test_a_moved_plane_is_the_plane_built_at_its_pose_with_the_same_texture() -> None:
    rng = np.random.default_rng(1)
    plane = Plane(
        np.array([1.0, 2.0, 3.0]), np.array([1.0, 0, 0]), np.array([0, 0, -1.0]), 2.0, 1.0,
        make_texture(24, 48, rng),
    )  # fmt: skip
    turn = quat_to_matrix(rotation_vector_to_quat(np.array([0.1, -0.2, 0.7])))
    pose = make_pose(turn, [4.0, -5.0, 0.5])
    moved = plane.moved(pose)
    built = Plane(
        turn @ plane.origin + pose[:3, 3], turn @ plane.u, turn @ plane.v, 2.0, 1.0, plane.texture
    )
    for name in ("origin", "u", "v", "normal"):
        np.testing.assert_allclose(getattr(moved, name), getattr(built, name), atol=1e-12)
    assert moved.levels is plane.levels  # no pyramid rebuilt per frame
    np.testing.assert_allclose(plane.origin, [1.0, 2.0, 3.0])  # the original stays put


def test_vehicles_keep_their_lanes_the_lead_its_gap_and_oncoming_ones_approach() -> None:
    drive = _drive()
    traffic = build_traffic(drive, 5.0, np.random.default_rng(2), 48.0)
    kinds = [vehicle.kind for vehicle in traffic.vehicles]
    assert kinds[0] is VehicleKind.LEAD and kinds.count(VehicleKind.LEAD) == 1
    assert len(kinds) == 1 + round(5.0 * drive.path_length() / 100.0)
    assert {VehicleKind.ONCOMING, VehicleKind.SAME_WAY} <= set(kinds)
    for time_s in (0.0, 7.5, 20.0):
        poses = traffic.poses_at(time_s)
        ego = drive.state(np.array([time_s])).positions[0, :2]
        for vehicle, pose in zip(traffic.vehicles, poses, strict=True):
            s = vehicle.arc_length(drive, time_s)
            heading, _ = drive.heading(np.array([s]))
            left = np.array([-np.sin(heading[0]), np.cos(heading[0])])
            offset = (pose[:2, 3] - drive.road(np.array([s]))[0]) @ left
            assert offset == pytest.approx(vehicle.lane_offset_m, abs=1e-9)
            assert pose[2, 3] == 0.0 and pose[2, 2] == pytest.approx(1.0)  # upright, on the road
            if vehicle.kind is VehicleKind.LEAD:
                ahead = np.linalg.norm(pose[:2, 3] - ego)
                assert ahead == pytest.approx(vehicle.start_s, rel=0.05)  # curves shorten it
    oncoming = next(v for v in traffic.vehicles if v.kind is VehicleKind.ONCOMING)
    assert oncoming.lane_offset_m == LANE_OFFSET_M and oncoming.speed_mps < 0
    assert oncoming.arc_length(drive, 10.0) < oncoming.arc_length(drive, 0.0)


def test_traffic_leaves_the_street_the_ground_truth_and_the_imu_as_they_were(tmp_path) -> None:
    plain = synthesize(tmp_path / "plain", SynthOptions.driving(frames=6, length_m=7.0))
    busy = synthesize(tmp_path / "busy", SynthOptions.driving(frames=6, length_m=7.0, traffic=4))
    assert plain.world.movers is None and busy.world.movers is not None
    assert len(busy.world.planes) == len(plain.world.planes)
    for ours, theirs in zip(busy.world.planes, plain.world.planes, strict=True):
        np.testing.assert_array_equal(ours.texture, theirs.texture)
    for name in ("imu0/data.csv", "state_groundtruth_estimate0/data.csv"):
        assert (tmp_path / "busy/mav0" / name).read_text() == (
            tmp_path / "plain/mav0" / name
        ).read_text()
    summary = json.loads((tmp_path / "busy" / "synth.json").read_text())
    assert summary["options"]["traffic"] == 4 and summary["moving_planes"] > 0
    # The lead vehicle fills part of the view ahead: the images differ there, not everywhere.
    first = sorted((tmp_path / "plain/mav0/cam0/data").iterdir())[0].name
    plain_image, busy_image = (
        cv2.imread(str(tmp_path / run / "mav0/cam0/data" / first), cv2.IMREAD_GRAYSCALE)
        for run in ("plain", "busy")
    )
    changed = np.mean(plain_image != busy_image)
    assert 0.005 < changed < 0.5


@pytest.mark.parametrize(
    ("overrides", "words"),
    [
        ({"traffic": -1.0}, "traffic must be in [0, 10]"),
        ({"traffic": float("nan")}, "traffic must be in [0, 10]"),
        ({"traffic": 11.0}, "traffic must be in [0, 10]"),
    ],
)
def test_bad_traffic_is_refused(overrides: dict, words: str) -> None:
    with pytest.raises(ValueError, match=re.escape(words)):
        SynthOptions.driving(**overrides).validate()


def test_traffic_is_refused_off_the_road_and_by_the_cli_in_one_line(tmp_path, capsys) -> None:
    with pytest.raises(ValueError, match="traffic is for the driving scenario"):
        SynthOptions(traffic=1.0).validate()
    assert main(["synth", str(tmp_path / "f"), "--traffic", "2", "--quiet"]) == 2
    error = capsys.readouterr().err.strip()
    assert error == (
        "swarmvo synth: error: traffic is for the driving scenario (vehicles on the road)"
    )
    assert not (tmp_path / "f").exists()


def test_a_drive_with_a_lead_vehicle_and_traffic_is_tracked(tmp_path) -> None:
    """A lead vehicle 15-30 m ahead keeps its distance: its pairs agree with a car that
    stands still. While the first frames run on the generous noise prior they pass the support
    gate; the refinement's kernel in units of the inliers' own spread weighs them down (with
    the kernel in prior sigmas this drive had 18 mm ATE and 0.0136 deg per frame)."""
    root = tmp_path / "drive"
    synthesize(root, SynthOptions.driving(frames=40, length_m=44.0, seed=0, traffic=3.0))
    out = tmp_path / "run"
    assert main(["run", str(root), "--no-imu", "--quiet", "--out", str(out)]) == 0
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["frames_failed"] == 0
    assert metrics["ate_rmse_m"] < 0.006  # measured 3.1 mm (2.0 without traffic)
    assert metrics["rpe_rot_rmse_deg"] < 0.005  # measured 0.0027 (0.0020 without traffic)


@pytest.mark.parametrize(
    ("option", "value", "message"),
    [
        ("--traffic", "-2", "traffic must be in [0, 10] vehicles per 100 m, got -2.0"),
        ("--blur", "2", "blur is an exposure fraction in [0, 1], got 2.0"),
    ],
)
def test_bench_driving_refuses_a_bad_scene_before_writing(
    tmp_path, capsys, option: str, value: str, message: str
) -> None:
    out = tmp_path / "results"
    args = ["bench", "driving", option, value, "--out", str(out), "--data", str(tmp_path)]
    assert main(args) == 2
    assert capsys.readouterr().err.strip() == f"swarmvo bench: error: {message}"
    assert not out.exists()


def test_bench_driving_names_what_the_drives_were_rendered_with() -> None:
    import argparse

    from estimator.bench.driving import _scene, _scene_note

    args = argparse.Namespace(traffic=2.0, noise=3.0, blur=0.0, brightness=0.2)
    scene = _scene(args)
    assert scene == {"traffic": 2.0, "noise": 3.0, "brightness": 0.2}  # unset ones left out
    assert _scene_note(scene) == (
        "With traffic: 2 moving vehicles per 100 m and a lead vehicle.\n\n"
        "Cameras: image noise sigma 3 grey levels, gains varying by +-20 % (per camera).\n\n"
    )
    assert _scene_note({}) == ""
