"""The accelerometer's three-frame inertial factor, and what it gives the fusion graph."""

from __future__ import annotations

import itertools
from dataclasses import replace

import gtsam
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from estimator.backend import FusionBackend
from estimator.backend.imu import GRAVITY, preintegrate_specific_force
from estimator.backend.inertial import (
    InertialTerms,
    inertial_factor,
    inertial_factor_sigma,
    predict_position,
    velocity_change_error,
)
from estimator.config import BackendConfig
from estimator.geometry import invert_pose
from estimator.rendered.scenario import (
    CAMERA_MOUNT,
    PERFECT_IMU,
    FrontendMeasurement,
    aligned_ate,
    simulate_frontend,
    smooth_trajectory,
)
from estimator.types import ImuBatch, ImuNoise

BODY_FROM_CAMERA = CAMERA_MOUNT
DOWN = np.array([0.0, 0.0, -GRAVITY])


def _deltas(scenario, accel_bias=(0.0, 0.0, 0.0)):
    """Specific force preintegrated over every frame interval of a scenario."""
    imu = scenario.imu
    accel = imu.accel + np.asarray(accel_bias)
    return [None] + [
        preintegrate_specific_force(imu.timestamps_ns, imu.gyro, accel, int(a), int(b))
        for a, b in itertools.pairwise(scenario.timestamps_ns)
    ]


def test_error_vanishes_on_the_true_trajectory_and_sees_gravity_and_bias():
    scenario = smooth_trajectory(40, seed=3, noise=PERFECT_IMU, initial_bias=(0.0, 0.0, 0.0))
    poses = scenario.body_poses
    deltas = _deltas(scenario)
    errors = np.array(
        [
            velocity_change_error(
                InertialTerms.of(deltas[k - 1], deltas[k]), *poses[k - 2 : k + 1], DOWN, np.zeros(3)
            )[0]
            for k in range(2, len(poses))
        ]
    )
    # Exact up to the 200 Hz Euler integration of a smooth trajectory: below the 1 mm/s floor
    # of the factor's sigma, and far below a gravity mistake (9.81 m/s^2 x 50 ms = 0.49 m/s).
    assert np.abs(errors).max() < 1e-3
    tilted = Rotation.from_rotvec([0.01, 0.0, 0.0]).apply(DOWN)  # 10 mrad off
    k = 20
    off = velocity_change_error(
        InertialTerms.of(deltas[k - 1], deltas[k]), *poses[k - 2 : k + 1], tilted, np.zeros(3)
    )
    assert np.linalg.norm(off[0]) > 0.5 * 0.01 * GRAVITY * 0.05
    # A bias in the accelerometer is undone by the same bias in the model (to first order),
    # and is visible without it (about |b| x 50 ms).
    bias = np.array([0.05, -0.08, 0.03])
    biased = _deltas(scenario, bias)
    window = poses[k - 2 : k + 1]
    with_bias = velocity_change_error(
        InertialTerms.of(biased[k - 1], biased[k]), *window, DOWN, bias
    )[0]
    without = velocity_change_error(
        InertialTerms.of(biased[k - 1], biased[k]), *window, DOWN, 0 * bias
    )[0]
    assert np.abs(with_bias - errors[k - 2]).max() < 1e-4
    assert np.linalg.norm(without - errors[k - 2]) > 0.8 * np.linalg.norm(bias) * 0.05


