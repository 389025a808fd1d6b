"""Per-point temporal search windows and keyframes spaced by the scene's depth."""

from __future__ import annotations

import math

import numpy as np
import pytest

from estimator.config import FrontendConfig, SwarmvoConfig
from estimator.formats.calibration import CameraModel, StereoRig
from estimator.frontend.stereo import StereoPoints
from estimator.frontend.temporal import (
    WINDOW_SIGMAS,
    PredictionUncertainty,
    match_temporal,
    project,
    search_radii,
)
from estimator.geometry import invert_pose, make_pose, transform_points
from estimator.odometry.frames import Estimate
from estimator.odometry.references import References
from estimator.rig_settings import NARROW_SEARCH_RADIUS_PX, apply_rig_settings

WIDTH, HEIGHT, FOCAL, BASELINE = 1241, 376, 718.856, 0.54  # a KITTI-like rig
DT_NS = 100_000_000  # 10 Hz


def _rig(
    width: int = WIDTH, height: int = HEIGHT, focal: float = FOCAL, baseline: float = BASELINE
) -> StereoRig:
    def camera(x: float) -> CameraModel:
        return CameraModel(
            width=width, height=height, fx=focal, fy=focal, cx=width / 2, cy=height / 2,
            distortion_model="none", distortion=(), T_BS=make_pose(np.eye(3), [x, 0.0, 0.0]),
        )  # fmt: skip

    return StereoRig(left=camera(0.0), right=camera(baseline))


RECT = _rig().rectification
WINDOWS = FrontendConfig(search_radius_px=132.0, min_search_radius_px=10.0)


def _yaw(angle_rad: float) -> np.ndarray:
    """Rotation about the camera's y axis (down): a turn of the road."""
    c, s = math.cos(angle_rad), math.sin(angle_rad)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def _stereo_points(points: np.ndarray, descriptors: np.ndarray) -> StereoPoints:
    """Camera-frame points as a frame's stereo points (ideal pixels and disparities)."""
    pixels = project(points, RECT.fx, RECT.cx, RECT.cy)
    disparity = RECT.fx * BASELINE / points[:, 2]
    return StereoPoints(pixels, disparity, points, 0.01 * points[:, 2], descriptors, True)


def test_window_shrinks_with_depth_and_grows_with_prediction_uncertainty() -> None:
    depths = np.array([3.0, 10.0, 30.0, 80.0])
    moved = np.column_stack([np.zeros(4), np.zeros(4), depths])  # on the optical axis
    expected = project(moved, RECT.fx, RECT.cx, RECT.cy)
    sure = PredictionUncertainty(rotation_rad=1e-4, translation_m=0.02)
    unsure = PredictionUncertainty(rotation_rad=4e-3, translation_m=0.08)
    narrow = search_radii(moved, expected, sure, WINDOWS, RECT)
    wide = search_radii(moved, expected, unsure, WINDOWS, RECT)
    assert np.all(np.diff(narrow) <= 0) and narrow[0] > narrow[-1]  # far points: smaller
    assert np.all(wide >= narrow) and wide[1] > narrow[1]
    # On the axis: 3 sigma of f x hypot(rotation, translation / depth), in [10, 132] px.
    three_m = WINDOW_SIGMAS * FOCAL * math.hypot(1e-4, 0.02 / 3.0)
    assert narrow[0] == pytest.approx(three_m, rel=1e-9) and 10.0 < three_m < 132.0
    assert narrow[-1] == 10.0  # the floor
    # The same rotation error moves a pixel at the image's edge further than one at its centre.
    edge = np.array([[(WIDTH - 20 - RECT.cx) * 80.0 / FOCAL, 0.0, 80.0]])
    at_edge = search_radii(edge, project(edge, RECT.fx, RECT.cx, RECT.cy), unsure, WINDOWS, RECT)
    assert at_edge[0] > wide[-1]
    # A poor prediction, or windows not narrowed at all: the wide window for every point.
    np.testing.assert_array_equal(search_radii(moved, expected, None, WINDOWS, RECT), 132.0)
    fixed = FrontendConfig(search_radius_px=132.0)
    np.testing.assert_array_equal(search_radii(moved, expected, sure, fixed, RECT), 132.0)


def _street(rng: np.random.Generator, count: int) -> np.ndarray:
    """Points of a street ahead of the camera: walls and facades from 3 m to 90 m."""
    z = rng.uniform(3.0, 90.0, count)
    x = rng.choice([-1.0, 1.0], count) * rng.uniform(2.0, 12.0, count)
    y = rng.uniform(-4.0, 1.5, count)
    return np.column_stack([x, y, z])


