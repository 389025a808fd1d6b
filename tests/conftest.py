"""Shared fixtures: the real EuRoC data beside the project, skipped with a reason when absent."""

from __future__ import annotations

from pathlib import Path

import pytest

PROJECT_ROOT = Path(__file__).resolve().parents[1]
SHARED_DATA = PROJECT_ROOT.parent / "shared" / "data"


def _dataset(name: str) -> Path:
    path = SHARED_DATA / name
    if not (path / "mav0").is_dir():
        pytest.skip(
            f"real EuRoC data not found at {path} (it lives in ../shared/data beside the "
            "project, present in CI; a fresh clone without it skips these tests)"
        )
    return path


@pytest.fixture(scope="session")
def euroc_v101_micro() -> Path:
    """EuRoC V1_01 first 95 stereo frames + IMU + ground truth (standing still)."""
    return _dataset("euroc_v101_micro")


@pytest.fixture(scope="session")
def euroc_v102_imu_segment() -> Path:
    """EuRoC V1_02 40 s of real IMU + ground truth, fast motion, no images."""
    return _dataset("euroc_v102_imu_segment")


@pytest.fixture(scope="session")
def euroc_mh01_moving() -> Path:
    """EuRoC MH_01 200 stereo frames + IMU + ground truth (carried and swung by hand)."""
    return _dataset("euroc_mh01_moving")


def _between_factor_ends(smoother_graph) -> set[tuple[str, int, str, int]]:
    """(symbol, index) of both ends of every relative-pose factor in a smoother's graph."""
    import gtsam

    factors = smoother_graph.getFactors()
    ends = set()
    for i in range(factors.size()):
        factor = factors.at(i)
        if factor is not None and isinstance(factor, gtsam.BetweenFactorPose3):
            first, second = (gtsam.Symbol(key) for key in factor.keys())
            ends.add((chr(first.chr()), first.index(), chr(second.chr()), second.index()))
    return ends


@pytest.fixture
def between_factor_ends():
    """What a back-end test asks of the smoother's graph: which keys its relative poses tie."""
    return _between_factor_ends
