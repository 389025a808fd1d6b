"""The table at the end of ``swarmvo run`` and the run command's user-facing help."""

from __future__ import annotations

import re

import pytest

from estimator.cli.main import build_parser, main
from estimator.cli.results_table import results_table

SUMMARY = {
    "sequence": "clip",
    "estimator": "pso-robust",
    "backend": True,
    "imu": True,
    "frames": 10,
    "frames_skipped": 1,
    "status_counts": {"ok": 7, "degraded": 2, "lost": 1},
    "path_length_m": 2.5,
    "ate_rmse_m": 0.0123,
    "rpe_trans_rmse_m": 0.0021,
    "rpe_rot_rmse_deg": 0.0345,
    "fps": 12.5,
    "wall_time_s": 0.8,
}


def _value(table: str, name: str) -> str:
    match = re.search(rf"^  {re.escape(name)}\s+(.*)$", table, re.MULTILINE)
    assert match is not None, table
    return match.group(1)


def test_table_with_ground_truth() -> None:
    table = results_table(SUMMARY, estimated_path_m=2.46)
    assert table.splitlines()[0] == "results: clip (pso-robust, fused, with IMU)"
    assert _value(table, "frames") == "10 (1 skipped: image missing or unreadable)"
    assert _value(table, "tracked").startswith("7 ")
    assert _value(table, "coasted").startswith("2 ")
    assert _value(table, "lost") == "1"
    assert _value(table, "path length") == "2.46 m (ground truth 2.5 m)"
    assert _value(table, "ATE RMSE") == "12.3 mm"
    assert _value(table, "RPE per frame") == "2.1 mm, 0.0345 deg"
    assert _value(table, "speed") == "12.5 fps (0.8 s)"


def test_table_without_ground_truth_or_back_end() -> None:
    summary = {
        key: value
        for key, value in SUMMARY.items()
        if key not in ("ate_rmse_m", "rpe_trans_rmse_m", "rpe_rot_rmse_deg", "path_length_m")
    }
    summary.update(backend=False, imu=False, frames_skipped=0)
    table = results_table(summary, estimated_path_m=0.01432)
    assert "(pso-robust, front end only)" in table.splitlines()[0]
    assert _value(table, "frames") == "10"
    assert _value(table, "path length") == "0.0143 m"
    assert _value(table, "ATE / RPE") == "no ground truth"
    assert "ATE RMSE" not in table


def test_back_end_without_imu_is_not_called_fused() -> None:
    summary = {**SUMMARY, "imu": False}
    table = results_table(summary, estimated_path_m=2.46)
    title = table.splitlines()[0]
    assert title == "results: clip (pso-robust, vision + back end, no IMU)"
    assert "fused" not in title and "IMU" not in _value(table, "coasted")
    assert _value(table, "coasted") == "2 (motion prior only)"
    with_imu = results_table(SUMMARY, estimated_path_m=2.46)
    assert _value(with_imu, "coasted") == "2 (IMU / motion prior only)"


def test_run_help_speaks_to_users(capsys) -> None:
    with pytest.raises(SystemExit):
        main(["run", "--help"])
    text = capsys.readouterr().out
    assert "results table" in text and "examples:" in text and "swarmvo run " in text
    assert "``" not in text  # no developer docstring (reST markup)
    for action in build_parser()._subparsers._group_actions[0].choices.values():
        assert "``" not in (action.description or "")