def _drive_with_a_sharp_turn(frames: int) -> list[np.ndarray]:
    """World poses of a camera at 12 m/s and 10 Hz that swings from straight into a 45 deg/s
    turn within 0.6 s (a car's sharpest), and out again."""
    yaw_rate = np.zeros(frames)
    ramp = np.linspace(0.0, 1.0, 7)
    onset = ramp**3 * (10 - 15 * ramp + 6 * ramp**2)  # smootherstep
    yaw_rate[30:37] = onset
    yaw_rate[37:43] = 1.0
    yaw_rate[43:50] = onset[::-1]
    yaw_rate = np.radians(45.0) * yaw_rate
    poses, pose = [], np.eye(4)
    for rate in yaw_rate:
        poses.append(pose)
        pose = pose @ make_pose(_yaw(rate * 0.1), [0.0, 0.0, 1.2])
    return poses


def test_a_drive_with_a_sharp_turn_keeps_its_matches() -> None:
    """Each frame is matched against the previous one with windows from References' learned
    prediction error: narrow on the straight, and wide enough through the turn."""
    rng = np.random.default_rng(3)
    references = References(FrontendConfig(tracking="frame", min_search_radius_px=10.0))
    config = WINDOWS
    poses = _drive_with_a_sharp_turn(55)
    world = np.empty((0, 3))
    kept, radii_straight, radii_turn = [], [], []
    previous = None
    image = np.zeros((HEIGHT, WIDTH), np.uint8)
    # Random descriptors, one per world point: only a point's own partner is near enough in
    # Hamming distance, so every match missed is a window that missed.
    descriptors_of = rng.integers(0, 256, (300 * len(poses), 32), dtype=np.uint8)
    for index, pose in enumerate(poses):
        # Fresh street ahead of each frame, so that every frame sees a few hundred points.
        world = np.vstack([world, transform_points(pose, _street(rng, 300))])
        camera = transform_points(invert_pose(pose), world)
        pixels = project(camera, RECT.fx, RECT.cx, RECT.cy)
        visible = (camera[:, 2] > 2.0) & (pixels[:, 0] > 10) & (pixels[:, 0] < WIDTH - 10)
        visible &= (pixels[:, 1] > 10) & (pixels[:, 1] < HEIGHT - 10)
        ids = np.flatnonzero(visible)
        points = _stereo_points(camera[ids], descriptors_of[ids])
        estimate = Estimate(None, None, "")
        if previous is not None:
            prev_ids, prev_points, prev_pose = previous
            predicted = references.reference_from_previous @ references.motion_over(DT_NS)
            uncertainty = references.prediction_uncertainty(DT_NS)
            pairs = match_temporal(
                prev_points, points, config, RECT, invert_pose(predicted),
                uncertainty=uncertainty,
            )  # fmt: skip
            in_both = np.isin(prev_ids, ids).sum()
            right = prev_ids[pairs.reference_index] == ids[pairs.current_index]
            assert right.all()
            kept.append(len(pairs) / in_both)
            moved = transform_points(invert_pose(predicted), prev_points.points)
            radii = search_radii(
                moved, project(moved, RECT.fx, RECT.cx, RECT.cy), uncertainty, config, RECT
            )
            (radii_turn if index >= 30 else radii_straight).append(np.median(radii))
            truth = invert_pose(prev_pose) @ pose
            estimate = Estimate(truth, None, "", reference=references.reference)
        references.update(index, points, image, pose, estimate, index * DT_NS)
        previous = (ids, points, pose)
    kept = np.array(kept)
    assert kept.min() > 0.97  # through the turn as on the straight
    # The first frames search wide (nothing measured yet), the straight narrowly.
    assert radii_straight[0] == 132.0
    assert radii_straight[-1] < 15.0  # 3 sigma of what a car's prediction misses
    assert max(radii_turn) > 1.5 * radii_straight[-1]  # the turn widened them


def test_a_failed_frame_or_a_gap_makes_the_next_search_wide() -> None:
    references = References(FrontendConfig(tracking="frame"))
    image = np.zeros((4, 4), np.uint8)
    points = _stereo_points(np.array([[0.0, 0.0, 5.0]] * 100), np.zeros((100, 32), np.uint8))
    step = make_pose(np.eye(3), [0.0, 0.0, 1.0])
    assert references.prediction_uncertainty(DT_NS) is None  # nothing measured yet
    references.update(0, points, image, np.eye(4), Estimate(None, None, ""), 0)
    assert references.prediction_uncertainty(DT_NS) is None  # the first frame: at rest
    for index in range(1, 26):
        estimate = Estimate(step, None, "", reference=references.reference)
        references.update(index, points, image, np.eye(4), estimate, index * DT_NS)
    learned = references.prediction_uncertainty(DT_NS)
    assert learned is not None
    # Constant velocity explained every step from frame 2 on: 24 times the level decayed by
    # 0.9 from the prior; one sigma = acceleration x (0.1 s)^2.
    config = FrontendConfig()
    decay = 0.9**24 * 0.01
    assert learned.rotation_rad == pytest.approx(
        math.radians(config.prediction_angular_accel_deg_s2) * decay, rel=1e-9
    )
    assert learned.translation_m == pytest.approx(
        config.prediction_linear_accel_m_s2 * decay, rel=1e-9
    )
    # A step that turns 1 deg more than the last one raises the level at once.
    estimate = Estimate(make_pose(_yaw(math.radians(1.0)), [0, 0, 1.0]), None, "",
                        reference=references.reference)  # fmt: skip
    references.update(26, points, image, np.eye(4), estimate, 26 * DT_NS)
    raised = references.prediction_uncertainty(DT_NS)
    assert raised is not None
    assert raised.rotation_rad == pytest.approx(math.radians(1.0), rel=1e-6)
    assert references.prediction_uncertainty(3 * DT_NS) is None  # a gap of two frames
    references.update(27, points, image, np.eye(4), Estimate(None, None, "lost"), 27 * DT_NS)
    assert references.prediction_uncertainty(2 * DT_NS) is None  # after a failed frame


