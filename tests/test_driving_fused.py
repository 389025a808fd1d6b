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


def _summary(rotation: float) -> dict[str, float]:
    return {
        "final_drift_pct": 0.1,
        "rpe_rot_rmse_deg": rotation,
        "frames_failed": 0,
        "matches_median": 400.0,
        "fps": 10.0,
        "path_length_m": 520.0,
    }


def test_bench_driving_table_has_a_row_per_mode_and_compares_fused_with_vision():
    from estimator.bench.driving import _table

    results = {
        "pso-robust": {
            "vision": {"0": _summary(0.0025), "1": _summary(0.0026)},
            "fused": {"0": _summary(0.0024), "1": _summary(0.0040)},
        }
    }
    table = _table(results)
    assert "| pso-robust vision seed 0 |" in table and "| pso-robust fused seed 1 |" in table
    assert "**pso-robust fused mean**" in table
    assert "fused rotation worse than vision alone on seeds 1: MISS" in table
    results["pso-robust"]["fused"]["1"] = _summary(0.0026)
    assert "no worse than vision alone on every seed: PASS" in _table(results)
    # Vision alone only: no comparison line.
    assert "fused rotation" not in _table({"msac": {"vision": {"0": _summary(0.003)}}})
