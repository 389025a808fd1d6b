"""The fusion graph driven by simulated relative poses and a simulated IMU."""

from __future__ import annotations

import json

import gtsam
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from estimator.backend import FusedEstimate, FusionBackend
from estimator.backend.noise import fit_covariance, relative_pose_sigmas
from estimator.cli.main import main
from estimator.config import BackendConfig
from estimator.geometry import invert_pose, kabsch, make_pose, rotation_angle_deg
from estimator.rendered.scenario import (
    CAMERA_MOUNT,
    PERFECT_IMU,
    FrontendMeasurement,
    aligned_ate,
    chain,
    simulate_frontend,
    smooth_trajectory,
)
from estimator.types import FrameStatus, ImuBatch, ImuNoise

BODY_FROM_CAMERA = CAMERA_MOUNT


def _run(
    scenario,
    measurements: list[FrontendMeasurement],
    config: BackendConfig,
    imu: bool = True,
    imu_noise: ImuNoise | None = None,
    imu_time_shift_ns: int = 0,
) -> list[FusedEstimate]:
    backend = FusionBackend(config, BODY_FROM_CAMERA, (imu_noise or ImuNoise()) if imu else None)
    stamps = scenario.timestamps_ns
    shifted = ImuBatch(
        scenario.imu.timestamps_ns + imu_time_shift_ns, scenario.imu.gyro, scenario.imu.accel
    )
    out = []
    for k, measurement in enumerate(measurements):
        start = stamps[k - 1] if k else stamps[0] - 10**9
        batch = shifted.between(int(start) + imu_time_shift_ns, int(stamps[k]) + imu_time_shift_ns)
        out.append(
            backend.add_frame(
                int(stamps[k]),
                None if k == 0 else measurement.relative_pose,
                measurement.residuals,
                measurement.inlier_count,
                batch if imu else None,
            )
        )
    return out


def _perfect_measurements(poses: np.ndarray) -> list[FrontendMeasurement]:
    camera = poses @ BODY_FROM_CAMERA
    relative = invert_pose(camera[:-1]) @ camera[1:]
    residuals = np.full(150, 0.02)
    return [FrontendMeasurement(np.eye(4), None, 0, "first")] + [
        FrontendMeasurement(r, residuals, 150, "good") for r in relative
    ]


def _relative_to_first(poses: np.ndarray) -> np.ndarray:
    return invert_pose(poses[0]) @ poses


def _poses(estimates: list[FusedEstimate]) -> np.ndarray:
    return np.stack([e.pose for e in estimates])


@pytest.mark.parametrize("smoother", ["fixed-lag", "isam2"])
def test_perfect_inputs_are_recovered_exactly_without_imu(smoother):
    scenario = smooth_trajectory(60, seed=1)
    truth = scenario.body_poses @ BODY_FROM_CAMERA
    out = _run(
        scenario,
        _perfect_measurements(scenario.body_poses),
        BackendConfig(smoother=smoother),
        imu=False,
    )
    assert all(e.status is FrameStatus.OK for e in out)
    np.testing.assert_allclose(
        _relative_to_first(_poses(out)), _relative_to_first(truth), atol=1e-6
    )
    # The camera pose is the body pose moved by the extrinsic.
    np.testing.assert_allclose(out[-1].pose, out[-1].body_pose @ BODY_FROM_CAMERA, atol=1e-12)


def test_perfect_inputs_are_recovered_with_a_perfect_imu():
    scenario = smooth_trajectory(60, seed=1, noise=PERFECT_IMU, initial_bias=(0.0, 0.0, 0.0))
    truth = _relative_to_first(scenario.body_poses @ BODY_FROM_CAMERA)
    out = _run(scenario, _perfect_measurements(scenario.body_poses), BackendConfig())
    estimate = _relative_to_first(_poses(out))
    # Exact up to the gyro's trapezoidal integration (~0.004 deg per frame on this motion).
    assert (
        rotation_angle_deg(np.swapaxes(estimate[:, :3, :3], 1, 2) @ truth[:, :3, :3]).max() < 0.02
    )
    assert np.abs(estimate[:, :3, 3] - truth[:, :3, 3]).max() < 1e-3
    assert np.abs(out[-1].gyro_bias).max() < 1e-3


def test_world_is_gravity_aligned_from_the_first_accelerometer_batch():
    tilt = Rotation.from_euler("ZYX", [0.4, -0.15, 0.25]).as_matrix()  # yaw, pitch, roll
    force = tilt.T @ np.array([0.0, 0.0, 9.81])
    backend = FusionBackend(BackendConfig(), BODY_FROM_CAMERA, ImuNoise())
    static = ImuBatch(
        np.arange(-200, 1, 5, dtype=np.int64) * 1_000_000,
        np.zeros((41, 3)),
        np.tile(force, (41, 1)),
    )
    first = backend.add_frame(0, None, None, 0, static)
    assert "gravity-aligned" in first.message
    yaw, pitch, roll = Rotation.from_matrix(first.body_pose[:3, :3]).as_euler("ZYX")
    assert (pitch, roll) == pytest.approx((-0.15, 0.25), abs=1e-6)
    assert yaw == pytest.approx(0.0, abs=1e-9)


