"""Shared fixtures: the real EuRoC data beside the project, skipped with a reason when absent."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import pytest

if TYPE_CHECKING:
    from estimator.formats.datasets import Sequence
    from estimator.pipeline import RunResult

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


@dataclass(frozen=True)
class RealClipRun:
    """One pipeline run over a real clip: the opened sequence, the run and its summary."""

    sequence: Sequence
    run: RunResult
    summary: dict[str, Any]


def _run_real_clip(path: Path, *, imu: bool, **sections: dict[str, Any]) -> RealClipRun:
    """Run the default configuration (with or without the IMU) over a real clip, with
    ``sections`` set on it (e.g. ``backend={"landmarks": True}``); every frame must be tracked."""
    import warnings

    from estimator.formats.datasets import open_sequence
    from estimator.pipeline import build_config, run_sequence, summarize

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # unpaired camera rows
        sequence = open_sequence(path)
    config = build_config(imu=imu)
    for section, values in sections.items():
        for name, value in values.items():
            setattr(getattr(config, section), name, value)
    run = run_sequence(sequence, config, use_imu=imu)
    summary, _ = summarize(run)
    assert summary["frames_failed"] == 0, summary["status_counts"]
    return RealClipRun(sequence, run, summary)


@pytest.fixture
def run_real_clip():
    """What a real-clip test asks: the pipeline run over a clip with a few settings changed."""
    return _run_real_clip


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


def _vision_flight(
    factor: float, config: Any, frames: int, noise_seed: int, sigmas: Any
) -> tuple[list, Any]:
    """The back end on a simulated flight with its IMU, each frame measured against the
    previous one with errors of ``factor`` times the covariance it is handed; the fused
    answers and the true body poses."""
    import gtsam
    import numpy as np

    from estimator.backend import FusionBackend
    from estimator.geometry import invert_pose
    from estimator.rendered.scenario import CAMERA_MOUNT, smooth_trajectory
    from estimator.types import ImuNoise

    scenario = smooth_trajectory(frames, seed=4)
    camera = scenario.body_poses @ CAMERA_MOUNT
    rng = np.random.default_rng(noise_seed)
    covariance = np.diag(np.square(sigmas))
    backend = FusionBackend(config, CAMERA_MOUNT, ImuNoise())
    stamps = scenario.timestamps_ns
    out = []
    for k in range(frames):
        start = stamps[k - 1] if k else stamps[0] - 10**8
        relative = None
        if k:
            error = rng.multivariate_normal(np.zeros(6), factor * covariance)
            truth = invert_pose(camera[k - 1]) @ camera[k]
            relative = truth @ gtsam.Pose3.Expmap(error).matrix()
        imu = scenario.imu.between(int(start), int(stamps[k]))
        out.append(
            backend.add_frame(
                int(stamps[k]), relative, None, 100, imu, covariance=covariance if k else None
            )
        )
    return out, scenario.body_poses


@pytest.fixture
def vision_flight():
    """``vision_flight(factor, config, frames, noise_seed, sigmas)``: a simulated flight fused
    from relative poses whose errors are ``factor`` times their stated covariance (standard
    deviations ``sigmas``: rotation rad, translation m)."""
    return _vision_flight
