"""Rendered sequences: ground truth read back exactly, images consistent with it, IMU too."""

from __future__ import annotations

import warnings
from pathlib import Path

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from estimator.formats.datasets import open_sequence
from estimator.geometry import invert_pose, make_pose, rotation_angle_deg, transform_points
from estimator.rendered.camera import CAMERA
from estimator.rendered.synthetic import SynthOptions, read_broken_frames, synthesize
from estimator.rendered.trajectory import GRAVITY, loop_for_length, simulate_imu
from estimator.rendered.world import build_world
from estimator.types import ImuNoise


@pytest.fixture(scope="module")
def rendered(tmp_path_factory):
    """A short clean sequence (12 frames, 1.2 m) and its reopened form."""
    root = tmp_path_factory.mktemp("synth") / "seq"
    result = synthesize(root, SynthOptions(frames=12, length_m=1.2, fps=20.0, seed=3))
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a clean rendered sequence must pair every frame
        sequence = open_sequence(root)
    return result, sequence


def test_written_ground_truth_reads_back_exactly(rendered):
    result, sequence = rendered
    assert len(sequence) == 12
    assert sequence.format == "euroc"
    np.testing.assert_array_equal(sequence.timestamps_ns, result.frame_timestamps_ns)
    gt = sequence.ground_truth
    np.testing.assert_array_equal(gt.timestamps_ns, result.imu_timestamps_ns)
    np.testing.assert_allclose(gt.poses, result.body_poses, atol=1e-12)
    assert gt.velocities is not None and gt.gyro_bias is not None and gt.accel_bias is not None
    # The velocity column is the derivative of the position column.
    dt = np.diff(gt.timestamps_ns) * 1e-9
    finite_difference = np.diff(gt.poses[:, :3, 3], axis=0) / dt[:, None]
    midpoint_velocity = 0.5 * (gt.velocities[1:] + gt.velocities[:-1])
    np.testing.assert_allclose(finite_difference, midpoint_velocity, atol=2e-3)
    rig = sequence.rig
    assert rig.baseline == pytest.approx(CAMERA["baseline"], abs=1e-12)
    assert rig.rectification.is_identity  # ideal pinhole pair, already rectified
    assert sequence.imu_noise is not None and sequence.imu_noise.rate_hz == 200.0
    frame = sequence.load(0)
    assert frame.left.shape == (CAMERA["height"], CAMERA["width"]) and frame.left.dtype == np.uint8


def _sample(image: np.ndarray, pixels: np.ndarray) -> np.ndarray:
    map_x = pixels[:, 0].astype(np.float32).reshape(-1, 1)
    map_y = pixels[:, 1].astype(np.float32).reshape(-1, 1)
    return cv2.remap(image, map_x, map_y, cv2.INTER_LINEAR).reshape(-1).astype(float)


def _project(points: np.ndarray) -> np.ndarray:
    f, cx, cy = CAMERA["f"], CAMERA["cx"], CAMERA["cy"]
    return np.stack([f * points[:, 0] / points[:, 2] + cx, f * points[:, 1] / points[:, 2] + cy], 1)


def _reprojection_residual(
    sequence, result, index: int, perturb: np.ndarray | None = None
) -> tuple[float, float]:
    """Median |I_left(k)(p) - I(q)| with q the GT reprojection into the right camera and into
    the next left image (via the read-back ground truth and calibration)."""
    rig = sequence.rig
    times = sequence.timestamps_ns
    T_W_left = sequence.ground_truth.interpolate(times[[index, index + 1]]) @ rig.left.T_BS
    _, inv_depth = result.world.render(T_W_left[0])
    left0 = sequence.load(index).left
    right0 = sequence.load(index).right
    left1 = sequence.load(index + 1).left
    # Pixels on smooth surfaces (no depth edge nearby), on a grid.
    ys, xs = np.mgrid[20 : left0.shape[0] - 20 : 7, 20 : left0.shape[1] - 20 : 7]
    edges = cv2.dilate(
        (cv2.Laplacian(inv_depth, cv2.CV_32F) ** 2 > 1e-8).astype(np.uint8), np.ones((9, 9))
    )
    keep = (inv_depth[ys, xs] > 0) & (edges[ys, xs] == 0)
    xs, ys = xs[keep], ys[keep]
    depth = 1.0 / inv_depth[ys, xs]
    f, cx, cy = CAMERA["f"], CAMERA["cx"], CAMERA["cy"]
    points = np.stack([(xs - cx) / f * depth, (ys - cy) / f * depth, depth], 1)
    reference = left0[ys, xs].astype(float)
    in_right = transform_points(invert_pose(rig.T_left_right), points)
    next_from_current = invert_pose(T_W_left[1]) @ T_W_left[0]
    if perturb is not None:
        next_from_current = perturb @ next_from_current
    in_next = transform_points(next_from_current, points)
    residuals = []
    for image, moved in ((right0, in_right), (left1, in_next)):
        pixels = _project(moved)
        inside = (
            (moved[:, 2] > 0.1)
            & (pixels[:, 0] > 2)
            & (pixels[:, 0] < image.shape[1] - 3)
            & (pixels[:, 1] > 2)
            & (pixels[:, 1] < image.shape[0] - 3)
        )
        assert inside.sum() > 500
        residuals.append(
            float(np.median(np.abs(_sample(image, pixels[inside]) - reference[inside])))
        )
    return residuals[0], residuals[1]


