"""A rendered drive with its IMU: fusing the gyro must not make a precise vision worse.

The drive's vision is accurate to ~0.04 mrad per frame; with the graph's real-rig floor on the
relative-pose covariance (0.1 mrad) the gyro and its bias set the rotation and fused tracked
worse than vision alone. An exact rig's floor (``fit_floor``) keeps vision's weight.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from estimator.formats.datasets import open_sequence
from estimator.pipeline import build_config, run_sequence, summarize
from estimator.rendered.synthetic import SynthOptions, synthesize

FRAMES = 30


@pytest.fixture(scope="module")
def euroc_drive(tmp_path_factory) -> Path:
    """A short rendered drive (30 frames at 10 Hz, 33 m) with its 100 Hz IMU."""
    root = tmp_path_factory.mktemp("fused_drive") / "drive"
    synthesize(root, SynthOptions.driving(frames=FRAMES, length_m=33.0, seed=1))
    return root


def _rotation_errors(root: Path, use_imu: bool) -> dict[str, float]:
    sequence = open_sequence(root, "euroc")
    result = run_sequence(sequence, build_config("pso-robust", seed=0), use_imu=use_imu)
    summary, _ = summarize(result)
    assert summary["frames_failed"] == 0 and sequence.imu is not None
    return {
        section: summary[section]["rpe_rot_rmse_deg"] for section in ("fused", "smoothed")
    }


def test_fused_drive_rotation_is_no_worse_than_vision_alone(euroc_drive):
    vision = _rotation_errors(euroc_drive, use_imu=False)
    fused = _rotation_errors(euroc_drive, use_imu=True)
    assert vision["fused"] < 0.01  # the drive's vision is precise: a meaningful comparison
    assert fused["fused"] <= 1.1 * vision["fused"]
    assert fused["smoothed"] <= 1.1 * vision["smoothed"]
