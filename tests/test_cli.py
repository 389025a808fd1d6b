"""The command line guides: version, configuration listing, one-line config errors."""

from __future__ import annotations

import numpy as np
import pytest
import yaml

from estimator.cli.main import main
from estimator.config import SwarmvoConfig


def test_version_is_printed(capsys):
    with pytest.raises(SystemExit) as stop:
        main(["--version"])
    assert stop.value.code == 0
    assert capsys.readouterr().out.startswith("swarmvo ")


def test_config_lists_every_default(capsys):
    assert main(["config"]) == 0
    listed = yaml.safe_load(capsys.readouterr().out)
    assert SwarmvoConfig.model_validate(listed) == SwarmvoConfig()
    assert listed["frontend"]["max_features"] == SwarmvoConfig().frontend.max_features


def test_config_file_is_shown_merged_onto_the_defaults(tmp_path, capsys):
    path = tmp_path / "config.yaml"
    path.write_text("seed: 7\nfrontend:\n  max_features: 900\n")
    assert main(["config", "--config", str(path)]) == 0
    listed = yaml.safe_load(capsys.readouterr().out)
    assert (listed["seed"], listed["frontend"]["max_features"]) == (7, 900)
    assert listed["registration"]["method"] == SwarmvoConfig().registration.method


def test_config_of_a_dataset_shows_the_settings_derived_from_its_rig(tmp_path, capsys):
    """A KITTI-like folder (0.54 m baseline, 10 Hz): its depth range and search window, with
    where they came from; a configured value wins; the output is itself a valid config."""
    import cv2

    from estimator.pipeline import load_config
    from estimator.rig_settings import derive_rig_settings

    folder = tmp_path / "drive"
    focal, baseline = 718.856, 0.54
    for side in ("image_0", "image_1"):
        (folder / side).mkdir(parents=True)
        for k in range(3):
            cv2.imwrite(str(folder / side / f"{k:06d}.png"), np.zeros((376, 1241), np.uint8))
    p0 = f"{focal} 0 620.5 0 0 {focal} 188 0 0 0 1 0"
    p1 = f"{focal} 0 620.5 {-focal * baseline} 0 {focal} 188 0 0 0 1 0"
    (folder / "calib.txt").write_text(f"P0: {p0}\nP1: {p1}\n")
    (folder / "times.txt").write_text("0.0\n0.1\n0.2\n")
    assert main(["config", str(folder)]) == 0
    out = capsys.readouterr().out
    from estimator.formats.datasets import open_sequence

    rig = open_sequence(folder).rig
    expected = {s.name: s.value for s in derive_rig_settings(rig, 0.1, SwarmvoConfig().frontend)}
    shown = yaml.safe_load(out)
    for name in ("max_depth_m", "search_radius_px"):
        assert shown["frontend"][name] == expected[name] != getattr(SwarmvoConfig().frontend, name)
        assert f"frontend.{name} = {expected[name]:g}" in out
    assert "10.0 Hz" in out
    assert main(["config", "--data", str(folder)]) == 0  # the same, as an option
    assert capsys.readouterr().out == out
    written = tmp_path / "derived.yaml"
    written.write_text(out)
    assert load_config(written).frontend.max_depth_m == expected["max_depth_m"]
    # A configured value wins over the rig's.
    (tmp_path / "mine.yaml").write_text("frontend:\n  max_depth_m: 55.0\n")
    assert main(["config", str(folder), "--config", str(tmp_path / "mine.yaml")]) == 0
    out = capsys.readouterr().out
    assert yaml.safe_load(out)["frontend"]["max_depth_m"] == 55.0
    assert "configured; the rig suggests" in out
    # A folder that is not a dataset: one error line.
    assert main(["config", str(tmp_path / "missing")]) == 2
    assert "swarmvo config: error:" in capsys.readouterr().err


def test_config_typo_is_one_line_with_a_suggestion(tmp_path, capsys):
    path = tmp_path / "config.yaml"
    path.write_text("frontend:\n  max_featurs: 10\nregistraton: {}\nseed: x\n")
    assert main(["config", "--config", str(path)]) == 2
    error = capsys.readouterr().err
    assert error.count("\n") == 1 and "http" not in error
    assert "frontend.max_featurs: unknown key (did you mean frontend.max_features?)" in error
    assert "registraton: unknown key (did you mean registration?)" in error
    assert "seed:" in error


def test_conflicting_flags_are_refused(tmp_path, capsys, euroc_v101_micro):
    assert main(["run", str(tmp_path), "--imu", "--no-backend"]) == 2
    assert "--imu needs the back end" in capsys.readouterr().err
    assert main(["run", str(tmp_path), "--export-storage", "mcap"]) == 2
    assert "--export-storage needs --export-bag" in capsys.readouterr().err
    assert main(["run", str(euroc_v101_micro), "--left-topic", "/cam0"]) == 2
    assert "--left-topic is for bags" in capsys.readouterr().err


def test_broken_yaml_is_one_line_with_its_place(tmp_path, capsys):
    path = tmp_path / "broken.yaml"
    path.write_text("frontend:\n  max_features: [1200\n")
    assert main(["config", "--config", str(path)]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err, err
    assert err.startswith("swarmvo config: error: ") and "line 3" in err, err


def test_a_bad_value_names_what_was_given(tmp_path, capsys):
    path = tmp_path / "bad.yaml"
    path.write_text("frontend: {max_features: -3}\n")
    assert main(["config", "--config", str(path)]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "frontend.max_features" in err and "(got -3)" in err, err


def test_service_settings_out_of_range_are_one_line(capsys, monkeypatch):
    monkeypatch.setenv("SWARMVO_WORKERS", "many")
    assert main(["serve", "--port", "99999"]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and err.startswith("swarmvo serve: error: invalid settings: "), err
    assert "port" in err and "99999" in err and "workers" in err and "'many'" in err, err
