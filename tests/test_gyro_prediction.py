"""Gyro-predicted search windows: the rotation between frames from the IMU, its bias and
error level learned against vision."""

from __future__ import annotations

import math

import numpy as np
import pytest

from estimator.config import FrontendConfig
from estimator.frontend.stereo import StereoPoints
from estimator.frontend.temporal import project
from estimator.geometry import (
    invert_pose,
    make_pose,
    quat_to_matrix,
    rotation_vector_to_quat,
    transform_points,
)
from estimator.odometry.frames import Estimate
from estimator.odometry.gyro_prediction import GyroPrediction, integrate_gyro
from estimator.odometry.references import References
from estimator.types import ImuBatch

FOCAL, CX, CY = 718.856, 620.5, 188.0  # a KITTI-like rig
DT_NS = 100_000_000  # frames at 10 Hz
IMU_NS = 10_000_000  # the IMU at 100 Hz
# Body (IMU) axes into the rectified camera: the camera looks along the body's x axis.
RECT_FROM_BODY = np.array([[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]])
WINDOWS = FrontendConfig(search_radius_px=132.0, min_search_radius_px=10.0, tracking="frame")


def _rotation(rotvec: np.ndarray) -> np.ndarray:
    return quat_to_matrix(rotation_vector_to_quat(np.asarray(rotvec, dtype=float)))


def _batch(start_ns: int, end_ns: int, rate_body: np.ndarray) -> ImuBatch:
    """Samples start < t <= end of a constant body rate (rad/s)."""
    stamps = np.arange(start_ns + IMU_NS, end_ns + 1, IMU_NS, dtype=np.int64)
    rates = np.tile(rate_body, (len(stamps), 1))
    return ImuBatch(stamps, rates, np.zeros_like(rates))


def _points(count: int = 200, near: float = 3.0) -> np.ndarray:
    rng = np.random.default_rng(4)
    depth = rng.uniform(near, 80.0, count)
    x = rng.uniform(-0.8, 0.8, count) * depth
    y = rng.uniform(-0.2, 0.2, count) * depth
    return np.column_stack([x, y, depth])


def _stereo_points(points: np.ndarray) -> StereoPoints:
    pixels = project(points, FOCAL, CX, CY)
    disparity = FOCAL * 0.54 / points[:, 2]
    descriptors = np.zeros((len(points), 32), np.uint8)
    return StereoPoints(pixels, disparity, points, 0.01 * points[:, 2], descriptors, True)


def test_integration_of_a_constant_rate_is_exact() -> None:
    rate = np.array([0.1, -0.3, 0.7])
    batch = _batch(0, DT_NS, rate)
    rotation = integrate_gyro(batch.timestamps_ns, batch.gyro, 0, DT_NS)
    assert rotation is not None
    np.testing.assert_allclose(rotation, _rotation(rate * 0.1), atol=1e-12)
    assert integrate_gyro(batch.timestamps_ns[5:], batch.gyro[5:], 0, DT_NS) is None  # a hole



def test_integration_reads_the_samples_as_the_back_end_preintegration() -> None:
    """Frame times between the samples, a varying rate: the search windows' rotation is the one
    the back end's gyro factor measures over the same interval (one sampling rule)."""
    from estimator.backend.imu import preintegrate_gyro, rotation_params
    from estimator.types import ImuNoise

    rng = np.random.default_rng(7)
    stamps = np.arange(0, 130_000_000, IMU_NS, dtype=np.int64)
    rates = rng.normal(0.0, 0.8, size=(len(stamps), 3))
    start_ns, end_ns = 3_000_000, 3_000_000 + DT_NS + 4_000_000
    rotation = integrate_gyro(stamps, rates, start_ns, end_ns)
    expected = preintegrate_gyro(stamps, rates, start_ns, end_ns, rotation_params(ImuNoise()))
    assert rotation is not None
    np.testing.assert_allclose(rotation, expected.delta_rotation, atol=1e-12)

