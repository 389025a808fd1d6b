"""Measurements against a keyframe that has left the smoother's window (``old_reference``)."""

from __future__ import annotations

import itertools

import numpy as np

from estimator.backend import FusionBackend
from estimator.backend.keyframe_views import view_key
from estimator.backend.smoother import pose_key
from estimator.config import BackendConfig
from estimator.geometry import invert_pose
from estimator.rendered.scenario import CAMERA_MOUNT, smooth_trajectory
from estimator.types import FrameStatus, ImuNoise

BODY_FROM_CAMERA = CAMERA_MOUNT


def _keyframe_run(
    frames: int,
    keyframe_every: int,
    imu: bool,
    seed: int = 31,
    mode: str = "views",
    **settings: float,
):
    """Exact keyframe measurements: frame k measured against the latest keyframe (every
    ``keyframe_every`` frames, each measured against the one before)."""
    scenario = smooth_trajectory(frames, seed=seed)
    stamps = scenario.timestamps_ns
    camera = scenario.body_poses @ BODY_FROM_CAMERA
    backend = FusionBackend(
        BackendConfig(old_reference=mode, **settings), BODY_FROM_CAMERA, ImuNoise() if imu else None
    )
    answers = [backend.add_frame(int(stamps[0]), None, None, 0, scenario.imu.between(
        int(stamps[0]) - 10**9, int(stamps[0])) if imu else None)]  # fmt: skip
    keyframe = 0
    for k in range(1, frames):
        measured = invert_pose(camera[keyframe]) @ camera[k]
        batch = scenario.imu.between(int(stamps[k - 1]), int(stamps[k])) if imu else None
        answers.append(
            backend.add_frame(
                int(stamps[k]), measured, np.full(150, 0.02), 150, batch,
                reference_ns=int(stamps[keyframe]),
            )
        )  # fmt: skip
        if k % keyframe_every == 0:
            keyframe = k
    return scenario, backend, answers


def test_views_tie_frames_to_an_old_keyframe_through_its_view(between_factor_ends):
    """Frames 1..23 are measured against frame 0, which leaves the 0.4 s window at about
    frame 8: its view stays in the smoother and each frame gets its own factor from it."""
    scenario, backend, answers = _keyframe_run(24, keyframe_every=100, imu=False)
    assert all(answer.status is FrameStatus.OK for answer in answers)
    assert not backend.smoother.has_pose(0)
    assert backend.smoother.isam().valueExists(view_key(0))
    assert {("r", 0, "x", 22), ("r", 0, "x", 23)} <= between_factor_ends(backend.smoother.graph)
    estimated = invert_pose(backend.smoother.pose(20)) @ backend.smoother.pose(23)
    true = invert_pose(scenario.body_poses[20]) @ scenario.body_poses[23]
    assert np.allclose(estimated, true, atol=1e-6)


def test_views_go_once_no_measurement_refers_to_them():
    """Keyframes change every 15 frames over 6 s with the IMU: each view stays while its
    keyframe is measured against, then is marginalised with no numerical failure (restart)."""
    scenario, backend, answers = _keyframe_run(120, keyframe_every=15, imu=True)
    assert all(answer.status is FrameStatus.OK for answer in answers)
    assert not any("restarted" in answer.message for answer in answers)
    exists = backend.smoother.isam().valueExists
    assert exists(view_key(105)) and not exists(view_key(90)) and not exists(pose_key(90))
    estimated = invert_pose(backend.smoother.pose(112)) @ backend.smoother.pose(119)
    true = invert_pose(scenario.body_poses[112]) @ scenario.body_poses[119]
    assert np.linalg.norm(estimated[:3, 3] - true[:3, 3]) < 1e-3