def test_one_grossly_wrong_relative_pose_does_not_tear_the_trajectory():
    scenario = smooth_trajectory(80, seed=4)
    measurements = simulate_frontend(scenario.body_poses, BODY_FROM_CAMERA, seed=5)
    bad = measurements[40]
    wrong = bad.relative_pose @ make_pose(
        Rotation.from_rotvec([0.0, 0.3, 0.0]).as_matrix(), [0.5, -0.3, 0.2]
    )
    measurements[40] = FrontendMeasurement(wrong, bad.residuals, bad.inlier_count, "gross")
    truth = scenario.body_poses @ BODY_FROM_CAMERA
    # Only the robust kernel (no gate; the motion prior on every frame gives the translation
    # something to disagree with) against plain least squares.
    robust = _run(
        scenario, measurements, BackendConfig(outlier_gate_chi2=None, motion_prior="always")
    )
    plain = _run(
        scenario,
        measurements,
        BackendConfig(outlier_gate_chi2=None, motion_prior="always", robust_kernel="none"),
    )
    robust_ate = aligned_ate(_poses(robust), truth)
    plain_ate = aligned_ate(_poses(plain), truth)
    assert robust_ate < 0.05, robust_ate
    assert plain_ate > 3 * robust_ate, (plain_ate, robust_ate)
    # With the gate (default) the frame is rejected outright and reported as degraded.
    gated = _run(scenario, measurements, BackendConfig())
    assert gated[40].status is FrameStatus.DEGRADED
    assert "rejected" in gated[40].message
    assert aligned_ate(_poses(gated), truth) < 0.05


def test_frames_without_vision_advance_with_the_imu():
    scenario = smooth_trajectory(60, seed=6)
    measurements = simulate_frontend(scenario.body_poses, BODY_FROM_CAMERA, seed=7)
    gap = range(30, 40)
    for k in gap:
        measurements[k] = FrontendMeasurement(None, None, 0, "failed")
    out = _run(scenario, measurements, BackendConfig())
    assert [out[k].status for k in gap] == [FrameStatus.DEGRADED] * len(gap)
    truth = scenario.body_poses
    # Rotation through the gap follows the gyro, translation keeps moving.
    before, after = out[29].body_pose, out[39].body_pose
    true_motion = invert_pose(truth[29]) @ truth[39]
    motion = invert_pose(before) @ after
    assert rotation_angle_deg(motion[:3, :3].T @ true_motion[:3, :3]) < 0.3
    true_moved = np.linalg.norm(true_motion[:3, 3])
    assert true_moved > 0.2  # the test motion is real
    # Constant velocity over 0.5 s of accelerating motion: much closer than standing still.
    assert np.linalg.norm(motion[:3, 3] - true_motion[:3, 3]) < 0.4 * true_moved


@pytest.mark.parametrize("imu_configured", [False, True])
def test_frames_without_vision_or_imu_are_lost_then_reconnect(imu_configured):
    scenario = smooth_trajectory(40, seed=8)
    measurements = simulate_frontend(scenario.body_poses, BODY_FROM_CAMERA, seed=9)
    for k in range(15, 20):
        measurements[k] = FrontendMeasurement(None, None, 0, "failed")
    backend = FusionBackend(
        BackendConfig(), BODY_FROM_CAMERA, ImuNoise() if imu_configured else None
    )
    out = [
        backend.add_frame(
            int(t), None if k == 0 else m.relative_pose, m.residuals, m.inlier_count, None
        )  # no IMU batches at all
        for k, (t, m) in enumerate(zip(scenario.timestamps_ns, measurements, strict=True))
    ]
    assert [o.status for o in out[15:20]] == [FrameStatus.LOST] * 5
    assert all(o.status is FrameStatus.OK for o in out[20:])
    poses = _poses(out)
    assert np.all(np.isfinite(poses))
    # After reconnecting, consecutive fused motions follow the front end again.
    for k in range(21, 40):
        fused = invert_pose(poses[k - 1]) @ poses[k]
        measured = measurements[k].relative_pose
        assert np.linalg.norm(fused[:3, 3] - measured[:3, 3]) < 0.02