def _keyframe_changes(depth_m: float, config: FrontendConfig, step_m: float) -> int:
    """Keyframes made along 40 frames moving ``step_m`` forward each, in a scene at
    ``depth_m``."""
    references = References(config)
    image = np.zeros((4, 4), np.uint8)
    rng = np.random.default_rng(0)
    cloud = np.column_stack([rng.uniform(-2, 2, (200, 2)), np.linspace(0.5, 1.5, 200) * depth_m])
    points = _stereo_points(cloud, np.zeros((200, 32), np.uint8))
    references.update(0, points, image, np.eye(4), Estimate(None, None, ""), 0)
    changes = 0
    travelled = 0.0
    for index in range(1, 41):
        travelled += step_m
        keyframe = references.reference
        assert keyframe is not None
        start = keyframe.pose[2, 3]
        pose = make_pose(np.eye(3), [0.0, 0.0, travelled])
        relative = make_pose(np.eye(3), [0.0, 0.0, travelled - start])
        result = type("Result", (), {"inliers": np.ones(200, bool)})()
        estimate = Estimate(relative, result, "", reference=keyframe)
        references.update(index, points, image, pose, estimate, index * DT_NS)
        changes += references.reference is not keyframe
    return changes


def test_keyframe_spacing_scales_with_scene_depth() -> None:
    by_depth = FrontendConfig(keyframe_max_parallax=0.05)
    room = _keyframe_changes(3.0, by_depth, 0.04)  # 0.15 m threshold: every 4th frame
    street = _keyframe_changes(30.0, by_depth, 0.4)  # 1.5 m: the same, at 10x the speed
    assert room == street == 40 // 4
    assert _keyframe_changes(30.0, FrontendConfig(), 0.4) == 40  # 0.25 m: every frame
    # A configured metre threshold wins over the parallax.
    explicit = FrontendConfig(keyframe_max_parallax=0.05, keyframe_max_translation_m=0.25)
    assert _keyframe_changes(30.0, explicit, 0.4) == 40
    assert References(by_depth).keyframe_translation_m() == 0.25  # no keyframe yet


@pytest.mark.parametrize(
    ("rig", "interval_s", "wide"),
    [
        ((752, 480, 436.2, 0.110), 0.05, 40.0),  # EuRoC
        ((1241, 376, 718.856, 0.54), 0.1, 131.9),  # KITTI
        ((848, 480, 425.0, 0.050), 1 / 30, 26.0),  # RealSense D435
        ((1280, 720, 700.0, 0.120), 1 / 30, 42.8),  # ZED
    ],
)
def test_per_point_windows_are_derived_within_the_wide_window(rig, interval_s, wide) -> None:
    config, settings = apply_rig_settings(SwarmvoConfig(), _rig(*rig), interval_s)
    assert config.frontend.min_search_radius_px == NARROW_SEARCH_RADIUS_PX
    assert config.frontend.search_radius_px == pytest.approx(wide, abs=0.1)
    (setting,) = [s for s in settings if s.name == "min_search_radius_px"]
    assert "per-point windows" in setting.reason
    # Without a frame interval yet (a service session before its stamps tell the rate) the
    # windows are per point from the first frame, within the default wide one.
    config, _ = apply_rig_settings(SwarmvoConfig(), _rig(*rig), None)
    assert config.frontend.min_search_radius_px == NARROW_SEARCH_RADIUS_PX
    assert config.frontend.search_radius_px == SwarmvoConfig().frontend.search_radius_px
    # A configured wide window: nothing about the windows is derived.
    user = SwarmvoConfig.model_validate({"frontend": {"search_radius_px": 150.0}})
    config, _ = apply_rig_settings(user, _rig(*rig), interval_s)
    assert config.frontend.min_search_radius_px is None
    assert config.frontend.search_radius_px == 150.0