def test_views_give_frames_measured_against_an_old_keyframe_its_uncertainty():
    """Without the IMU the absolute uncertainty grows with each keyframe measurement (frames
    10, 20, 30 are keyframes, each measured against the one before after it left the window):
    frame 30 is about three times as uncertain as frame 10. A pose prior from the old
    keyframe's estimate with the measurement's covariance alone keeps it at one time, and a
    filter trusting that sees the frame's errors as too large."""
    _, _, answers = _keyframe_run(34, keyframe_every=10, imu=False)
    first, third = answers[10].body_covariance, answers[30].body_covariance
    assert first is not None and third is not None
    assert 2.5 < np.trace(third) / np.trace(first) < 3.5
    assert np.linalg.eigvalsh(third - first).min() > 0


def test_measurements_against_one_keyframe_are_not_counted_as_independent():
    """Frames 1..20 all measured against frame 0 (no IMU): the n-th measurement's covariance is
    n times its own, so frame 20 is about twice as uncertain as frame 10, as a drift that
    accumulates along the keyframe's measurements is; counted as independent, the two are
    equally uncertain (one measurement each from the pinned frame 0)."""
    _, _, inflated = _keyframe_run(21, keyframe_every=100, imu=False)
    _, _, independent = _keyframe_run(21, keyframe_every=100, imu=False, keyframe_count_inflation=0)
    ratio = np.trace(inflated[20].body_covariance) / np.trace(inflated[10].body_covariance)
    assert 1.7 < ratio < 2.3
    ratio = np.trace(independent[20].body_covariance) / np.trace(independent[10].body_covariance)
    assert 0.8 < ratio < 1.25


def test_prior_reports_the_uncertainty_its_placement_drops():
    """As above with ``"prior"``: from frame 8 on, frames are placed in the world from their
    keyframe's estimate (frame 0, then 10, then 20). The smoother holds each to within one
    measurement (its marginal does not grow), but the reported covariance carries the
    keyframe's and grows along the frames placed from one keyframe, so it keeps growing."""
    _, backend, answers = _keyframe_run(34, keyframe_every=10, imu=False, mode="prior")
    before = np.trace(answers[5].body_covariance)  # no frame placed yet
    marginal = np.asarray(backend.smoother.isam().marginalCovariance(pose_key(33)))
    assert np.trace(marginal) < 2.2 * before  # what the graph alone reports
    covariances = [answers[k].body_covariance for k in (10, 20, 30)]
    assert np.trace(covariances[2]) > 5.0 * before
    for earlier, later in itertools.pairwise(covariances):
        assert np.linalg.eigvalsh(later - earlier).min() > 0


def test_placement_covariance_follows_the_frames():
    """The carried part moves with the frame (adjoint of the motion), a placement replaces it
    by the keyframe's reported covariance plus the earlier placements from that keyframe (a
    random walk along its measurements), and a restart carries the whole newest report."""
    from estimator.backend.placement_covariance import PlacementCovariance
    from estimator.geometry import transport_covariance

    rng = np.random.default_rng(3)
    base = rng.normal(size=(6, 6))
    marginal = base @ base.T + np.eye(6)
    measurement = 0.1 * np.eye(6)
    motion = np.eye(4)
    motion[:3, :3] = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    motion[:3, 3] = [0.3, -0.1, 0.2]
    carried = PlacementCovariance()
    assert np.allclose(carried.report(0, np.eye(4), marginal), marginal)
    carried.place(0, motion, measurement)
    placed = carried.report(1, motion, marginal)
    assert np.allclose(placed, marginal + transport_covariance(marginal, motion))
    moved = carried.report(2, motion @ motion, marginal)
    expected = marginal + transport_covariance(transport_covariance(marginal, motion), motion)
    assert np.allclose(moved, expected)
    carried.place(0, motion, measurement)  # the second frame placed from frame 0
    second = carried.report(3, motion, marginal)
    assert np.allclose(second, placed + measurement)
    carried.forget_before(2)
    carried.place(0, motion, measurement)  # forgotten reference: nothing to carry from it
    carried.anchor()
    assert np.allclose(carried.report(4, motion, marginal), marginal + second)
