"""A wrong estimate must not spoil the frames after it: neither the vision-alone plausibility
check nor the back end's gate lets it update the noise model or become the reference."""

from __future__ import annotations

import numpy as np
import pytest
from test_odometry import _config, _rendered_flight, _rendered_rig, _run

from estimator.geometry import invert_pose, make_pose, quat_to_matrix, rotation_angle_deg
from estimator.geometry import rotation_vector_to_quat as rotvec_quat
from estimator.odometry import Odometry
from estimator.odometry.estimation import PoseEstimation
from estimator.types import FrameStatus

WRONG_FRAME = 8


def _corrupting(monkeypatch: pytest.MonkeyPatch, wrong: np.ndarray) -> None:
    """From now on every estimate of frame ``WRONG_FRAME`` comes out composed with ``wrong``:
    the pose a fit with a flipped rotation or a bad match set would produce."""
    original = PoseEstimation.against

    def corrupted(self, reference, prediction, current, *args, **kwargs):
        estimate = original(self, reference, prediction, current, *args, **kwargs)
        if current.index == WRONG_FRAME and estimate.reference_from_current is not None:
            estimate.reference_from_current = estimate.reference_from_current @ wrong
            estimate.covariance = None  # the back end weighs the fit of the inliers instead
        return estimate

    monkeypatch.setattr(PoseEstimation, "against", corrupted)


def _run_watching_noise(odometry: Odometry, frames) -> tuple[list, list]:
    reports, noise = [], []
    for frame in frames:
        reports.append(odometry.process(frame))
        noise.append(odometry.noise.summary())
    return reports, noise


def _relative_rotation_error(report, truth: np.ndarray, k: int) -> float:
    true_motion = invert_pose(truth[k - 1]) @ truth[k]
    return rotation_angle_deg(true_motion[:3, :3].T @ report.relative_pose[:3, :3])


@pytest.mark.slow
def test_a_huge_wrong_rotation_is_not_accepted_as_reference(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Vision alone (no back end): a 94 degree wrong rotation is rejected against the
    constant-velocity prediction; the frame coasts and the frames after it are tracked as in a
    clean run."""
    frames, truth = _rendered_flight()
    config = _config(backend={"enabled": False}, registration={"method": "msac"})
    clean = _run(Odometry(_rendered_rig(), config), frames)
    odometry = Odometry(_rendered_rig(), config)
    flipped = make_pose(quat_to_matrix(rotvec_quat(np.radians([0, 94, 0]))), [0] * 3)
    _corrupting(monkeypatch, flipped)
    reports, noise = _run_watching_noise(odometry, frames)
    wrong = reports[WRONG_FRAME]
    assert wrong.status == FrameStatus.DEGRADED
    assert "implausible rotation" in wrong.message
    assert _relative_rotation_error(wrong, truth, WRONG_FRAME) < 1.0
    assert noise[WRONG_FRAME] == noise[WRONG_FRAME - 1]  # nothing learnt from it
    assert odometry.reference_index != WRONG_FRAME
    for report, reference in zip(reports[WRONG_FRAME + 1 :], clean[WRONG_FRAME + 1 :], strict=True):
        assert report.status == FrameStatus.OK
        np.testing.assert_allclose(report.pose[:3, 3], reference.pose[:3, 3], atol=2e-3)


@pytest.mark.slow
def test_a_frame_rejected_by_the_back_end_does_not_change_the_noise_model(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A 0.5 m wrong jump with a plausible rotation passes the front end's check but not the
    back end's gate: the frame is then no reference and the noise level does not learn from
    its residuals."""
    frames, truth = _rendered_flight()
    config = _config(backend={"enabled": True, "use_imu": False}, registration={"method": "msac"})
    odometry = Odometry(_rendered_rig(), config)
    wrong_motion = make_pose(quat_to_matrix(rotvec_quat(np.radians([0, 2, 0]))), [0.5, 0, 0])
    _corrupting(monkeypatch, wrong_motion)
    references = []
    reports, noise = [], []
    for frame in frames:
        reports.append(odometry.process(frame))
        noise.append(odometry.noise.summary())
        references.append(odometry.reference_index)
    wrong = reports[WRONG_FRAME]
    assert "relative pose rejected" in wrong.message
    assert noise[WRONG_FRAME] == noise[WRONG_FRAME - 1]
    assert references[WRONG_FRAME] != WRONG_FRAME
    # The front end coasts through it instead of chaining the 0.5 m jump.
    before = reports[WRONG_FRAME - 1].frontend_pose
    jump = np.linalg.norm(wrong.frontend_pose[:3, 3] - before[:3, 3])
    true_step = np.linalg.norm(truth[WRONG_FRAME, :3, 3] - truth[WRONG_FRAME - 1, :3, 3])
    assert abs(jump - true_step) < 0.05
    assert all(report.status == FrameStatus.OK for report in reports[WRONG_FRAME + 1 :])
