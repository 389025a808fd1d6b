"""pso-robust's stereo support test (Mahalanobis, per-point covariances) and its benchmark."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from estimator.bench.registration_stereo import RIGS, run_stereo_grid, simulate_stereo_pair
from estimator.cli.main import main
from estimator.geometry import rotation_angle_deg
from estimator.registration.refine import refine_pose_mahalanobis
from estimator.registration.registry import register


def _oracle_rotation_error(pair) -> float:
    mask = pair.inliers
    refined = refine_pose_mahalanobis(
        pair.source[mask], pair.target[mask], pair.source_cov[mask], pair.target_cov[mask],
        pair.rotation, pair.translation, iterations=20, robust="none",
    )  # fmt: skip
    return rotation_angle_deg(refined.rotation.T @ pair.rotation)


@pytest.mark.parametrize("rig", sorted(RIGS))
def test_mahalanobis_support_finds_the_inliers_and_the_oracle_accuracy(rig: str) -> None:
    ours, isotropic, oracle = [], [], []
    for trial in range(8):
        pair = simulate_stereo_pair(RIGS[rig], 300, 0.6, np.random.default_rng(trial))
        covariances = {"source_cov": pair.source_cov, "target_cov": pair.target_cov}
        result = register(pair.source, pair.target, seed=trial, **covariances)
        assert result.success, result.message
        found = np.count_nonzero(result.inliers & pair.inliers)
        assert found / np.count_nonzero(pair.inliers) > 0.95
        assert found / result.support > 0.98
        ours.append(rotation_angle_deg(result.rotation.T @ pair.rotation))
        plain = register(pair.source, pair.target, seed=trial)
        isotropic.append(rotation_angle_deg(plain.rotation.T @ pair.rotation))
        oracle.append(_oracle_rotation_error(pair))
    assert np.median(ours) <= 1.25 * np.median(oracle)
    assert np.median(ours) < np.median(isotropic)


@pytest.mark.parametrize(
    ("options", "message"),
    [
        ({"source_cov": np.ones((20, 3, 3))}, "together"),
        ({"source_cov": np.ones((19, 3, 3)), "target_cov": np.ones((19, 3, 3))}, "shape"),
        ({"source_cov": np.full((20, 3, 3), np.nan), "target_cov": np.ones((20, 3, 3))}, "finite"),
        ({"gate_chi2": 0.0}, "gate_chi2"),
    ],
)
def test_bad_covariances_are_rejected(options: dict, message: str) -> None:
    pair = simulate_stereo_pair(RIGS["euroc"], 20, 0.0, np.random.default_rng(1))
    with pytest.raises(ValueError, match=message):
        register(pair.source[:20], pair.target[:20], **options)


def test_stereo_grid_on_a_tiny_grid() -> None:
    report = run_stereo_grid(["euroc", "kitti"], [0.5], trials=2, count=120, seed=0)
    for rig in ("euroc", "kitti"):
        cell = report["table"][rig]["0.5"]
        assert {"pso-robust", "msac", "svd", "pso", "oracle"} <= set(cell)
        assert cell["pso-robust"]["success"] == 1.0
        assert cell["svd"]["success"] == 0.0  # no outlier rejection at half outliers


def test_stereo_mode_from_the_command_line(tmp_path: Path, capsys) -> None:
    arguments = "bench registration --mode stereo --trials 1 --outlier-ratios 0.3 --out"
    assert main([*arguments.split(), str(tmp_path)]) == 0
    report = json.loads((tmp_path / "registration_stereo.json").read_text())
    assert report["trials"] == 1 and report["outlier_ratios"] == [0.3]
    assert "pso-robust targets" in capsys.readouterr().out