@pytest.mark.parametrize("imu", [True, False])
@pytest.mark.parametrize("vision_across_gap", [True, False])
def test_a_frame_gap_longer_than_the_smoother_lag_is_bridged(imu, vision_across_gap):
    # Frames 11..39 never arrive: 1.5 s between two frames, longer than the 1 s lag, so the
    # previous frame's variables fall out of the window in the update that needs them.
    scenario = smooth_trajectory(60, seed=21)
    kept = [*range(11), *range(40, 60)]
    stamps = scenario.timestamps_ns[kept]
    assert (stamps[11] - stamps[10]) * 1e-9 > BackendConfig().smoother_lag_s
    camera = scenario.body_poses[kept] @ BODY_FROM_CAMERA
    relative = invert_pose(camera[:-1]) @ camera[1:]
    backend = FusionBackend(BackendConfig(), BODY_FROM_CAMERA, ImuNoise() if imu else None)
    out = []
    for j, stamp in enumerate(stamps):
        start = stamps[j - 1] if j else stamp - 10**8
        measured = None if j == 0 or (j == 11 and not vision_across_gap) else relative[j - 1]
        out.append(
            backend.add_frame(
                int(stamp),
                measured,
                np.full(150, 0.02) if measured is not None else None,
                150 if measured is not None else 0,
                scenario.imu.between(int(start), int(stamp)) if imu else None,
            )
        )
    poses = _poses(out)
    assert np.all(np.isfinite(poses))
    # Every frame gets its final (smoothed) estimate exactly once, across the gap too.
    final = [pose for estimate in out for pose in estimate.final_poses] + list(backend.flush())
    assert [stamp for stamp, _ in final] == [int(stamp) for stamp in stamps]
    assert np.all(np.isfinite(np.stack([pose for _, pose in final])))
    truth = _relative_to_first(camera)
    error = np.linalg.norm(_relative_to_first(poses)[:, :3, 3] - truth[:, :3, 3], axis=1)
    assert error[:11].max() < 1e-3
    if vision_across_gap:
        # The long-baseline measurement passes the gate (its spread grows with the interval)
        # and the trajectory goes on where it truly is.
        assert all(o.status is FrameStatus.OK for o in out)
        assert error.max() < 2e-3
    else:
        assert out[11].status is (FrameStatus.DEGRADED if imu else FrameStatus.LOST)
        assert all(o.status is FrameStatus.OK for o in out[12:])
        if imu:  # the gyro carries the rotation over the gap
            across = invert_pose(poses[10]) @ poses[11]
            assert rotation_angle_deg(across[:3, :3].T @ relative[10][:3, :3]) < 0.5
        # After the gap, consecutive fused motions follow the measurements again.
        for j in range(13, len(kept)):
            fused = invert_pose(poses[j - 1]) @ poses[j]
            assert np.linalg.norm(fused[:3, 3] - relative[j - 1][:3, 3]) < 0.02


def test_imu_time_offset_is_applied():
    scenario = smooth_trajectory(60, seed=10, noise=PERFECT_IMU, initial_bias=(0.0, 0.0, 0.0))
    measurements = [
        FrontendMeasurement(None, None, 0, "failed") if k else m
        for k, m in enumerate(_perfect_measurements(scenario.body_poses))
    ]
    shift = 30_000_000  # the IMU clock runs 30 ms ahead of the camera clock
    truth = _relative_to_first(scenario.body_poses)

    def rotation_error(offset_s: float) -> float:
        out = _run(
            scenario,
            measurements,
            BackendConfig(imu_time_offset_s=offset_s),
            imu_time_shift_ns=shift,
        )
        estimate = _relative_to_first(np.stack([o.body_pose for o in out]))
        return float(rotation_angle_deg(estimate[-1, :3, :3].T @ truth[-1, :3, :3]))

    assert rotation_error(0.03) < 0.05
    assert rotation_error(0.0) > 5 * max(rotation_error(0.03), 0.01)


def test_twenty_percent_broken_frames_fused_beats_front_end_by_30_percent():
    scenario = smooth_trajectory(300, seed=11)
    measurements = simulate_frontend(
        scenario.body_poses, BODY_FROM_CAMERA, seed=12, broken_fraction=0.2
    )
    truth = scenario.body_poses @ BODY_FROM_CAMERA
    out = _run(scenario, measurements, BackendConfig())
    fused = aligned_ate(_poses(out), truth)
    relative = [m.relative_pose for m in measurements]
    frontend = min(aligned_ate(chain(relative, hold=h), truth) for h in (True, False))
    assert not any(o.status is FrameStatus.LOST for o in out)
    assert fused < 0.7 * frontend, (fused, frontend)


def test_same_inputs_give_the_same_output():
    scenario = smooth_trajectory(50, seed=13)
    measurements = simulate_frontend(
        scenario.body_poses, BODY_FROM_CAMERA, seed=14, broken_fraction=0.2
    )
    first = _poses(_run(scenario, measurements, BackendConfig()))
    second = _poses(_run(scenario, measurements, BackendConfig()))
    np.testing.assert_array_equal(first, second)