def test_the_gyro_lands_a_turning_cars_points_within_a_pixel() -> None:
    """Straight at 12 m/s, then a turn at 45 deg/s begins: constant velocity misses it by tens
    of pixels, the gyro's prediction (with a bias it has learned against vision) lands every
    point within a pixel, and the windows stay narrow."""
    bias = np.array([0.004, -0.006, 0.003])  # rad/s, body frame
    references = References(WINDOWS, GyroPrediction(RECT_FROM_BODY, math.radians(2.0)))
    image = np.zeros((4, 4), np.uint8)
    reference_points = _points(near=10.0)  # in the previous camera, as seen from it
    pose = np.eye(4)  # rectified camera in the world
    rate = np.zeros(3)
    misses, cv_misses, radii = [], [], []
    for index in range(30):
        if index == 20:
            rate = np.array([0.0, 0.0, math.radians(45.0)])  # yaw about the body's z (up)
        now_ns = index * DT_NS
        step_rotation = RECT_FROM_BODY @ _rotation(rate * 0.1) @ RECT_FROM_BODY.T
        step = make_pose(step_rotation, [0.0, 0.0, 1.2]) if index else np.eye(4)
        pose = pose @ step  # previous <- current is ``step``
        batch = _batch(now_ns - DT_NS, now_ns, rate + bias) if index else None
        references.advance_gyro(batch, now_ns)
        current_points = transform_points(invert_pose(step), reference_points)
        if index:
            truth = project(current_points, FOCAL, CX, CY)
            for prediction, found in (
                (references.motion_over(DT_NS), misses),
                (references.motion, cv_misses),  # constant velocity alone
            ):
                moved = transform_points(invert_pose(prediction), reference_points)
                offsets = np.linalg.norm(project(moved, FOCAL, CX, CY) - truth, axis=1)
                found.append(float(offsets.max()))
            uncertainty = references.prediction_uncertainty(DT_NS)
            radii.append(None if uncertainty is None else 3 * FOCAL * uncertainty.rotation_rad)
        estimate = Estimate(step if index else None, None, "", reference=references.reference)
        references.update(index, _stereo_points(current_points), image, pose, estimate, now_ns)
    # The first steps carry the bias (0.008 rad/s x 0.1 s, 0.6-1 px); learned, it is gone.
    assert misses[0] > 20.0  # nothing measured yet: the translation is unknown
    assert max(misses[1:4]) < 3.0
    assert max(misses[10:]) < 1.0  # the turn included
    assert cv_misses[19] > 40.0  # constant velocity misses the start of the turn
    np.testing.assert_allclose(references.gyro.bias, bias, atol=1e-3)
    assert radii[-1] is not None and radii[-1] < 3.0  # 3 sigma of the rotation, in pixels


def test_no_samples_leave_the_constant_velocity_prediction() -> None:
    references = References(WINDOWS, GyroPrediction(RECT_FROM_BODY, math.radians(2.0)))
    image = np.zeros((4, 4), np.uint8)
    points = _stereo_points(_points(20))
    step = make_pose(np.eye(3), [0.0, 0.0, 1.0])
    for index in range(3):
        references.advance_gyro(None, index * DT_NS)
        estimate = Estimate(step if index else None, None, "", reference=references.reference)
        references.update(index, points, image, np.eye(4), estimate, index * DT_NS)
    references.advance_gyro(None, 3 * DT_NS)
    np.testing.assert_array_equal(references.motion_over(DT_NS), references.motion)
    uncertainty = references.prediction_uncertainty(DT_NS)
    assert uncertainty is not None
    assert uncertainty.rotation_rad == pytest.approx(references.angular_accel * 0.01)


def test_odometry_uses_the_gyro_only_with_per_point_windows() -> None:
    from estimator.config import SwarmvoConfig
    from estimator.formats.calibration import CameraModel, StereoRig
    from estimator.odometry import Odometry

    def camera(x: float) -> CameraModel:
        return CameraModel(
            width=1241, height=376, fx=FOCAL, fy=FOCAL, cx=CX, cy=CY, distortion_model="none",
            distortion=(), T_BS=make_pose(RECT_FROM_BODY.T, x * RECT_FROM_BODY[0]),
        )  # fmt: skip

    rig = StereoRig(left=camera(0.0), right=camera(0.54))  # baseline along the camera x
    one_window = Odometry(rig, SwarmvoConfig())
    assert one_window.gyro_prediction is None
    per_point = Odometry(rig, SwarmvoConfig(frontend=WINDOWS))
    gyro = per_point.gyro_prediction
    assert gyro is not None
    np.testing.assert_allclose(gyro.rect_from_body, RECT_FROM_BODY, atol=1e-9)
    off = WINDOWS.model_copy(update={"gyro_prediction": False})
    assert Odometry(rig, SwarmvoConfig(frontend=off)).gyro_prediction is None
