"""Stereo landmarks in the back end: the inliers' pixels fix a frame's pose on their own."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from estimator.backend import FusionBackend
from estimator.backend.landmarks import spread_order, stereo_covariance
from estimator.backend.observations import StereoCamera, StereoObservations, stereo_pixels
from estimator.config import BackendConfig
from estimator.geometry import invert_pose, make_pose, rotation_angle_deg, transform_points
from estimator.rendered.scenario import CAMERA_MOUNT

FX, CX, CY, BASELINE = 436.0, 370.0, 245.0, 0.11
CAMERA_FROM_RECT = make_pose(Rotation.from_euler("xyz", [0.4, -0.3, 0.2], degrees=True).as_matrix(),
                             np.zeros(3))  # fmt: skip
CAMERA = StereoCamera(FX, CX, CY, BASELINE, CAMERA_FROM_RECT)
STEP_NS = 50_000_000


def _pixels(points_rect: np.ndarray) -> np.ndarray:
    """(u_left, u_right, v) of rectified-camera points."""
    depth = points_rect[:, 2]
    uv = np.column_stack([FX * points_rect[:, 0] / depth + CX, FX * points_rect[:, 1] / depth + CY])
    return stereo_pixels(uv, FX * BASELINE / depth)


def _scene(rng: np.random.Generator, count: int) -> np.ndarray:
    return np.column_stack(
        [rng.uniform(-3, 3, count), rng.uniform(-2, 2, count), rng.uniform(1.5, 5.0, count)]
    )


def _observations(
    world: np.ndarray, rect_poses: list[np.ndarray], reference: int, current: int, ids: np.ndarray,
    noise_px: float, rng: np.random.Generator,
) -> StereoObservations:  # fmt: skip
    """Frame ``current`` against ``reference``: point i keeps index ids[i] in every frame."""
    in_reference = transform_points(invert_pose(rect_poses[reference]), world)
    in_current = transform_points(invert_pose(rect_poses[current]), world)
    return StereoObservations(
        reference_ns=reference * STEP_NS,
        reference_ids=ids,
        current_ids=ids,
        reference_pixels=_pixels(in_reference) + rng.normal(0, noise_px, (len(ids), 3)),
        current_pixels=_pixels(in_current) + rng.normal(0, noise_px, (len(ids), 3)),
        reference_points=in_reference,
        camera=CAMERA,
        sigmas_px=(max(noise_px, 0.05),) * 3,
    )


@pytest.mark.parametrize("noise_px", [0.0, 0.2])
def test_landmarks_recover_the_true_pose_from_a_wrong_relative_pose(noise_px: float) -> None:
    """Without the relative-pose factor, frames 1-3 measured against frame 0 with a relative
    pose 8 mm and 0.3 deg off (as initial guess) end at the pose the pixels say."""
    rng = np.random.default_rng(3)
    motion = make_pose(Rotation.from_euler("xyz", [1.0, -2.0, 0.5], degrees=True).as_matrix(),
                       np.array([0.04, 0.01, -0.02]))  # fmt: skip
    body_poses = [np.eye(4)]
    for _ in range(3):
        body_poses.append(body_poses[-1] @ motion)
    rect_poses = [pose @ CAMERA_MOUNT @ CAMERA_FROM_RECT for pose in body_poses]
    world = transform_points(rect_poses[0], _scene(rng, 150))
    config = BackendConfig(use_imu=False, landmarks=True, landmark_between=False,
                           landmark_max_per_frame=100)  # fmt: skip
    backend = FusionBackend(config, CAMERA_MOUNT, None)
    backend.add_frame(0, np.eye(4), None, 0, None)
    error = make_pose(Rotation.from_rotvec([0.003, 0.0, -0.004]).as_matrix(),
                      np.array([0.006, -0.005, 0.0]))  # fmt: skip
    ids = np.arange(150)
    for k in (1, 2, 3):
        true_camera = invert_pose(CAMERA_MOUNT) @ body_poses[k] @ CAMERA_MOUNT
        covariance = np.diag([1e-4] * 3 + [1e-4] * 3)
        stereo = _observations(world, rect_poses, 0, k, ids, noise_px, rng)
        fused = backend.add_frame(
            k * STEP_NS, true_camera @ error, None, 150, None, reference_ns=0,
            covariance=covariance, stereo=stereo,
        )  # fmt: skip
        assert fused.status.value == "ok", fused.message
        translation_error = np.linalg.norm(fused.body_pose[:3, 3] - body_poses[k][:3, 3])
        angle = rotation_angle_deg(fused.body_pose[:3, :3].T @ body_poses[k][:3, :3])
        # The initial guess was 8 mm / 0.29 deg off; the pixels bring it to the truth.
        assert translation_error < (1e-4 if noise_px == 0 else 1.5e-3), k
        assert angle < (0.002 if noise_px == 0 else 0.03), k


def test_a_landmark_seen_again_from_a_new_keyframe_is_the_same_variable() -> None:
    """Frame 1 matched to frame 0 names its points; frame 2 matched to frame 1 (a new
    keyframe) observes the same landmarks, so no new landmark is made."""
    rng = np.random.default_rng(5)
    motion = make_pose(np.eye(3), np.array([0.03, 0.0, 0.0]))
    body_poses = [np.eye(4), motion, motion @ motion]
    rect_poses = [pose @ CAMERA_MOUNT @ CAMERA_FROM_RECT for pose in body_poses]
    world = transform_points(rect_poses[0], _scene(rng, 60))
    config = BackendConfig(
        use_imu=False, landmarks=True, landmark_max_per_frame=60, landmark_across_keyframes=True
    )
    backend = FusionBackend(config, CAMERA_MOUNT, None)
    backend.add_frame(0, np.eye(4), None, 0, None)
    ids = np.arange(60)
    covariance = np.eye(6) * 1e-4
    for k, reference in ((1, 0), (2, 1)):
        relative = invert_pose(CAMERA_MOUNT) @ invert_pose(body_poses[reference]) @ body_poses[k]
        stereo = _observations(world, rect_poses, reference, k, ids, 0.0, rng)
        backend.add_frame(
            k * STEP_NS, relative @ CAMERA_MOUNT, None, 60, None, reference_ns=reference * STEP_NS,
            covariance=covariance, stereo=stereo,
        )  # fmt: skip
    assert backend.landmark_count == 60


def test_spread_order_covers_the_image_before_repeating_a_cell() -> None:
    rng = np.random.default_rng(0)
    uv = np.vstack(
        [rng.uniform([0, 0], [60, 40], (200, 2)), rng.uniform([0, 0], [752, 480], (48, 2))]
    )
    pixels = stereo_pixels(uv, rng.uniform(1, 40, len(uv)))
    order = spread_order(pixels)
    assert sorted(order.tolist()) == list(range(len(uv)))
    first = pixels[order[:40]]
    # A prefix is spread: far more of it lies outside the dense corner than the 20 % overall.
    assert np.mean((first[:, 0] > 60) | (first[:, 2] > 40)) > 0.6


def test_stereo_covariance_shares_the_column_noise_between_both_images() -> None:
    covariance = stereo_covariance(0.1, 0.2, 0.05)
    assert covariance[0, 1] == pytest.approx(0.01)
    assert covariance[1, 1] == pytest.approx(0.01 + 0.0025)
    assert covariance[2, 2] == pytest.approx(0.04)
    assert np.all(np.linalg.eigvalsh(covariance) > 0)


@pytest.mark.slow
@pytest.mark.euroc
def test_real_clip_with_landmarks_is_tracked_within_the_bounds_of_the_default(
    euroc_mh01_moving: Path, run_real_clip
) -> None:
    """The option on MH_01, vision alone: measured 4.7 mm ATE and 0.0202 deg per frame (the
    default: 4.7 mm, 0.0211 deg), every frame tracked."""
    summary = run_real_clip(euroc_mh01_moving, imu=False, backend={"landmarks": True}).summary
    assert summary["ate_rmse_m"] < 0.0052
    assert summary["rpe_rot_rmse_deg"] < 0.022