def test_fewer_inliers_and_larger_residuals_mean_larger_sigmas():
    config = BackendConfig()
    residuals = np.full(200, 0.05)
    many = relative_pose_sigmas(residuals, 200, config)
    few = relative_pose_sigmas(residuals[:20], 20, config)
    worse = relative_pose_sigmas(residuals * 3, 200, config)
    assert few[0] > many[0] and few[1] > many[1]
    assert worse[0] > many[0] and worse[1] > many[1]
    tiny = relative_pose_sigmas(np.full(10_000, 1e-6), 10_000, config)
    assert tiny == (config.min_rotation_sigma_rad, config.min_translation_sigma_m)
    huge = relative_pose_sigmas(np.full(3, 50.0), 3, config)
    assert huge == (config.max_rotation_sigma_rad, config.max_translation_sigma_m)
    with pytest.raises(ValueError, match="NaN"):
        relative_pose_sigmas(np.array([np.nan]), 1, config)


def test_bad_inputs_raise_clear_errors():
    backend = FusionBackend(BackendConfig(), np.eye(4), None)
    backend.add_frame(100, None, None, 0, None)
    with pytest.raises(ValueError, match="4x4"):
        backend.add_frame(200, np.eye(3), None, 10, None)
    with pytest.raises(ValueError, match="NaN"):
        backend.add_frame(200, np.full((4, 4), np.nan), None, 10, None)
    with pytest.raises(ValueError, match="increase"):
        backend.add_frame(100, np.eye(4), None, 10, None)
    with pytest.raises(ValueError, match="inlier_count"):
        backend.add_frame(200, np.eye(4), None, -1, None)
    with pytest.raises(ValueError, match="rotation"):
        FusionBackend(BackendConfig(), np.diag([1.0, 1.0, -1.0, 1.0]), None)
    override = BackendConfig(body_from_camera=list(BODY_FROM_CAMERA.ravel()))
    assert np.allclose(FusionBackend(override, np.eye(4), None).body_from_camera, BODY_FROM_CAMERA)


@pytest.mark.parametrize("imu", [False, True])
def test_a_numerical_failure_inside_gtsam_restarts_the_graph_instead_of_crashing(imu):
    scenario = smooth_trajectory(20, seed=15)
    measurements = simulate_frontend(scenario.body_poses, BODY_FROM_CAMERA, seed=16)
    backend = FusionBackend(BackendConfig(), BODY_FROM_CAMERA, ImuNoise() if imu else None)
    stamps = scenario.timestamps_ns

    class Failing:
        """The real smoother, except that its next update fails."""

        def __init__(self, smoother):
            self.smoother = smoother

        def update(self, *args, **kwargs):
            raise RuntimeError("Indeterminant linear system detected (simulated)")

        def __getattr__(self, name):
            return getattr(self.smoother, name)

    out = []
    for k, m in enumerate(measurements):
        if k == 10:
            backend.smoother.graph = Failing(backend.smoother.graph)
        out.append(
            backend.add_frame(
                int(stamps[k]),
                None if k == 0 else m.relative_pose,
                m.residuals,
                m.inlier_count,
                scenario.imu.between(int(stamps[k - 1] if k else stamps[0] - 10**8), int(stamps[k]))
                if imu
                else None,
            )
        )
    assert "restarted" in out[10].message
    assert all(o.status is FrameStatus.OK for o in out[11:])
    truth = scenario.body_poses @ BODY_FROM_CAMERA
    assert aligned_ate(_poses(out), truth) < 0.05
    # The frames the failed graph held are still finished, once each, with their last estimate.
    final = [pose for estimate in out for pose in estimate.final_poses] + list(backend.flush())
    assert [stamp for stamp, _ in final] == [int(stamp) for stamp in stamps]


def test_bench_backend_simulated_part_writes_its_tables(tmp_path, capsys):
    code = main(
        [
            "bench",
            "backend",
            "--parts",
            "simulated",
            "--frames",
            "40",
            "--isam2-frames",
            "20",
            "--out",
            str(tmp_path),
        ]
    )
    assert code == 0
    result = json.loads((tmp_path / "backend.json").read_text())
    cases = result["simulated"]["cases"]
    assert set(cases) == {"broken_0.00", "broken_0.20"}
    assert "fixed-lag, IMU" in cases["broken_0.20"]
    assert "ATE m" in capsys.readouterr().out
    assert main(["bench", "backend", "--frames", "3", "--out", str(tmp_path)]) == 2


