"""Keyframe revisits (odometry/revisits.py): back at a place, the old keyframe is the reference
again and the drift collected since does not stay."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from test_odometry import FRAME_NS, _config, _rendered_flight, _rendered_rig, _run

from estimator.config import FrontendConfig
from estimator.geometry import invert_pose, rotation_angle_deg
from estimator.odometry import MeasurementKind, Odometry
from estimator.odometry.revisits import revisits_on
from estimator.types import FrameStatus, StereoFrame


def _out_and_back() -> tuple[list[StereoFrame], np.ndarray]:
    """A rendered flight flown 20 frames out and the same way back to its first pose."""
    frames, truth = _rendered_flight(20, 1.5)
    order = list(range(20)) + list(range(18, -1, -1))
    flown = [
        StereoFrame(1_000 + step * FRAME_NS, frames[index].left, frames[index].right)
        for step, index in enumerate(order)
    ]
    return flown, truth[order]


def _final_error(revisit: bool, observer=None) -> tuple[Odometry, float, float]:
    """The odometry after the flight out and back, and its last pose's error (mm, deg): the
    truth ends where it started."""
    frames, truth = _out_and_back()
    config = _config(frontend={"revisit_keyframes": revisit}, backend={"enabled": False})
    odometry = Odometry(_rendered_rig(), config, observer=observer)
    reports = _run(odometry, frames)
    assert all(report.status == FrameStatus.OK for report in reports)
    estimated = invert_pose(reports[0].pose) @ reports[-1].pose
    true = invert_pose(truth[0]) @ truth[-1]
    error = invert_pose(true) @ estimated
    return odometry, float(np.linalg.norm(error[:3, 3])) * 1e3, rotation_angle_deg(error[:3, :3])


@pytest.mark.slow
def test_back_at_the_start_the_first_keyframe_is_the_reference_again() -> None:
    seen: list = []
    revisiting, error_mm, error_deg = _final_error(True, seen.append)
    tried = [m for m in seen if m.kind is MeasurementKind.REVISIT]
    assert len(tried) >= revisiting.keyframe_revisits  # each revisit was tried and seen
    assert _final_error(True)[1:] == (error_mm, error_deg)  # seeing them changes nothing
    chained, chained_mm, chained_deg = _final_error(False)
    assert chained.keyframe_revisits is None
    assert revisiting.keyframe_revisits is not None and revisiting.keyframe_revisits >= 1
    assert revisiting.reference_index == 0  # measured against the very first frame
    # Measured 0.11 mm / 0.0008 deg against 1.38 mm / 0.016 deg for the chain of keyframes.
    assert error_mm < 0.5 * chained_mm and error_mm < 0.4
    assert error_deg < 0.5 * chained_deg


def test_revisits_are_on_vision_alone_in_detect_mode_unless_configured() -> None:
    assert revisits_on(FrontendConfig(), imu_fused=False)
    assert not revisits_on(FrontendConfig(), imu_fused=True)
    assert not revisits_on(FrontendConfig(mode="track"), imu_fused=False)
    assert revisits_on(FrontendConfig(revisit_keyframes=True), imu_fused=True)
    assert not revisits_on(FrontendConfig(revisit_keyframes=False), imu_fused=False)


@pytest.mark.slow
@pytest.mark.euroc
def test_real_clip_revisits_lower_the_vision_alone_error(
    euroc_mh01_moving: Path, run_real_clip
) -> None:
    """MH_01 is carried back and forth through the same part of the hall: vision alone the
    front end goes back to its older keyframes and the ATE falls (measured 4.46 -> 3.95 mm,
    11 revisits) while the rotation error per frame stays within the target (0.0177 deg)."""
    revisiting = run_real_clip(euroc_mh01_moving, imu=False).summary
    chained = run_real_clip(euroc_mh01_moving, imu=False, frontend={"revisit_keyframes": False})
    assert revisiting["keyframe_revisits"] >= 5
    assert chained.summary["keyframe_revisits"] is None
    assert revisiting["ate_rmse_m"] < 0.0043
    assert revisiting["ate_rmse_m"] < chained.summary["ate_rmse_m"] - 0.0002
    assert revisiting["rpe_rot_rmse_deg"] < 0.018
