"""``swarmvo bench frontend`` times the configuration ``swarmvo run`` uses on the same data."""

from __future__ import annotations

import argparse

import pytest

from estimator.bench import frontend as bench_frontend
from estimator.formats.datasets import open_sequence
from estimator.pipeline import build_config, frame_interval_s
from estimator.rendered.synthetic import SynthOptions, synthesize
from estimator.rig_settings import apply_rig_settings


@pytest.fixture(scope="module")
def drive(tmp_path_factory):
    """A short rendered drive in KITTI's layout (1241 x 376, 10 Hz)."""
    root = tmp_path_factory.mktemp("drive")
    synthesize(root, SynthOptions.driving(frames=3, length_m=3.0, seed=1, layout="kitti"))
    return open_sequence(root)


def _args(*argv: str) -> argparse.Namespace:
    parser = argparse.ArgumentParser()
    bench_frontend.add_arguments(parser)
    return parser.parse_args(list(argv))


@pytest.mark.parametrize("argv", [(), ("--method", "msac")])
def test_bench_frontend_derives_the_settings_run_derives(drive, argv) -> None:
    args = _args(*argv)
    config, derived = bench_frontend.bench_config(bench_frontend.command_config(args), drive)
    method = argv[1] if argv else None
    expected, expected_derived = apply_rig_settings(
        build_config(estimator=method, backend=False), drive.rig, frame_interval_s(drive)
    )
    assert config.model_dump() == expected.model_dump()
    assert derived == expected_derived
    # The drive's wide rig gets its own settings, not the EuRoC defaults.
    assert config.frontend.search_radius_px == pytest.approx(131.9, abs=0.1)
    assert config.frontend.min_search_radius_px is not None
    assert config.frontend.max_features == 1551


def test_no_rig_settings_keeps_the_defaults(drive) -> None:
    args = _args("--no-rig-settings")
    config, derived = bench_frontend.bench_config(
        bench_frontend.command_config(args), drive, args.rig_settings
    )
    assert derived == []
    assert config.frontend.min_search_radius_px is None
    assert config.frontend.max_features == build_config().frontend.max_features