@pytest.mark.slow
def test_bench_backend_pipeline_tabulates_each_seed(tmp_path, capsys):
    args = ["bench", "backend", "--parts", "pipeline", "--rendered-frames", "12"]
    args += ["--data", str(tmp_path / "data"), "--euroc-micro", str(tmp_path / "none")]
    assert main([*args, "--seeds", "0-1", "--out", str(tmp_path)]) == 0
    result = json.loads((tmp_path / "backend.json").read_text())["pipeline"]
    rows = result["seeds"]
    assert {"0", "1"} <= set(rows)
    for row in (rows["0"], rows["1"]):
        assert set(row["ate_m"]) == {"frontend_pose", "pose", "smoothed"}
        assert all(np.isfinite(value) for value in row["ate_m"].values())
    assert 0 <= rows["online_met"] <= 2
    assert "fused smoothed, IMU" in result["rendered, 20 % broken"]
    assert "fused smoothed mm" in capsys.readouterr().out
    with pytest.raises(SystemExit):
        main([*args, "--seeds", "3-1", "--out", str(tmp_path)])


# ----------------------------------------------------------------------------- fit covariance


def _points_in_view(rng: np.random.Generator, count: int) -> np.ndarray:
    """Points 3-7 m in front of a camera (z forward), like a stereo front end's inliers."""
    return np.column_stack(
        [rng.uniform(-2, 2, count), rng.uniform(-1.5, 1.5, count), rng.uniform(3, 7, count)]
    )


def _fit(rng: np.random.Generator, true: np.ndarray, count: int = 80, noise: float = 0.01):
    """A noisy rigid fit p ~ T q: (estimated T, residual norms, current-frame points)."""
    points = _points_in_view(rng, count)
    target = points @ true[:3, :3].T + true[:3, 3] + rng.normal(0.0, noise, (count, 3))
    rotation, translation = kabsch(points, target)
    residuals = np.linalg.norm(target - (points @ rotation.T + translation), axis=1)
    return make_pose(rotation, translation), residuals, points


def test_fit_covariance_matches_monte_carlo_fits():
    rng = np.random.default_rng(3)
    true = make_pose(Rotation.from_rotvec([0.02, -0.05, 0.01]).as_matrix(), [0.05, 0.01, 0.1])
    config = BackendConfig(fit_min_rotation_sigma_rad=0.0, fit_min_translation_sigma_m=0.0)
    points = _points_in_view(rng, 120)
    clean = points @ true[:3, :3].T + true[:3, 3]
    errors, covariances = [], []
    for _ in range(400):
        target = clean + rng.normal(0.0, 0.01, clean.shape)
        rotation, translation = kabsch(points, target)
        error = invert_pose(true) @ make_pose(rotation, translation)
        errors.append(gtsam.Pose3.Logmap(gtsam.Pose3(error)))
        residuals = np.linalg.norm(target - (points @ rotation.T + translation), axis=1)
        covariances.append(fit_covariance(points, residuals, config))
    empirical, model = np.cov(np.array(errors).T), np.mean(covariances, axis=0)
    sigma_e, sigma_m = np.sqrt(np.diag(empirical)), np.sqrt(np.diag(model))
    np.testing.assert_allclose(sigma_e, sigma_m, rtol=0.12)
    # Pitch/yaw errors come with the lever-arm translation error: ~95 % correlated.
    correlation_e = empirical / np.outer(sigma_e, sigma_e)
    correlation_m = model / np.outer(sigma_m, sigma_m)
    assert abs(correlation_m[0, 4]) > 0.9 and abs(correlation_m[1, 3]) > 0.9
    np.testing.assert_allclose(correlation_e, correlation_m, atol=0.1)


def test_full_fit_covariance_lets_the_gyro_correct_the_translation_too():
    # Correlated fit errors (rotation with its lever-arm translation) and a gyro with a known
    # bias: the gyro fixes the rotation, and only the full covariance also moves the
    # translation back; with sigmas alone the translation keeps its share of the error.
    scenario = smooth_trajectory(150, seed=1, initial_bias=(0.0, 0.0, 0.0))
    camera = scenario.body_poses @ BODY_FROM_CAMERA
    rng = np.random.default_rng(101)
    fits = [_fit(rng, invert_pose(camera[k - 1]) @ camera[k]) for k in range(1, len(camera))]
    config = BackendConfig(gyro_bias_prior_sigma=1e-4)
    ate = {}
    for with_points in (True, False):
        backend = FusionBackend(config, BODY_FROM_CAMERA, ImuNoise())
        stamps, poses = scenario.timestamps_ns, []
        for k, stamp in enumerate(stamps):
            start = stamps[k - 1] if k else stamp - 10**8
            batch = scenario.imu.between(int(start), int(stamp))
            if k == 0:
                poses.append(backend.add_frame(int(stamp), None, None, 0, batch).pose)
                continue
            pose, residuals, points = fits[k - 1]
            out = backend.add_frame(
                int(stamp),
                pose,
                residuals,
                len(residuals),
                batch,
                inlier_points=points if with_points else None,
            )
            poses.append(out.pose)
        ate[with_points] = aligned_ate(np.stack(poses), camera)
    frontend = aligned_ate(chain([np.eye(4)] + [fit[0] for fit in fits], hold=True), camera)
    assert ate[True] < 0.5 * frontend, (ate, frontend)
    assert ate[True] < 0.6 * ate[False], (ate, frontend)