def test_jacobians_match_finite_differences_and_prediction_zeroes_the_error():
    scenario = smooth_trajectory(10, seed=4)
    deltas = _deltas(scenario)
    rng = np.random.default_rng(0)
    # Poses away from the truth, so that every term of the Jacobians matters.
    poses = [
        gtsam.Pose3(p).retract(rng.normal(0.0, 0.02, 6)).matrix() for p in scenario.body_poses[3:6]
    ]
    gravity, bias = DOWN + rng.normal(0, 0.1, 3), rng.normal(0, 0.05, 3)
    args = (InertialTerms.of(deltas[4], deltas[5]),)
    error, jacobians = velocity_change_error(*args, *poses, gravity, bias)
    eps = 1e-6
    for slot in range(3):
        numeric = np.zeros((3, 6))
        for axis in range(6):
            step = np.zeros(6)
            step[axis] = eps
            moved = list(poses)
            moved[slot] = gtsam.Pose3(poses[slot]).retract(step).matrix()
            numeric[:, axis] = (
                velocity_change_error(*args, *moved, gravity, bias)[0] - error
            ) / eps
        np.testing.assert_allclose(jacobians[slot], numeric, atol=2e-4)
    for slot, base in ((3, gravity), (4, bias)):
        numeric = np.zeros((3, 3))
        for axis in range(3):
            moved = base.copy()
            moved[axis] += eps
            values = (moved, bias) if slot == 3 else (gravity, moved)
            numeric[:, axis] = (velocity_change_error(*args, *poses, *values)[0] - error) / eps
        np.testing.assert_allclose(jacobians[slot], numeric, atol=1e-6)
    # The GTSAM factor reports the same error, and the prediction zeroes it.
    keys = [gtsam.symbol("x", i) for i in range(3)]
    values = gtsam.Values()
    for key, pose in zip(keys, poses, strict=True):
        values.insert(key, gtsam.Pose3(pose))
    values.insert(gtsam.symbol("g", 0), gravity)
    values.insert(gtsam.symbol("a", 0), bias)
    factor = inertial_factor(
        tuple(keys), gtsam.symbol("g", 0), gtsam.symbol("a", 0), *args, sigma=1.0
    )
    np.testing.assert_allclose(factor.unwhitenedError(values), error, atol=1e-12)
    predicted = poses[2].copy()
    predicted[:3, 3] = predict_position(*args, poses[0], poses[1], gravity, bias)
    assert (
        np.abs(velocity_change_error(*args, poses[0], poses[1], predicted, gravity, bias)[0]).max()
        < 1e-9
    )
    sigma = inertial_factor_sigma(*args, 2e-3)
    assert sigma == pytest.approx(2e-3 * np.sqrt(0.1 / 3.0), rel=1e-6)


def _drive(scenario, measurements, config, accel_bias, references=None):
    """Run the back end; ``references`` maps a frame to the earlier frame it was measured
    against (default: the previous frame)."""
    references = references or {}
    backend = FusionBackend(config, BODY_FROM_CAMERA, ImuNoise())
    stamps = scenario.timestamps_ns
    imu = ImuBatch(scenario.imu.timestamps_ns, scenario.imu.gyro, scenario.imu.accel + accel_bias)
    out, final = [], []
    for k, measurement in enumerate(measurements):
        start = stamps[k - 1] if k else stamps[0] - 10**9
        estimate = backend.add_frame(
            int(stamps[k]),
            None if k == 0 else measurement.relative_pose,
            measurement.residuals,
            measurement.inlier_count,
            imu.between(int(start), int(stamps[k])),
            reference_ns=int(stamps[references[k]]) if k in references else None,
        )
        out.append(estimate)
        final += estimate.final_poses
    final += backend.flush()
    return out, final


def _gap_errors(estimates, truth, gap):
    """Position error (m) of each gap frame, in the frame of the last pose before the gap."""
    before = gap[0] - 1
    errors = []
    for k in gap:
        motion = invert_pose(estimates[before]) @ estimates[k]
        true_motion = invert_pose(truth[before]) @ truth[k]
        errors.append(np.linalg.norm(motion[:3, 3] - true_motion[:3, 3]))
    return np.array(errors)


@pytest.fixture(scope="module")
def gap_runs():
    """100 frames (5 s) of simulated vision (about 1 mm of translation noise per frame, like
    the rendered front end's) with a 6-frame gap at 70-75 and a 0.058 m/s^2 accelerometer
    bias, with and without the accelerometer."""
    scenario = smooth_trajectory(100, seed=11)
    measurements = simulate_frontend(
        scenario.body_poses, BODY_FROM_CAMERA, seed=12, point_sigma_m=0.01
    )
    gap = range(70, 76)
    for k in gap:
        measurements[k] = FrontendMeasurement(None, None, 0, "failed")
    # As a keyframe front end would: the frame after the gap is measured against the last
    # frame before it (the true motion with the noise of frame 76's own measurement).
    camera = scenario.body_poses @ BODY_FROM_CAMERA
    noise = invert_pose(invert_pose(camera[75]) @ camera[76]) @ measurements[76].relative_pose
    measurements[76] = replace(
        measurements[76], relative_pose=invert_pose(camera[69]) @ camera[76] @ noise
    )
    bias = np.array([0.04, -0.03, 0.03])
    runs = {
        accel: _drive(
            scenario, measurements, BackendConfig(use_accelerometer=accel), bias, {76: 69}
        )
        for accel in (True, False)
    }
    return scenario, gap, bias, runs