def test_images_agree_with_ground_truth_poses_and_stereo_geometry(rendered):
    result, sequence = rendered
    stereo, temporal = _reprojection_residual(sequence, result, 4)
    # Same surface point, same texture: only resampling differences remain.
    assert stereo < 4.0
    assert temporal < 4.0
    # A 1 degree error in the relative pose is clearly visible in the images.
    wrong = np.eye(4)
    wrong[:3, :3] = Rotation.from_rotvec(np.radians([0.0, 1.0, 0.0])).as_matrix()
    _, temporal_wrong = _reprojection_residual(sequence, result, 4, perturb=wrong)
    assert temporal_wrong > 3 * max(temporal, 2.0)


def test_disparity_of_rendered_points_is_f_b_over_z(rendered):
    result, sequence = rendered
    T_W_left = sequence.ground_truth.interpolate(sequence.timestamps_ns[[2]])[0]
    T_W_left = T_W_left @ sequence.rig.left.T_BS
    _, inv_left = result.world.render(T_W_left)
    _, inv_right = result.world.render(T_W_left @ sequence.rig.T_left_right)
    f, b = CAMERA["f"], CAMERA["baseline"]
    # Along each row, the right view shows the point at x - f b / Z with the same depth.
    ys, xs = np.mgrid[30:450:11, 120:700:13]
    inv = inv_left[ys, xs]
    disparity = f * b * inv
    xr = np.round(xs - disparity).astype(int)
    valid = (inv > 0) & (xr >= 0)
    rows = ys[valid]
    # Integer sampling: compare where the depth is locally smooth in the right view.
    right_inv = inv_right[rows, xr[valid]]
    smooth = np.abs(right_inv - inv[valid]) < 0.02 * inv[valid]
    assert smooth.mean() > 0.9  # occlusion boundaries are the only exceptions


def test_renderer_pixel_centres_are_those_of_the_calibration(rendered):
    """A 180 deg roll about the optical axis mirrors the image about (cx, cy) exactly.

    The renderer and the written intrinsics both put pixel centres on integer coordinates; a
    half-pixel disagreement would need a 1 px shift to line the mirrored images up.
    """
    result, sequence = rendered
    T_WC = sequence.ground_truth.interpolate(sequence.timestamps_ns[[3]])[0]
    T_WC = T_WC @ sequence.rig.left.T_BS
    image, _ = result.world.render(T_WC)
    rolled, _ = result.world.render(T_WC @ make_pose(np.diag([-1.0, -1.0, 1.0]), np.zeros(3)))
    ys, xs = np.mgrid[20:460, 20:730]
    centre_x, centre_y = round(2 * CAMERA["cx"]), round(2 * CAMERA["cy"])
    assert (centre_x, centre_y) == (2 * CAMERA["cx"], 2 * CAMERA["cy"])

    def mismatch(dx: int, dy: int) -> float:
        mirrored = image[centre_y - ys + dy, centre_x - xs + dx].astype(float)
        return float(np.mean(np.abs(rolled[ys, xs] - mirrored)))

    aligned = mismatch(0, 0)
    assert aligned < 1.0  # grey levels: only mipmap blending differs
    assert min(mismatch(1, 0), mismatch(-1, 0), mismatch(0, 1), mismatch(0, -1)) > 10 * aligned