# ----------------------------------------------------------------------------- keyframes


def _keyframe_run(poses, stamps, reference_of, config: BackendConfig):
    """Perfect keyframe measurements: frame k measured against frame ``reference_of(k)``."""
    camera = poses @ BODY_FROM_CAMERA
    backend = FusionBackend(config, BODY_FROM_CAMERA, None)
    out = [backend.add_frame(int(stamps[0]), None, None, 0, None)]
    for k in range(1, len(stamps)):
        reference = reference_of(k)
        out.append(
            backend.add_frame(
                int(stamps[k]),
                invert_pose(camera[reference]) @ camera[k],
                np.full(150, 0.02),
                150,
                None,
                reference_ns=int(stamps[reference]),
            )
        )
    return out


@pytest.mark.parametrize("span", [2, 3])
def test_keyframe_measurements_are_tied_to_their_reference(span):
    # Inverse and product of the same poses fed back as initial values: orthonormal only to
    # rounding, a deviation that compounded from frame to frame until the graph diverged.
    scenario = smooth_trajectory(120, seed=23)
    out = _keyframe_run(
        scenario.body_poses,
        scenario.timestamps_ns,
        lambda k: (k - 1) // span * span,  # the last multiple of span before k
        BackendConfig(),
    )
    truth = _relative_to_first(scenario.body_poses @ BODY_FROM_CAMERA)
    error = _relative_to_first(_poses(out))[:, :3, 3] - truth[:, :3, 3]
    assert np.abs(error).max() < 1e-6
    assert all(o.status is FrameStatus.OK for o in out)


def test_a_reference_older_than_the_lag_is_reached_through_its_last_estimate():
    # The reference (30 frames = 1.5 s back) has left the window: the measurement is chained
    # through the previous frame with the reference's remembered pose, and stays exact.
    scenario = smooth_trajectory(80, seed=24)
    camera = scenario.body_poses @ BODY_FROM_CAMERA
    out = _keyframe_run(
        scenario.body_poses,
        scenario.timestamps_ns,
        lambda k: 10 if 10 < k < 45 else k - 1,  # frames 11..44 are measured against 10
        BackendConfig(),
    )
    error = _relative_to_first(_poses(out))[:, :3, 3] - _relative_to_first(camera)[:, :3, 3]
    assert np.abs(error).max() < 1e-6
    assert all(o.status is FrameStatus.OK for o in out)


def test_an_unknown_reference_is_not_used():
    scenario = smooth_trajectory(10, seed=25)
    stamps = scenario.timestamps_ns
    backend = FusionBackend(BackendConfig(), BODY_FROM_CAMERA, None)
    for k in range(4):
        backend.add_frame(int(stamps[k]), np.eye(4), np.full(50, 0.02), 50, None)
    out = backend.add_frame(
        int(stamps[4]), np.eye(4), np.full(50, 0.02), 50, None, reference_ns=int(stamps[4]) - 7
    )
    assert out.status is FrameStatus.LOST
    assert "unknown" in out.message


def _steady_imu(rng: np.random.Generator, noise: ImuNoise, rate: np.ndarray, seconds: float):
    """200 Hz IMU from 0.2 s before frame 0: a constant angular rate (bias and any turn) and
    gravity, each with the sheet's white noise (what a still sensor, or a steady cruise, reads)."""
    stamps = np.arange(-40, round(seconds * 200) + 1, dtype=np.int64) * 5_000_000
    gyro = rate + rng.normal(0.0, noise.gyro_noise_density * np.sqrt(200.0), (len(stamps), 3))
    accel = np.array([0.0, 0.0, 9.81]) + rng.normal(
        0.0, noise.accel_noise_density * np.sqrt(200.0), (len(stamps), 3)
    )
    return ImuBatch(stamps, gyro, accel)


def _run_at_20_hz(backend: FusionBackend, imu: ImuBatch, frames: int, relative_pose):
    """Frame 0 with the IMU before it, then ``frames`` frames at 20 Hz, each measured against
    the previous one by ``relative_pose(k)`` (camera frame) and given its interval's IMU."""
    out = [backend.add_frame(0, None, None, 0, imu.between(-(10**10), 0))]
    for k in range(1, frames + 1):
        out.append(
            backend.add_frame(
                k * 50_000_000,
                relative_pose(k),
                np.full(100, 0.01),
                100,
                imu.between((k - 1) * 50_000_000, k * 50_000_000),
            )
        )
    return out


