"""Old configuration keys are read as their current setting, with one warning line."""

from __future__ import annotations

import warnings

import pytest
from test_odometry import FRAME_NS, _blank, _flat_rig

from estimator.cli.main import main
from estimator.config import FRAME_INTERVAL_CONTEXT, SwarmvoConfig
from estimator.odometry import Odometry
from service.estimator_adapter import EstimatorFactory


def _validated(data: dict, interval_s: float | None = None) -> tuple[SwarmvoConfig, list]:
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        config = SwarmvoConfig.model_validate(data, context={FRAME_INTERVAL_CONTEXT: interval_s})
    return config, caught


def test_max_coast_frames_becomes_seconds_with_the_frame_period():
    config, caught = _validated({"frontend": {"max_coast_frames": 4}}, interval_s=0.1)
    assert config.frontend.max_coast_s == pytest.approx(0.4)
    assert "max_coast_s" in config.frontend.model_fields_set  # counts as configured
    assert len(caught) == 1
    message = str(caught[0].message)
    assert "\n" not in message and "max_coast_frames" in message and "frame period" in message
    # Without a known frame rate: the 20 Hz the old key's default was chosen at, said so.
    config, caught = _validated({"frontend": {"max_coast_frames": 4}})
    assert config.frontend.max_coast_s == pytest.approx(0.2)
    assert len(caught) == 1 and "assumed 20 Hz" in str(caught[0].message)


def test_the_alias_gives_the_same_run_as_max_coast_s():
    interval_s = FRAME_NS * 1e-9
    old, _ = _validated(
        {"backend": {"enabled": False}, "frontend": {"max_coast_frames": 2}}, interval_s
    )
    new, caught = _validated({"backend": {"enabled": False}, "frontend": {"max_coast_s": 0.1}})
    assert old == new and not caught
    runs = []
    for config in (old, new):
        odometry = Odometry(_flat_rig(), config)
        runs.append([odometry.process(_blank(k * FRAME_NS)).status for k in range(5)])
    assert runs[0] == runs[1]
    assert [str(status) for status in runs[0]].count("degraded") == 2  # two frames coasted


@pytest.mark.parametrize(
    ("frontend", "expected"),
    [
        ({"max_coast_frames": -1}, "whole number >= 0"),
        ({"max_coast_frames": 1.5}, "whole number >= 0"),
        ({"max_coast_frames": 2, "max_coast_s": 0.1}, "not both"),
    ],
)
def test_a_bad_old_key_is_one_line(tmp_path, capsys, frontend, expected):
    path = tmp_path / "config.yaml"
    path.write_text(f"frontend: {frontend}\n")
    assert main(["config", "--config", str(path)]) == 2
    error = capsys.readouterr().err
    assert error.count("\n") == 1 and expected in error


def test_the_cli_warns_in_one_plain_line(tmp_path, capsys):
    path = tmp_path / "config.yaml"
    path.write_text("frontend:\n  max_coast_frames: 3\n")
    assert main(["config", "--config", str(path)]) == 0
    captured = capsys.readouterr()
    assert captured.err.count("\n") == 1
    assert captured.err.startswith("swarmvo: warning: frontend.max_coast_frames is deprecated")
    assert "max_coast_s: 0.15\n" in captured.out


def test_a_service_session_converts_with_its_declared_frame_rate():
    """A session config written for an earlier release: frames x the declared frame period."""
    calibration = _flat_rig().to_dict()
    config = {"frontend": {"max_coast_frames": 3}}
    with warnings.catch_warnings(record=True):
        warnings.simplefilter("always")
        at_10_hz = EstimatorFactory().prepare(calibration, config, None, 10.0)
        unknown = EstimatorFactory().prepare(calibration, config, None)
    assert at_10_hz.config["frontend"]["max_coast_s"] == pytest.approx(0.3)
    assert unknown.config["frontend"]["max_coast_s"] == pytest.approx(0.15)  # 20 Hz assumed