def test_rendered_images_agree_with_the_calibration_to_sub_pixel(rendered):
    """Corners back-projected with their true depth and reprojected with the calibration that
    was read back land where Lucas-Kanade finds them: in the right image and in the next left
    image, without a mean offset (measured: < 0.01 px, from ~0.1 px noise per corner)."""
    result, sequence = rendered
    rig = sequence.rig
    f, cx, cy = rig.left.fx, rig.left.cx, rig.left.cy
    times = sequence.timestamps_ns
    offsets: dict[str, list[np.ndarray]] = {"right": [], "next": []}
    for index in range(len(sequence) - 1):
        T_W_left = sequence.ground_truth.interpolate(times[[index, index + 1]]) @ rig.left.T_BS
        _, inv_depth = result.world.render(T_W_left[0])
        left = sequence.load(index).left
        corners = cv2.goodFeaturesToTrack(left, 400, 0.01, 10).reshape(-1, 2)
        pixels = np.rint(corners).astype(int)  # integer pixels: the true depth is exact there
        # Keep corners away from depth edges, where the patch mixes two surfaces.
        edges = cv2.dilate(
            (cv2.Laplacian(inv_depth, cv2.CV_32F) ** 2 > 1e-8).astype(np.uint8), np.ones((15, 15))
        )
        keep = (inv_depth[pixels[:, 1], pixels[:, 0]] > 0) & (
            edges[pixels[:, 1], pixels[:, 0]] == 0
        )
        pixels = pixels[keep].astype(float)
        depth = 1.0 / inv_depth[pixels[:, 1].astype(int), pixels[:, 0].astype(int)]
        points = np.column_stack(
            [(pixels[:, 0] - cx) / f * depth, (pixels[:, 1] - cy) / f * depth, depth]
        )
        targets = {
            "right": (sequence.load(index).right, rig.right, invert_pose(rig.T_left_right)),
            "next": (
                sequence.load(index + 1).left,
                rig.left,
                invert_pose(T_W_left[1]) @ T_W_left[0],
            ),
        }
        for name, (image, camera, target_from_left) in targets.items():
            moved = transform_points(target_from_left, points)
            expected = np.column_stack(
                [
                    camera.fx * moved[:, 0] / moved[:, 2] + camera.cx,
                    camera.fy * moved[:, 1] / moved[:, 2] + camera.cy,
                ]
            ).astype(np.float32)
            found, status, _ = cv2.calcOpticalFlowPyrLK(
                left,
                image,
                pixels.astype(np.float32),
                expected.copy(),
                winSize=(11, 11),
                maxLevel=0,
                criteria=(cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 50, 0.001),
                flags=cv2.OPTFLOW_USE_INITIAL_FLOW,
            )
            good = (status.ravel() == 1) & (np.linalg.norm(found - expected, axis=1) < 1.0)
            offsets[name].append((found - expected)[good])
    for name, chunks in offsets.items():
        offset = np.concatenate(chunks)
        assert len(offset) > 1000, name
        assert np.all(np.abs(offset.mean(axis=0)) < 0.02), (name, offset.mean(axis=0))
        assert np.all(np.median(np.abs(offset), axis=0) < 0.1), name


def test_noiseless_imu_integrates_to_ground_truth(tmp_path):
    result = synthesize(
        tmp_path / "imu", SynthOptions(frames=7, fps=5.0, length_m=2.4, imu_noise_scale=0.0, seed=1)
    )
    sequence = open_sequence(result.root)
    imu, gt = sequence.imu, sequence.ground_truth
    assert np.abs(gt.gyro_bias).max() == 0.0 and np.abs(gt.accel_bias).max() == 0.0
    dt = np.diff(imu.timestamps_ns) * 1e-9
    # Gyro: trapezoidal rotation increments, chained over one second.
    steps = Rotation.from_rotvec(0.5 * (imu.gyro[1:] + imu.gyro[:-1]) * dt[:, None])
    start, end = 40, 240  # samples, 1 s apart
    rotation = Rotation.from_matrix(gt.poses[start, :3, :3])
    for step in steps[start:end]:
        rotation = rotation * step
    error = rotation_angle_deg(rotation.as_matrix().T @ gt.poses[end, :3, :3])
    assert error < 2e-3  # degrees, after 1 s of up to ~100 deg/s motion
    # Accelerometer: specific force + gravity, rotated to the world, double-integrated.
    world_accel = np.einsum("kij,kj->ki", gt.poses[:, :3, :3], imu.accel) + GRAVITY
    position, velocity = gt.poses[start, :3, 3].copy(), gt.velocities[start].copy()
    for k in range(start, end):
        mean_accel = 0.5 * (world_accel[k] + world_accel[k + 1])
        position += velocity * dt[k] + 0.5 * mean_accel * dt[k] ** 2
        velocity += mean_accel * dt[k]
    assert np.linalg.norm(position - gt.poses[end, :3, 3]) < 2e-3
    assert np.linalg.norm(velocity - gt.velocities[end]) < 2e-3


