"""The front end's reported relative-pose covariance agrees with its errors on a rendered drive
(exact ground truth and calibration), with clean images and with image noise: the robust
sandwich (``registration.refine_covariance``) where the median-scaled one is too small."""

from __future__ import annotations

from pathlib import Path

import pytest

from estimator.cli.main import main
from estimator.config import SwarmvoConfig
from estimator.evaluation.consistency import measurement_nees
from estimator.formats.datasets import open_sequence
from estimator.pipeline import build_config, run_sequence

FRAMES = 30


@pytest.fixture(scope="module", params=[0.0, 6.0], ids=["clean", "image-noise-6"])
def drive(request, tmp_path_factory) -> Path:
    """A short rendered drive (KITTI-like rig, 10 Hz, 33 m), optionally with image noise."""
    root = tmp_path_factory.mktemp("drive") / "07"
    args = ["synth", str(root), "--scenario", "driving", "--layout", "kitti", "--quiet"]
    args += ["--frames", str(FRAMES), "--length-m", "33", "--seed", "1"]
    assert main([*args, "--noise", str(request.param)]) == 0
    return root


def _measurement_nees(root: Path, model: str) -> dict[str, float]:
    sequence = open_sequence(root, "kitti")
    base = SwarmvoConfig.model_validate({"registration": {"refine_covariance": model}})
    run = run_sequence(sequence, build_config(backend=False, imu=False, base=base), use_imu=False)
    check = measurement_nees(run.reports, sequence.ground_truth, sequence.rig.left.T_BS)
    return check.summary()


def test_reported_measurement_covariance_matches_the_errors(drive: Path) -> None:
    """Measured (29 measurements each): sandwich 0.89 / 0.96 per DOF (translation 1.4), the
    median-scaled covariance 1.6 (translation 2.57 / 2.46, outside the band of 0.5-2) on the
    clean and the noisy drive."""
    sandwich = _measurement_nees(drive, "sandwich-reported")
    median = _measurement_nees(drive, "median")
    assert sandwich["windows"] == median["windows"] >= FRAMES - 2
    assert 0.5 <= sandwich["mean_nees_per_dof"] <= 2.0
    assert 0.5 <= sandwich["translation_per_dof"] <= 2.0
    assert 0.5 <= sandwich["rotation_per_dof"] <= 2.0
    assert median["translation_per_dof"] > 2.0  # the miss the sandwich removes
