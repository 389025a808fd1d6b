"""The image-only rotation reference, and what it says about the EuRoC standstill."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from estimator.config import SwarmvoConfig
from estimator.evaluation.image_reference import bearing_vectors, image_rotations
from estimator.evaluation.metrics import camera_ground_truth, relative_to_first
from estimator.formats.calibration import CameraModel
from estimator.formats.datasets import open_sequence
from estimator.geometry import (
    invert_pose,
    quat_to_matrix,
    rotation_angle_deg,
    rotation_vector_to_quat,
)
from estimator.odometry import Odometry

WIDTH, HEIGHT, FOCAL = 752, 480, 460.0


def _camera(distortion_model: str = "none", distortion: tuple = ()) -> CameraModel:
    return CameraModel.from_dict(
        {
            "width": WIDTH, "height": HEIGHT, "fx": FOCAL, "fy": FOCAL, "cx": 370.0,
            "cy": 250.0, "distortion_model": distortion_model, "distortion": list(distortion),
            "T_BS": np.eye(4).tolist(),
        }
    )  # fmt: skip


def _texture(seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    image = np.zeros((HEIGHT, WIDTH), np.float32)
    for scale in (3, 7, 15):
        noise = rng.normal(size=(HEIGHT // scale + 2, WIDTH // scale + 2)).astype(np.float32)
        image += cv2.resize(noise, (WIDTH, HEIGHT), interpolation=cv2.INTER_CUBIC)
    return cv2.normalize(image, None, 0, 255, cv2.NORM_MINMAX).astype(np.uint8)


def _rotation(degrees: list[float]) -> np.ndarray:
    return quat_to_matrix(rotation_vector_to_quat(np.radians(degrees)))


def test_bearings_are_unit_rays_through_the_pixels() -> None:
    camera = _camera()
    pixels = np.array([[370.0, 250.0], [370.0 + FOCAL, 250.0], [0.0, 0.0]])
    rays = bearing_vectors(pixels, camera)
    np.testing.assert_allclose(np.linalg.norm(rays, axis=1), 1.0)
    np.testing.assert_allclose(rays[0], [0, 0, 1], atol=1e-12)
    np.testing.assert_allclose(rays[1], [1 / np.sqrt(2), 0, 1 / np.sqrt(2)], atol=1e-9)


@pytest.mark.parametrize("degrees", [[0.3, 0.0, 0.0], [-0.2, 0.15, 0.1], [1.5, -2.0, 0.7]])
def test_pure_rotation_is_recovered_from_the_images(degrees: list[float]) -> None:
    camera = _camera()
    first = _texture(3)
    truth = _rotation(degrees)  # pose of the second camera in the first: R_01
    # A direction d seen by camera 0 is R_01^T d in camera 1: the image moves by K R^T K^-1.
    homography = camera.K @ truth.T @ np.linalg.inv(camera.K)
    second = cv2.warpPerspective(first, homography, (WIDTH, HEIGHT), flags=cv2.INTER_CUBIC)
    (measured,) = image_rotations(first, [second], camera)
    assert measured.tracked > 300
    assert rotation_angle_deg(measured.rotation.T @ truth) < 0.01
    assert measured.residual_deg < 0.01


def test_unrelated_images_are_refused() -> None:
    camera = _camera()
    with pytest.raises(ValueError, match="corners"):
        image_rotations(np.zeros((HEIGHT, WIDTH), np.uint8), [_texture(1)], camera)


@pytest.mark.slow
@pytest.mark.euroc
def test_euroc_standstill_rotation_follows_the_images(euroc_v101_micro: Path) -> None:
    """The estimate turns as the raw images turn, not as the ground truth says.

    Over the 95 frames the images themselves show the camera pitching by ~0.2 deg while the
    ground-truth attitude (from other sensors) turns the other way; the visual estimate must
    follow what the camera saw.
    """
    sequence = open_sequence(euroc_v101_micro)
    odometry = Odometry(sequence.rig, SwarmvoConfig(), imu_noise=sequence.imu_noise)
    reports = []
    previous = int(sequence.timestamps_ns[0]) - 50_000_000
    for frame in sequence:
        reports.append(odometry.process(frame, sequence.imu_between(previous, frame.timestamp_ns)))
        previous = frame.timestamp_ns
    last = len(sequence) - 1
    (images,) = image_rotations(
        sequence.load(0).left, [sequence.load(last).left], sequence.rig.left
    )
    truth = relative_to_first(
        camera_ground_truth(sequence.ground_truth, sequence.timestamps_ns, sequence.rig.left.T_BS)
    )[last, :3, :3]
    # The vision estimate (the fused pose also weighs the gyro, which sides with the ground truth).
    poses = np.array([report.frontend_pose for report in reports])
    estimate = (invert_pose(poses[0]) @ poses[last])[:3, :3]
    # The image-only rotation ignores translation: the camera moves ~2 mm along its y axis at
    # a median depth of ~2 m, which tilts the bearings by up to ~0.06 deg about x. The estimate
    # (measured 0.07 deg from the image-only rotation; 0.014 deg once its own translation is
    # projected with the stereo depths) is held to that, far below the 0.3 deg ground truth gap.
    assert rotation_angle_deg(images.rotation.T @ estimate) < 0.1
    # The data fact behind the looser ground-truth bound of the standstill test.
    assert rotation_angle_deg(images.rotation.T @ truth) > 0.2