def _standstill_run(config: BackendConfig, seconds: float, seed: int = 0):
    """A still body (IMU with EuRoC noise and a known bias) seen by noisy identity poses."""
    noise = ImuNoise()
    rng = np.random.default_rng(seed)
    bias = np.array([0.003, -0.004, 0.002])
    imu = _steady_imu(rng, noise, bias, seconds)
    backend = FusionBackend(config, BODY_FROM_CAMERA, noise)

    def jitter(_: int) -> np.ndarray:
        return make_pose(
            Rotation.from_rotvec(rng.normal(0, 2e-4, 3)).as_matrix(), rng.normal(0, 1e-3, 3)
        )

    out = _run_at_20_hz(backend, imu, round(seconds * 20), jitter)
    return out, bias, backend, imu.gyro.mean(axis=0)  # every sample was delivered, all at rest


def test_static_initialisation_estimates_the_gyro_bias_from_the_standstill():
    out, bias, backend, window_mean = _standstill_run(BackendConfig(), 2.0)
    assert "at rest for 0.20 s before frame 0" in out[0].message
    assert backend.rest_summary is None  # still at rest: the start-up goes on
    # 2.2 s of rest: density / sqrt(T) = 1.1e-4 rad/s per axis; allow 4 sigma.
    assert np.abs(out[-1].gyro_bias - bias).max() < 4 * 1.7e-4 / np.sqrt(2.2)
    # With the rotation pinned, the gyro factors make the bias the mean gyro of the window
    # (each sample used once); 1e-5 rad/s is a tenth of that mean's noise.
    np.testing.assert_allclose(out[-1].gyro_bias, window_mean, atol=1e-5)
    # The zero-motion factors hold the pose against the vision jitter.
    assert np.abs(out[-1].body_pose[:3, 3]).max() < 1e-3
    # Over a few seeds the static initialisation beats what vision and the gyro factors alone
    # make of the bias.
    errors = {True: [], False: []}
    for seed in range(4):
        for static in (True, False):
            run, truth, _, _ = _standstill_run(BackendConfig(static_init=static), 2.0, seed)
            errors[static].append(run[-1].gyro_bias - truth)
    rms = {key: float(np.sqrt(np.mean(np.square(value)))) for key, value in errors.items()}
    assert rms[True] < 4 * 1.7e-4 / np.sqrt(2.2)
    assert rms[True] < 0.7 * rms[False]


def test_a_cruising_start_that_reads_like_rest_does_not_set_the_gyro_bias():
    """A platform already moving at constant speed and turn rate (a car cruising): its IMU
    before frame 0 reads like a still sensor, but its mean rate is bias plus turn. Vision shows
    the motion at the first interval, so the tight bias prior of a rest must not hold; the
    bias is then learned from vision and the gyro."""
    noise = ImuNoise()
    rng = np.random.default_rng(5)
    bias = np.array([0.001, -0.002, 0.0005])
    turn = np.array([0.0, 0.02, 0.0])  # rad/s about the body y axis
    imu = _steady_imu(rng, noise, bias + turn, 3.05)
    config = BackendConfig(use_accelerometer=False)
    backend = FusionBackend(config, BODY_FROM_CAMERA, noise)
    body_step = make_pose(Rotation.from_rotvec(turn * 0.05).as_matrix(), [0.6, 0.0, 0.0])
    camera_step = invert_pose(BODY_FROM_CAMERA) @ body_step @ BODY_FROM_CAMERA
    out = _run_at_20_hz(backend, imu, 60, lambda _: camera_step)
    assert "at rest for 0.20 s before frame 0" in out[0].message
    # Taken as rest, the bias would start at bias + turn (0.02 rad/s off) and stay there.
    assert np.abs(out[-1].gyro_bias - bias).max() < 2e-3
    assert "its gyro bias prior dropped" in out[1].message
    assert all(o.status is FrameStatus.OK for o in out)


def test_static_initialisation_is_skipped_when_the_imu_moves_before_the_first_frame():
    scenario = smooth_trajectory(30, seed=2)
    measurements = simulate_frontend(scenario.body_poses, BODY_FROM_CAMERA, seed=3)
    with_init = _run(scenario, measurements, BackendConfig())
    without = _run(scenario, measurements, BackendConfig(static_init=False))
    assert "IMU not at rest before frame 0" in with_init[0].message
    np.testing.assert_array_equal(_poses(with_init), _poses(without))


