"""A late right shutter: image velocity, the offset's fit, undoing it, and a rendered rig."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from estimator.config import SwarmvoConfig
from estimator.formats.calibration import Rectification
from estimator.formats.datasets import open_sequence
from estimator.frontend.shutter_offset import ShutterOffset, image_velocity, undo_offset
from estimator.frontend.stereo import StereoPoints, triangulate
from estimator.frontend.tracks import TrackedPoints
from estimator.geometry import make_pose, quat_to_matrix, rotation_vector_to_quat
from estimator.pipeline import build_config, run_sequence, summarize
from estimator.rendered.synthetic import SynthOptions, synthesize

DELAY_MS = 5.0


def _rectification() -> Rectification:
    eye = np.eye(3)
    return Rectification(
        (752, 480), 435.0, 376.0, 240.0, 0.11, eye, eye, np.zeros((3, 4)), np.zeros((3, 4)),
        np.zeros((4, 4)), None, None,
    )  # fmt: skip


def _scene(rng: np.random.Generator, count: int, far_m: float) -> np.ndarray:
    return np.column_stack(
        [rng.uniform(-2, 2, count), rng.uniform(-1, 1, count), rng.uniform(1, far_m, count)]
    )


def _pixels(points: np.ndarray, rectification: Rectification) -> np.ndarray:
    f = rectification.fx
    return np.column_stack([
        f * points[:, 0] / points[:, 2] + rectification.cx,
        f * points[:, 1] / points[:, 2] + rectification.cy,
    ])  # fmt: skip


def test_image_velocity_is_the_derivative_of_the_projection():
    rectification = _rectification()
    rng = np.random.default_rng(0)
    points = _scene(rng, 50, 9.0)
    angular, linear = np.array([0.4, -0.9, 0.3]), np.array([0.5, -0.2, 1.5])
    dt = 1e-6
    rotation = quat_to_matrix(rotation_vector_to_quat(angular * dt))
    later = make_pose(rotation, linear * dt)  # the later camera in the earlier one
    moved = (points - later[:3, 3]) @ later[:3, :3]  # R^T (P - t), row-wise
    expected = (_pixels(moved, rectification) - _pixels(points, rectification)) / dt
    velocity = image_velocity(points, angular, linear, rectification)
    assert np.allclose(velocity, expected, rtol=1e-4, atol=1e-3)


def test_fit_recovers_a_known_offset_and_nothing_from_synchronised_rows():
    rng = np.random.default_rng(1)
    late, synchronised = ShutterOffset(), ShutterOffset()
    for _ in range(20):
        velocity = rng.normal(0.0, 200.0, 150)  # px/s
        quantised = rng.uniform(-0.5, 0.5, 150)  # keypoints on the pixel grid
        late.observe(velocity, 0.3 + 0.004 * velocity + quantised)
        synchronised.observe(velocity, 0.3 + quantised)
    slope, error = late.fit()
    assert abs(slope - 0.004) < 4 * error and error < 1e-4
    assert late.measured_s == pytest.approx(slope)
    assert late.offset_s == 0.0  # measured, not undone
    assert synchronised.fit() is not None and synchronised.measured_s is None


def test_too_little_motion_measures_nothing_and_a_configured_offset_is_not_measured():
    still = ShutterOffset()
    still.observe(np.full(100, 3.0), np.zeros(100))
    assert still.fit() is None and still.measured_s is None
    configured = ShutterOffset(0.004)
    configured.observe(np.linspace(-500, 500, 100), np.linspace(-2, 2, 100))
    assert configured.offset_s == 0.004 and configured.measured_s is None


def test_undo_offset_restores_the_synchronised_points():
    rectification = _rectification()
    rng = np.random.default_rng(2)
    truth = _scene(rng, 30, 20.0)
    pixels = _pixels(truth, rectification)
    disparity = rectification.fx * rectification.baseline / truth[:, 2]
    horizontal = rng.normal(0.0, 300.0, 30)
    offset = 0.005
    late = disparity - horizontal * offset  # the right pixel moved on by velocity x offset
    horizontal[0], late[0] = -400.0, 0.5  # its disparity would not stay positive: dropped
    points = TrackedPoints(
        pixels, late, triangulate(pixels, late.clip(1e-3), rectification), np.ones(30),
        np.zeros((30, 32), np.uint8), True, row_offset=np.zeros(30), ids=np.arange(30),
    )  # fmt: skip
    undone = undo_offset(points, horizontal, offset, rectification)
    assert isinstance(undone, TrackedPoints)
    assert len(undone) == 29 and list(undone.ids) == list(range(1, 30))
    assert np.allclose(undone.points, truth[1:], rtol=1e-9)
    assert np.allclose(undone.disparity, disparity[1:])


@pytest.fixture(scope="module")
def late_flight(tmp_path_factory) -> Path:
    """A short rendered flight whose right shutter opens 5 ms after the left."""
    root = tmp_path_factory.mktemp("late_shutter") / "flight"
    synthesize(root, SynthOptions(frames=60, length_m=6.0, seed=0, right_delay_ms=DELAY_MS))
    return root


def _run(root: Path, offset_ms: float | None) -> dict:
    base = SwarmvoConfig.model_validate({"frontend": {"stereo_time_offset_ms": offset_ms}})
    config = build_config("pso-robust", seed=0, imu=False, base=base)
    summary, _ = summarize(run_sequence(open_sequence(root, "euroc"), config, use_imu=False))
    assert summary["frames_failed"] == 0
    return summary


def test_a_late_right_shutter_is_measured_and_undone_when_configured(late_flight):
    measured = _run(late_flight, None)
    timing = measured["stereo_time_offset"]
    # The slope is diluted (rows truncated at the row tolerance, velocity errors): 4.4 ms of 5
    # on the 200-frame flight.
    assert 3.5 < timing["measured_ms"] < 5.5
    assert timing["configured_ms"] is None
    undone = _run(late_flight, DELAY_MS)
    assert undone["stereo_time_offset"]["configured_ms"] == DELAY_MS
    assert undone["ate_rmse_m"] < 0.3 * measured["ate_rmse_m"]


def test_stereo_points_select_keeps_every_per_point_array():
    points = StereoPoints(
        np.zeros((3, 2)), np.ones(3), np.ones((3, 3)), np.ones(3), np.zeros((3, 32), np.uint8),
        True, row_offset=np.array([0.1, 0.2, 0.3]),
    )  # fmt: skip
    chosen = points.select(np.array([True, False, True]))
    assert len(chosen) == 2 and list(chosen.row_offset) == [0.1, 0.3]


def test_swarmvo_run_warns_of_a_late_right_shutter(late_flight, tmp_path, capsys):
    from estimator.cli.main import main

    assert main(["run", str(late_flight), "--no-imu", "--quiet", "--out", str(tmp_path)]) == 0
    lines = [line for line in capsys.readouterr().out.splitlines() if "right shutter" in line]
    assert len(lines) == 1 and lines[0].startswith("warning: the right shutter runs +")
    assert "frontend.stereo_time_offset_ms:" in lines[0]


@pytest.mark.parametrize("delay_ms", [float("nan"), 250.0, -250.0])
def test_a_rendered_delay_outside_the_ground_truth_margin_is_refused(delay_ms):
    with pytest.raises(ValueError, match="right_delay_ms must be within"):
        SynthOptions(right_delay_ms=delay_ms).validate()