def test_accelerometer_carries_translation_through_a_vision_gap(gap_runs):
    scenario, gap, _, runs = gap_runs
    online = {
        accel: _gap_errors([e.body_pose for e in out], scenario.body_poses, gap)
        for accel, (out, _) in runs.items()
    }
    # Constant velocity through 0.3 s of accelerating motion drifts by centimetres (31 mm
    # measured); the accelerometer keeps the gap frames within about a millimetre (1.2 mm).
    assert online[False].max() > 0.02
    assert online[True].max() < 0.15 * online[False].max()
    assert online[True].max() < 0.003


def test_gravity_is_estimated(gap_runs):
    scenario, _, _, runs = gap_runs
    out, _ = runs[True]
    # The world is the first body pose levelled from its (moving) accelerometer: its gravity
    # is the true one rotated into it, here about 1 m/s^2 (6 deg) away from -z.
    world_from_truth = out[0].body_pose @ invert_pose(scenario.body_poses[0])
    true_gravity = world_from_truth[:3, :3] @ DOWN
    initial_error = np.linalg.norm(true_gravity - DOWN)
    assert initial_error > 0.5
    # Measured 0.06 m/s^2 after 5 s (0.35 deg); the bias (0.058 m/s^2 here) is weakly
    # observable in so short a run and is not asserted.
    assert np.linalg.norm(out[-1].gravity - true_gravity) < min(0.1, 0.1 * initial_error)
    assert runs[False][0][-1].gravity is None


def test_smoothed_output_lists_every_frame_once_and_beats_the_online_answers(gap_runs):
    scenario, _, _, runs = gap_runs
    out, final = runs[True]
    stamps = [stamp for stamp, _ in final]
    assert stamps == [int(t) for t in scenario.timestamps_ns]  # each frame once, in order
    smoothed = np.stack([pose for _, pose in final]) @ invert_pose(BODY_FROM_CAMERA)
    online = np.stack([e.body_pose for e in out])
    # Later frames revise earlier ones (measured: ATE 4.4 mm smoothed vs 5.8 mm online).
    assert aligned_ate(smoothed, scenario.body_poses) < 0.9 * aligned_ate(
        online, scenario.body_poses
    )
    # The newest frame has no later information: its final pose is its online one.
    np.testing.assert_allclose(smoothed[-1], online[-1], atol=1e-12)


def test_real_clip_fused_bridges_black_frames_close_to_vision(euroc_mh01_moving) -> None:
    """The real MH_01 clip with every 10th frame black, default configuration: fused with the
    real IMU it stays within 1.5 mm of vision alone (measured: 3.9 against 2.8 mm; the fused run
    being no worse at all is still open). The gap frame's position is corrected by the next
    frame's measurement; left at a stale linearisation point it bent the gravity and
    accelerometer-bias estimates (the inertial factor sees 1 mm as ~20 mm/s) once marginalised:
    55 mm fused against 6 mm vision alone.
    """
    import warnings

    from estimator.bench.perturbations import run_one
    from estimator.formats.datasets import open_sequence

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # unpaired camera rows of the recording
        sequence = open_sequence(euroc_mh01_moving)
        vision, fused = (
            run_one(sequence, "black every 10th", "default", mode, limit=70)["ate_rmse_m"]
            for mode in ("vision", "fused")
        )
    assert fused <= vision + 1.5e-3, f"fused {fused * 1e3:.1f} mm > vision {vision * 1e3:.1f} mm"


def test_the_factors_own_skew_matrix_is_geometrys_to_the_bit() -> None:
    """The inertial factor builds its cross-product matrices itself (hot path); they must be
    ``geometry.skew``'s exactly, signed zeros included."""
    from estimator.backend.inertial import _skew
    from estimator.geometry import skew

    rng = np.random.default_rng(8)
    vectors = [rng.normal(size=3), np.zeros(3), np.array([-0.0, 1.5, -2.0])]
    vectors.append(np.array([3.0, 0.0, -0.0]))
    for vector in vectors:
        assert _skew(vector).tobytes() == skew(vector).tobytes()