def _yaw_biased_run(rotation_sigma: float) -> float:
    """Final heading error (deg) when every vision step turns 0.05 deg too far about the
    camera z axis, with a perfect gyro, given the vision covariance the front end reports."""
    scenario = smooth_trajectory(60, seed=1, noise=PERFECT_IMU, initial_bias=(0.0, 0.0, 0.0))
    camera = scenario.body_poses @ BODY_FROM_CAMERA
    error = make_pose(Rotation.from_euler("z", 0.05, degrees=True).as_matrix(), [0, 0, 0])
    covariance = np.diag([rotation_sigma**2] * 3 + [1e-3**2] * 3)
    backend = FusionBackend(BackendConfig(), BODY_FROM_CAMERA, ImuNoise())
    stamps = scenario.timestamps_ns
    out = []
    for k in range(len(stamps)):
        start = stamps[k - 1] if k else stamps[0] - 10**9
        measured = None if k == 0 else invert_pose(camera[k - 1]) @ camera[k] @ error
        out.append(
            backend.add_frame(
                int(stamps[k]), measured, None, 150,
                scenario.imu.between(int(start), int(stamps[k])),
                covariance=None if k == 0 else covariance,
            )
        )  # fmt: skip
    final = invert_pose(_relative_to_first(_poses(out))[-1]) @ _relative_to_first(camera)[-1]
    return float(rotation_angle_deg(final[:3, :3]))


def test_a_front_end_covariance_sets_the_weight_of_its_measurement():
    # Trusted vision (0.001 deg) carries its whole 59 x 0.05 deg turn into the result
    # (measured 2.94 deg); distrusted vision (1 deg) leaves more of the heading to the gyro
    # (measured 1.61 deg; the online bias still absorbs part of the turn). Ignoring the
    # covariance would give both runs the same result.
    trusted, distrusted = _yaw_biased_run(np.radians(0.001)), _yaw_biased_run(np.radians(1.0))
    assert trusted > 2.5, trusted
    assert distrusted < 0.7 * trusted, (trusted, distrusted)


def test_a_front_end_covariance_must_be_a_finite_6x6():
    backend = FusionBackend(BackendConfig(), np.eye(4), None)
    backend.add_frame(100, None, None, 0, None)
    with pytest.raises(ValueError, match="6x6"):
        backend.add_frame(200, np.eye(4), None, 10, None, covariance=np.eye(3))
    with pytest.raises(ValueError, match="6x6"):
        backend.add_frame(200, np.eye(4), None, 10, None, covariance=np.full((6, 6), np.nan))


def _prior_keys(backend: FusionBackend) -> set[int]:
    """Frame indices with a pose prior in the smoother's graph."""
    graph = backend.smoother.graph.getFactors()
    return {
        gtsam.Symbol(graph.at(i).keys()[0]).index()
        for i in range(graph.size())
        if graph.at(i) is not None and isinstance(graph.at(i), gtsam.PriorFactorPose3)
    }


@pytest.mark.parametrize("old_reference", ["chain", "prior-after-gap", "prior"])
def test_after_a_gap_an_old_reference_does_not_go_through_the_coasted_frame(
    old_reference, between_factor_ends
):
    """Frame 20 has no vision; frame 21 is measured against frame 10, long out of the window.
    "chain": its factor starts at frame 19 (measured), not at the coasted frame 20, whose
    estimate is only the motion prior's (or the IMU's) and would carry its error into frame 21.
    "prior-after-gap" and "prior": frame 21 is placed from frame 10's estimate directly (a
    pose prior)."""
    scenario = smooth_trajectory(24, seed=26)
    stamps = scenario.timestamps_ns
    camera = scenario.body_poses @ BODY_FROM_CAMERA
    config = BackendConfig(old_reference=old_reference)
    backend = FusionBackend(config, BODY_FROM_CAMERA, None)
    backend.add_frame(int(stamps[0]), None, None, 0, None)
    for k in range(1, 22):
        reference = 10 if k > 10 else k - 1
        measured = None if k == 20 else invert_pose(camera[reference]) @ camera[k]
        out = backend.add_frame(
            int(stamps[k]), measured, np.full(150, 0.02), 150, None,
            reference_ns=int(stamps[reference]),
        )  # fmt: skip
    assert out.status is FrameStatus.OK
    pairs = {(a, b) for _, a, _, b in between_factor_ends(backend.smoother.graph)}
    assert (20, 21) not in pairs
    if old_reference == "chain":
        assert (19, 21) in pairs and 21 not in _prior_keys(backend)
    else:
        assert not any(second == 21 for _, second in pairs) and 21 in _prior_keys(backend)
    estimated = invert_pose(backend.smoother.pose(19)) @ backend.smoother.pose(21)
    true = invert_pose(scenario.body_poses[19]) @ scenario.body_poses[21]
    assert np.linalg.norm(estimated[:3, 3] - true[:3, 3]) < 1e-6
