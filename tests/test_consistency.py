"""Per-measurement NEES of the front end (estimator.consistency.measurement_nees)."""

from __future__ import annotations

from types import SimpleNamespace

import gtsam
import numpy as np
import pytest

from estimator.evaluation.consistency import measurement_nees
from estimator.formats.datasets import GroundTruth
from estimator.geometry import make_pose

SIGMAS = np.array([1e-3, 2e-3, 1.5e-3, 4e-3, 3e-3, 5e-3])  # rotation rad, translation m


def _reports(errors: np.ndarray, covariance: np.ndarray, keyframe_every: int):
    """Frames 50 ms apart on a curved path; frame k is measured against its keyframe with
    exactly ``errors[k]`` (right perturbation of the true motion)."""
    n = len(errors)
    stamps = np.arange(n, dtype=np.int64) * 50_000_000
    truth = [make_pose(gtsam.Rot3.Expmap(np.array([0.0, 0.01 * k, 0.02 * k])).matrix(),
                       [0.1 * k, np.sin(0.1 * k), 0.0]) for k in range(n)]
    body_from_camera = make_pose(np.eye(3), [0.05, 0.0, 0.0])
    camera = [pose @ body_from_camera for pose in truth]
    frontend, reports = [camera[0]], []
    for k in range(n):
        reference = (k - 1) // keyframe_every * keyframe_every if k else None
        if k:
            motion = np.linalg.inv(camera[reference]) @ camera[k]
            frontend.append(frontend[reference] @ motion @ gtsam.Pose3.Expmap(errors[k]).matrix())
        reports.append(SimpleNamespace(
            timestamp_ns=int(stamps[k]), frontend_pose=frontend[k],
            reference_timestamp_ns=None if reference is None else int(stamps[reference]),
            measurement_covariance=covariance if k else None, covariance_scale=1.0))
    return reports, GroundTruth(stamps, np.array(truth)), body_from_camera


def test_right_covariances_give_one_per_dof_and_small_ones_more() -> None:
    rng = np.random.default_rng(0)
    errors = rng.normal(size=(1200, 6)) * SIGMAS
    covariance = np.diag(SIGMAS**2)
    check = measurement_nees(*_reports(errors, covariance, keyframe_every=1))
    summary = check.summary()
    assert summary["windows"] == 1199
    assert summary["mean_nees_per_dof"] == pytest.approx(1.0, abs=0.08)
    assert summary["rotation_per_dof"] == pytest.approx(1.0, abs=0.1)
    assert abs(check.lag1_new_reference) < 0.08  # independent errors
    # Sigmas reported half as large: four times the NEES.
    small = measurement_nees(*_reports(errors, covariance / 4, keyframe_every=1)).summary()
    assert small["mean_nees_per_dof"] == pytest.approx(4.0 * summary["mean_nees_per_dof"])


def test_errors_shared_within_a_keyframe_show_in_the_lag1_correlation() -> None:
    rng = np.random.default_rng(1)
    # One shared error per keyframe: frames 1-5 are measured against frame 0, 6-10 against 5...
    shared = np.vstack([np.zeros((1, 6)), np.repeat(rng.normal(size=(240, 6)), 5, axis=0)])
    errors = (0.9 * shared + 0.3 * rng.normal(size=shared.shape)) * SIGMAS
    check = measurement_nees(*_reports(errors, np.diag(SIGMAS**2), keyframe_every=5))
    assert check.lag1_same_reference > 0.8
    assert abs(check.lag1_new_reference) < 0.15