def test_noisy_imu_has_the_specified_white_noise_and_bias_walk():
    trajectory = loop_for_length(20.0, 100.0)
    state = trajectory.state(np.arange(20000) / 200.0)
    noise = ImuNoise()
    rng = np.random.default_rng(0)
    gyro, accel, gyro_bias, accel_bias = simulate_imu(state, noise, rng, scale=1.0)
    clean_gyro, clean_accel, zero_g, zero_a = simulate_imu(state, noise, rng, scale=0.0)
    assert np.abs(zero_g).max() == 0.0 and np.abs(zero_a).max() == 0.0
    white = gyro - clean_gyro - gyro_bias
    assert white.std() == pytest.approx(noise.gyro_noise_density * np.sqrt(200.0), rel=0.05)
    white = accel - clean_accel - accel_bias
    assert white.std() == pytest.approx(noise.accel_noise_density * np.sqrt(200.0), rel=0.05)
    # Bias increments: random walk with sigma = random_walk * sqrt(dt).
    steps = np.diff(gyro_bias, axis=0)
    assert steps.std() == pytest.approx(noise.gyro_random_walk * np.sqrt(1 / 200.0), rel=0.05)
    steps = np.diff(accel_bias, axis=0)
    assert steps.std() == pytest.approx(noise.accel_random_walk * np.sqrt(1 / 200.0), rel=0.05)


def test_same_seed_same_files_and_other_seed_differs(tmp_path):
    options = SynthOptions(frames=2, length_m=0.5, seed=11, noise=2.0, texture_px_per_m=48.0)
    one = synthesize(tmp_path / "one", options)
    two = synthesize(tmp_path / "two", SynthOptions(**{**vars(options)}))
    other = synthesize(tmp_path / "other", SynthOptions(**{**vars(options), "seed": 12}))
    relative = Path("mav0/cam0/data") / f"{one.frame_timestamps_ns[1]}.png"
    imu = Path("mav0/imu0/data.csv")
    assert (one.root / relative).read_bytes() == (two.root / relative).read_bytes()
    assert (one.root / imu).read_bytes() == (two.root / imu).read_bytes()
    assert (one.root / relative).read_bytes() != (other.root / relative).read_bytes()


def test_broken_frames_are_broken_and_listed(tmp_path):
    result = synthesize(
        tmp_path / "broken", SynthOptions(frames=10, length_m=1.0, broken_fraction=0.5, seed=5)
    )
    broken = read_broken_frames(result.root)
    assert broken == result.broken
    assert len(broken) == 5 and min(broken) >= 2
    sequence = open_sequence(result.root)
    for index, kind in broken.items():
        frame = sequence.load(index)
        if kind == "black":
            assert frame.left.max() == 0 and frame.right.max() == 0
        elif kind == "blur":
            assert cv2.Laplacian(frame.left, cv2.CV_64F).var() < 5.0
        else:
            T_W_left = sequence.ground_truth.interpolate([frame.timestamp_ns])[0]
            T_W_left = T_W_left @ sequence.rig.left.T_BS
            expected, _ = result.world.render(T_W_left @ sequence.rig.T_left_right)
            assert np.abs(frame.right.astype(float) - expected).mean() > 20.0
    assert set(broken.values()) <= {"black", "blur", "shuffled"}


def test_large_loop_keeps_clear_of_the_pillars():
    """The default 20 m / 200 frame loop fits its hall: every pillar >= 0.9 m from the camera."""
    trajectory = loop_for_length(20.0, 199 / 20.0)
    assert trajectory.path_length() == pytest.approx(20.0, rel=1e-6)
    world = build_world(trajectory, np.random.default_rng(0), px_per_m=8.0)
    pillars = world.planes[6:]
    assert len(pillars) >= 24  # 4 faces per pillar, at least 6 pillars
    centres = trajectory.state(np.linspace(0, trajectory.duration, 2000)).positions
    corners = np.array([plane.corners for plane in pillars])  # (P, 4, 3)
    low, high = corners.min(axis=1)[:, :2], corners.max(axis=1)[:, :2]
    # Distance from each path point to each pillar footprint (axis-aligned rectangle).
    gap = np.maximum(
        np.maximum(low[None] - centres[:, None, :2], centres[:, None, :2] - high[None]), 0
    )
    assert np.linalg.norm(gap, axis=-1).min() > 0.9
    half_x, half_y, height = world.bounds
    assert np.abs(centres[:, 0]).max() < half_x - 2.0 and np.abs(centres[:, 1]).max() < half_y - 2.0
    assert 0.5 < centres[:, 2].min() and centres[:, 2].max() < height - 0.5


