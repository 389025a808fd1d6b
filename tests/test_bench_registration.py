"""The registration benchmark: a tiny grid end to end, the peers, seeds and the target check."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from estimator import available_methods
from estimator.bench import registration as bench
from estimator.bench.peers import PEERS, inlier_threshold, oracle, run_peer
from estimator.cli.main import main
from estimator.rendered.simulation import rotation_error_deg, simulate_pair, translation_error

SIGMA = 0.02
RATIOS = (0.0, 0.6)


def _tiny_methods() -> list[str]:
    methods = ["svd", "oracle"]
    if "pso-robust" in available_methods():
        methods.insert(0, "pso-robust")
    return methods


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory: pytest.TempPathFactory) -> tuple[dict, Path, str]:
    out = tmp_path_factory.mktemp("registration")
    methods = _tiny_methods()
    ratios = ",".join(map(str, RATIOS))
    arguments = f"bench registration --sigmas {SIGMA} --outlier-ratios {ratios} --trials 3"
    options = ["--methods", ",".join(methods), "--seed", "7", "--no-progress", "--out", str(out)]
    code = main([*arguments.split(), *options])
    assert code == 0
    report = json.loads((out / "registration.json").read_text())
    return report, out, ",".join(methods)


def _entry(report: dict, ratio: float, method: str) -> dict:
    (cell,) = [cell for cell in report["cells"] if cell["outlier_ratio"] == ratio]
    return cell["methods"][method]


def test_report_structure(tiny_run: tuple[dict, Path, str]) -> None:
    report, _, methods = tiny_run
    assert report["grid"]["sigmas_m"] == [SIGMA]
    assert report["grid"]["outlier_ratios"] == list(RATIOS)
    assert report["grid"]["trials"] == 3
    assert report["grid"]["methods"] == methods.split(",")
    assert report["machine"]["cpu_count"] >= 1
    assert "numpy" in report["machine"]["packages"]
    assert len(report["cells"]) == len(RATIOS)
    for cell in report["cells"]:
        assert cell["mean_true_inliers"] <= cell["mean_pairs"]
        for entry in cell["methods"].values():
            assert entry["status"] == "ok"
            assert entry["trials"] == 3
            assert len(entry["per_trial"]["time_ms"]) == 3
            assert 0.0 <= entry["success_rate"] <= 1.0
            assert entry["median_time_ms"] > 0.0
            assert entry["p95_time_ms"] >= entry["median_time_ms"]


def test_oracle_error_is_small_relative_to_noise(tiny_run: tuple[dict, Path, str]) -> None:
    report, _, _ = tiny_run
    for ratio in RATIOS:
        entry = _entry(report, ratio, "oracle")
        assert entry["success_rate"] == 1.0
        assert entry["median_translation_error_m"] < SIGMA
        assert entry["median_rotation_error_deg"] < 0.2
        assert entry["mean_inlier_precision"] == 1.0


def test_svd_breaks_down_under_outliers(tiny_run: tuple[dict, Path, str]) -> None:
    report, _, _ = tiny_run
    clean, dirty = _entry(report, 0.0, "svd"), _entry(report, 0.6, "svd")
    assert clean["success_rate"] == 1.0
    assert dirty["success_rate"] == 0.0
    assert dirty["median_translation_error_m"] > 10 * clean["median_translation_error_m"]
    # svd keeps every pair, so its precision is the inlier fraction.
    assert dirty["mean_inlier_precision"] == pytest.approx(0.4, abs=0.02)


def test_figures_and_table_are_written(tiny_run: tuple[dict, Path, str]) -> None:
    _, out, methods = tiny_run
    for name in ("figure6_position_error.png", "figure7_time.png"):
        data = (out / name).read_bytes()
        assert data.startswith(b"\x89PNG") and len(data) > 10_000
    table = (out / "registration.md").read_text()
    for method in methods.split(","):
        assert f"| {method} |" in table


def test_targets_are_checked_when_pso_robust_runs(tiny_run: tuple[dict, Path, str]) -> None:
    report, _, methods = tiny_run
    if "pso-robust" not in methods:
        assert report["targets"] is None
        return
    targets = report["targets"]
    assert [cell["outlier_ratio"] for cell in targets["cells"]] == list(RATIOS)
    assert targets["passed"] + targets["missed"] == 3 * len(RATIOS)


def test_repeat_run_replays_the_same_pairs() -> None:
    def errors(ratios: tuple[float, ...]) -> list:
        report = bench.run_grid(
            sigmas=[SIGMA],
            outlier_ratios=ratios,
            trials=2,
            methods=["svd"],
            seed=3,
            progress=False,
        )
        cell = next(cell for cell in report["cells"] if cell["outlier_ratio"] == 0.6)
        return cell["methods"]["svd"]["per_trial"]["translation_error_m"]

    # The same cell inside a larger grid sees exactly the same pairs (seeds follow values).
    assert errors((0.6,)) == errors((0.0, 0.6))
    assert bench.trial_seeds(3, SIGMA, 0.6, 0) != bench.trial_seeds(3, SIGMA, 0.6, 1)
    assert bench.trial_seeds(3, SIGMA, 0.6, 0) != bench.trial_seeds(4, SIGMA, 0.6, 0)


def test_unknown_method_fails_clearly() -> None:
    with pytest.raises(ValueError, match="nope"):
        bench.run_grid(sigmas=[SIGMA], outlier_ratios=[0.0], trials=1, methods=["oracle", "nope"])


def test_a_method_error_names_the_trial(monkeypatch: pytest.MonkeyPatch) -> None:
    calls = []

    def fail_after_warm_up(source: np.ndarray, target: np.ndarray, mask: np.ndarray):
        calls.append(1)
        if len(calls) > 1:
            raise ValueError("bad input")
        return oracle(source, target, mask)

    monkeypatch.setattr(bench, "oracle", fail_after_warm_up)
    with pytest.raises(ValueError, match=r"oracle failed at sigma=0.02 e=0 trial 0 .*bad input"):
        bench.run_grid(sigmas=[SIGMA], outlier_ratios=[0.0], trials=1, methods=["oracle"])


@pytest.mark.parametrize(
    ("options", "message"),
    [
        ({"sigmas": [0.0]}, "sigmas"),
        ({"outlier_ratios": [1.0]}, "outlier ratios"),
        ({"trials": 0}, "trials"),
        ({"seed": -1}, "seed"),
        ({"methods": ["oracle", "oracle"]}, "twice"),
    ],
)
def test_bad_grid_is_rejected(options: dict, message: str) -> None:
    arguments = {"sigmas": [SIGMA], "outlier_ratios": [0.0], "trials": 1, "methods": ["oracle"]}
    with pytest.raises(ValueError, match=message):
        bench.run_grid(**{**arguments, **options}, progress=False)


def test_missing_peer_is_reported_not_run(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.setattr(bench, "peer_missing_package", lambda name: "pymagsac")
    arguments = "bench registration --sigmas 0.02 --outlier-ratios 0 --trials 1 --no-progress"
    code = main([*arguments.split(), "--methods", "magsac++,oracle", "--out", str(tmp_path)])
    assert code == 0
    report = json.loads((tmp_path / "registration.json").read_text())
    assert report["cells"][0]["methods"]["magsac++"]["status"].startswith("not installed")
    assert report["cells"][0]["methods"]["oracle"]["status"] == "ok"
    assert "| magsac++ | not installed" in capsys.readouterr().out


@pytest.mark.parametrize("name", list(PEERS))
def test_peer_recovers_the_motion_under_outliers(name: str) -> None:
    pytest.importorskip(PEERS[name].package)
    pair = simulate_pair(400, SIGMA, 0.5, rng=11)
    result = run_peer(name, pair.source, pair.target, noise_sigma=SIGMA, seed=1)
    assert result.success, result.message
    assert rotation_error_deg(result.rotation, pair.rotation) < 0.5
    assert translation_error(result.translation, pair.translation) < 0.05
    np.testing.assert_allclose(np.linalg.det(result.rotation), 1.0, atol=1e-9)
    hits = (result.inliers & pair.inlier_mask).sum()
    assert hits / result.inliers.sum() > 0.95
    assert hits / pair.inlier_mask.sum() > 0.9
    assert result.elapsed_s > 0.0 and result.method == name


def test_oracle_uses_only_true_inliers() -> None:
    pair = simulate_pair(400, SIGMA, 0.8, rng=5)
    result = oracle(pair.source, pair.target, pair.inlier_mask)
    assert result.success and result.support == pair.inlier_mask.sum()
    assert translation_error(result.translation, pair.translation) < SIGMA
    assert not oracle(pair.source, pair.target, np.zeros(len(pair.source), bool)).success


def test_inlier_threshold_needs_positive_noise() -> None:
    assert inlier_threshold(0.01) == pytest.approx(0.0337, abs=1e-4)
    with pytest.raises(ValueError, match="sigma"):
        inlier_threshold(0.0)


_QUALITY = {"mean_inlier_precision": 1.0, "mean_inlier_recall": 1.0, "mean_support": 300.0}


def _report(cells: list[tuple[float, float, float, float, float]]) -> dict:
    """(ratio, success, our error, oracle error, our median ms) -> a minimal report."""
    return {
        "cells": [
            {
                "sigma": SIGMA,
                "outlier_ratio": ratio,
                "methods": {
                    "pso-robust": {
                        "status": "ok",
                        "success_rate": success,
                        "median_translation_error_m": ours,
                        "median_time_ms": ms,
                        **_QUALITY,
                    },
                    "oracle": {
                        "status": "ok",
                        "success_rate": 1.0,
                        "median_translation_error_m": floor,
                        "median_time_ms": 0.1,
                        **_QUALITY,
                    },
                },
            }
            for ratio, success, ours, floor, ms in cells
        ]
    }


def test_target_check_applies_the_stated_bounds() -> None:
    targets = bench.check_targets(
        _report(
            [
                (0.2, 1.00, 0.0110, 0.010, 1.9),  # all pass
                (0.6, 0.98, 0.0130, 0.010, 2.5),  # success and error miss; 2.5 ms <= 5 passes
                (0.95, 0.96, 0.0140, 0.010, 5.1),  # success 96 % >= 95 %, 1.4x <= 1.5x; time miss
                (0.97, 0.10, 0.0900, 0.010, 4.0),  # beyond the stated grid: only time checked
            ]
        )
    )
    verdicts = [
        {key: value["pass"] for key, value in cell.items() if isinstance(value, dict)}
        for cell in targets["cells"]
    ]
    assert verdicts == [
        {"success_rate": True, "error_vs_oracle": True, "median_time_ms": True},
        {"success_rate": False, "error_vs_oracle": False, "median_time_ms": True},
        {"success_rate": True, "error_vs_oracle": True, "median_time_ms": False},
        {"median_time_ms": True},
    ]
    assert (targets["passed"], targets["missed"]) == (7, 3)


def test_strict_turns_a_miss_into_exit_code_1(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    report = _report([(0.0, 0.5, 0.02, 0.01, 9.0)])  # misses all three targets
    report["grid"] = {
        "sigmas_m": [SIGMA],
        "outlier_ratios": [0.0],
        "trials": 1,
        "points_drawn": 400,
        "seed": 0,
        "methods": ["pso-robust", "oracle"],
    }
    report["cells"][0].update(mean_pairs=300.0, mean_true_inliers=300.0)
    report["targets"] = bench.check_targets(report)
    monkeypatch.setattr(bench, "run_grid", lambda **_: report)
    monkeypatch.setattr(bench, "write_outputs", lambda *args, **kwargs: None)
    arguments = ["bench", "registration", "--out", str(tmp_path), "--no-progress"]
    assert main(arguments) == 0
    assert main([*arguments, "--strict"]) == 1


@pytest.mark.parametrize("mode", ["paper", "stereo"])
def test_zero_trials_is_refused_not_taken_for_the_default(mode, tmp_path, capsys) -> None:
    argv = ["bench", "registration", "--mode", mode, "--trials", "0", "--out", str(tmp_path)]
    assert main(argv) == 2
    assert "--trials must be >= 1, got 0" in capsys.readouterr().err
