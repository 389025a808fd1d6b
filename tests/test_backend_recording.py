"""The back end's observer sees its construction and every frame, changes nothing, and what it
saw replays the back end to the same answers (benchmarks/backend_replay.py relies on it)."""

from __future__ import annotations

import copy

import numpy as np

from estimator.backend import FusionBackend
from estimator.backend.recording import BackendFrame, BackendInput, BackendSetup
from estimator.config import BackendConfig
from estimator.geometry import make_pose

STEP_NS = 50_000_000
MOUNT = make_pose(np.eye(3), np.array([0.02, -0.06, 0.01]))


def _feed(backend: FusionBackend, frames: int = 8) -> list[np.ndarray]:
    rng = np.random.default_rng(3)
    poses = [backend.add_frame(0, np.eye(4), None, 0, None).pose]
    for k in range(1, frames):
        motion = make_pose(np.eye(3), np.array([0.03, 0.0, 0.0]) + rng.normal(0, 1e-3, 3))
        relative = None if k == 4 else motion  # one frame without vision
        fused = backend.add_frame(
            k * STEP_NS, relative, None, 40, None, covariance=np.eye(6) * 1e-5
        )
        poses.append(fused.pose)
    return poses


def test_the_observer_sees_everything_changes_nothing_and_replays_the_answers() -> None:
    config = BackendConfig(use_imu=False)
    seen: list[BackendInput] = []
    observed = FusionBackend(
        config, MOUNT, None, observer=lambda given: seen.append(copy.deepcopy(given))
    )
    poses = _feed(observed)
    plain = _feed(FusionBackend(config, MOUNT, None))
    for pose, reference in zip(poses, plain, strict=True):
        np.testing.assert_array_equal(pose, reference)

    setup, *frames = seen
    assert isinstance(setup, BackendSetup) and setup.imu_noise is None
    assert setup.config == config
    np.testing.assert_array_equal(setup.body_from_camera, MOUNT)
    assert all(isinstance(frame, BackendFrame) for frame in frames)
    assert [frame.timestamp_ns for frame in frames] == [k * STEP_NS for k in range(8)]
    assert frames[4].arguments["relative_pose"] is None
    assert frames[5].arguments["inlier_count"] == 40

    replayed = FusionBackend(setup.config, setup.body_from_camera, setup.imu_noise)
    for frame, pose in zip(frames, poses, strict=True):
        assert isinstance(frame, BackendFrame)
        np.testing.assert_array_equal(
            replayed.add_frame(frame.timestamp_ns, **frame.arguments).pose, pose
        )