@pytest.mark.parametrize(
    ("field", "value"),
    [
        ("frames", 1), ("length_m", 0.0), ("noise", -1.0), ("blur", 2.0),
        ("broken_fraction", 0.9), ("standstill_s", float("nan")), ("standstill_s", 61.0),
        ("seed", -1),
    ],
)
def test_bad_options_are_rejected(tmp_path, field, value):
    with pytest.raises(ValueError, match=field.split("_")[0]):
        synthesize(tmp_path / "bad", SynthOptions(**{field: value}))


def test_existing_output_is_not_overwritten(tmp_path):
    synthesize(tmp_path / "seq", SynthOptions(frames=2, length_m=2.0))
    with pytest.raises(ValueError, match="already exists"):
        synthesize(tmp_path / "seq", SynthOptions(frames=2, length_m=2.0))


@pytest.mark.slow
def test_image_effects_change_the_images_as_specified(tmp_path):
    base = {"frames": 4, "length_m": 0.5, "seed": 9, "texture_px_per_m": 48.0}

    def left(name: str, **effects) -> np.ndarray:
        result = synthesize(tmp_path / name, SynthOptions(**base, **effects))
        return open_sequence(result.root).load(2).left.astype(float)

    clean = left("clean")
    noisy = left("noise", noise=5.0)
    assert np.std(noisy - clean) == pytest.approx(5.0, rel=0.15)
    blurred = left("blur", blur=1.0)
    sharpness = cv2.Laplacian(blurred, cv2.CV_64F).var() / cv2.Laplacian(clean, cv2.CV_64F).var()
    assert sharpness < 0.8  # 0.17 m of motion per frame smears the texture
    bright = left("bright", brightness=0.3)
    gain = np.median(bright[clean > 20] / clean[clean > 20])
    assert abs(gain - 1.0) > 0.01 and abs(gain - 1.0) <= 0.3 + 0.01


def test_standstill_option_holds_the_body_still_then_starts_smoothly(tmp_path):
    options = SynthOptions(frames=4, length_m=0.5, seed=5, standstill_s=0.5)
    result = synthesize(tmp_path / "still", options)
    # 10 still frames in front of the 4 of the flight (the flight starts at frame 10).
    assert len(result.frame_timestamps_ns) == 14
    gt = open_sequence(tmp_path / "still").ground_truth
    start = result.frame_timestamps_ns[10]
    still = gt.timestamps_ns <= start
    assert still.sum() == 40 + 100 + 1  # the 0.2 s IMU lead-in, the 0.5 s standstill, t = 0
    np.testing.assert_array_equal(
        gt.poses[still], np.broadcast_to(gt.poses[0], gt.poses[still].shape)
    )
    assert gt.velocities is not None and np.abs(gt.velocities[still]).max() == 0.0
    # The IMU reads only its bias and noise there: the mean rate minus the bias is noise.
    imu = open_sequence(tmp_path / "still").imu
    assert imu is not None and gt.gyro_bias is not None
    at_rest = imu.timestamps_ns <= start
    noise = ImuNoise()
    sigma_mean = noise.gyro_noise_density * np.sqrt(noise.rate_hz) / np.sqrt(at_rest.sum())
    residual = (imu.gyro[at_rest] - gt.gyro_bias[still]).mean(axis=0)
    assert np.abs(residual).max() < 5 * sigma_mean
    # Then it moves, and the velocity column stays the derivative of the positions.
    moving = ~still
    assert np.linalg.norm(gt.poses[-1, :3, 3] - gt.poses[0, :3, 3]) > 0.02
    dt = np.diff(gt.timestamps_ns[moving]) * 1e-9
    finite = np.diff(gt.poses[moving, :3, 3], axis=0) / dt[:, None]
    mid = 0.5 * (gt.velocities[moving][1:] + gt.velocities[moving][:-1])
    np.testing.assert_allclose(finite, mid, atol=2e-3)
