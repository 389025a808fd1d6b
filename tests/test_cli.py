"""The command line guides: version, configuration listing, one-line config errors."""

from __future__ import annotations

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


def test_config_typo_is_one_line_with_a_suggestion(tmp_path, capsys):
    path = tmp_path / "config.yaml"
    path.write_text("frontend:\n  max_featurs: 10\nregistraton: {}\nseed: x\n")
    assert main(["config", "--config", str(path)]) == 2
    error = capsys.readouterr().err
    assert error.count("\n") == 1 and "http" not in error
    assert "frontend.max_featurs: unknown key (did you mean frontend.max_features?)" in error
    assert "registraton: unknown key (did you mean registration?)" in error
    assert "seed:" in error


def test_conflicting_flags_are_refused(tmp_path, capsys):
    assert main(["run", str(tmp_path), "--imu", "--no-backend"]) == 2
    assert "--imu needs the back end" in capsys.readouterr().err
