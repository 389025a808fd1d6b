"""Gyro preintegration, the rotation factor, IMU buffering and gravity alignment."""

from __future__ import annotations

from pathlib import Path

import gtsam
import numpy as np
import pytest

from estimator.backend.factors import gyro_rotation_error
from estimator.backend.imu import (
    GRAVITY,
    ImuBuffer,
    gravity_aligned_rotation,
    preintegrate_gyro,
    rotation_params,
)
from estimator.formats.datasets import read_euroc_ground_truth, read_euroc_imu, read_euroc_imu_noise
from estimator.geometry import rotation_angle_deg
from estimator.imu_sampling import sample_segments
from estimator.types import ImuBatch, ImuNoise


def _euroc_steps(root: Path) -> tuple[ImuBatch, np.ndarray, np.ndarray, np.ndarray]:
    """Real IMU and the 20 Hz ground-truth steps (timestamps, rotations, gyro bias) it covers."""
    imu = read_euroc_imu(root / "mav0/imu0/data.csv")
    truth = read_euroc_ground_truth(root / "mav0/state_groundtruth_estimate0/data.csv")
    inside = (truth.timestamps_ns >= imu.timestamps_ns[0]) & (
        truth.timestamps_ns <= imu.timestamps_ns[-1]
    )
    stamps = truth.timestamps_ns[inside]
    # Keep one row per 50 ms (the ground truth of this segment is denser than 20 Hz).
    keep = np.concatenate([[True], np.diff(stamps // 50_000_000) > 0])
    keep[0] = True
    rows = np.flatnonzero(inside)[keep]
    assert truth.gyro_bias is not None
    return imu, truth.timestamps_ns[rows], truth.poses[rows, :3, :3], truth.gyro_bias[rows]


@pytest.mark.euroc
def test_preintegration_matches_ground_truth_on_real_fast_motion(euroc_v102_imu_segment):
    imu, stamps, rotations, bias = _euroc_steps(euroc_v102_imu_segment)
    noise = read_euroc_imu_noise(euroc_v102_imu_segment / "mav0/imu0/sensor.yaml")
    params = rotation_params(noise)
    errors = []
    for k in range(len(stamps) - 1):
        pre = preintegrate_gyro(
            imu.timestamps_ns, imu.gyro, stamps[k], stamps[k + 1], params, bias[k]
        )
        truth = rotations[k].T @ rotations[k + 1]
        errors.append(rotation_angle_deg(pre.delta_rotation.T @ truth))
    errors = np.asarray(errors)
    steps = np.diff(stamps) * 1e-9
    assert len(errors) > 700 and np.allclose(steps, 0.05, atol=1e-3)
    rms = float(np.sqrt(np.mean(errors**2)))
    assert rms < 0.05, f"per-step rotation RMS {rms:.4f} deg"
    # Without the bias the same steps are clearly worse: the check can tell.
    unbiased = [
        rotation_angle_deg(
            preintegrate_gyro(
                imu.timestamps_ns, imu.gyro, stamps[k], stamps[k + 1], params
            ).delta_rotation.T
            @ rotations[k].T
            @ rotations[k + 1]
        )
        for k in range(0, len(stamps) - 1, 10)
    ]
    assert np.sqrt(np.mean(np.square(unbiased))) > 2 * rms


def test_constant_rate_integrates_exactly_between_off_grid_times():
    rate = np.array([0.3, -1.2, 0.7])
    stamps = np.arange(0, 200_000_000, 5_000_000, dtype=np.int64)
    gyro = np.tile(rate, (len(stamps), 1))
    pre = preintegrate_gyro(stamps, gyro, 12_345_678, 112_345_678, rotation_params(ImuNoise()))
    expected = gtsam.Rot3.Expmap(rate * 0.1).matrix()
    assert pre.duration_s == pytest.approx(0.1)
    np.testing.assert_allclose(pre.delta_rotation, expected, atol=1e-12)
    # Covariance grows linearly with time: sigma_c^2 * T per axis.
    np.testing.assert_allclose(np.diag(pre.covariance), 1.6968e-4**2 * 0.1, rtol=1e-6)


def test_segments_cut_at_frame_times_and_interpolate():
    stamps = np.array([0, 10, 20], dtype=np.int64)
    gyro = np.array([[0.0, 0, 0], [1.0, 0, 0], [2.0, 0, 0]])
    rates, durations = sample_segments(stamps, gyro, 5, 15)
    np.testing.assert_allclose(durations, [5e-9, 5e-9])
    np.testing.assert_allclose(rates[:, 0], [0.75, 1.25])
    with pytest.raises(ValueError, match="end > start"):
        sample_segments(stamps, gyro, 15, 5)
    with pytest.raises(ValueError, match="no IMU samples"):
        sample_segments(stamps[:0], gyro[:0], 0, 5)


def test_rotation_factor_matches_gtsam_ahrs_factor_and_its_jacobians():
    rng = np.random.default_rng(3)
    stamps = np.arange(0, 60_000_000, 5_000_000, dtype=np.int64)
    gyro = rng.normal(0.0, 1.0, size=(len(stamps), 3))
    params = rotation_params(ImuNoise())
    bias_hat = np.array([0.01, -0.02, 0.03])
    pre = preintegrate_gyro(stamps, gyro, 2_000_000, 52_000_000, params, bias_hat)
    pim = gtsam.PreintegratedAhrsMeasurements(params, bias_hat)
    for rate, duration in zip(*sample_segments(stamps, gyro, 2_000_000, 52_000_000), strict=True):
        pim.integrateMeasurement(rate, duration)
    native = gtsam.AHRSFactor(1, 2, 3, pim)
    rot_i = gtsam.Rot3.Expmap(np.array([0.1, 0.2, -0.3]))
    rot_j = gtsam.Rot3.Expmap(np.array([0.15, 0.1, -0.2]))
    bias = bias_hat + np.array([0.004, -0.003, 0.005])  # exercises the bias Jacobian
    error, (d_i, d_j, d_b) = gyro_rotation_error(pre, rot_i.matrix(), rot_j.matrix(), bias)
    # GTSAM 4.3's AHRSFactor reports the same residual with the opposite sign convention
    # (Log(actual^-1 predicted)); the Gaussian cost is identical.
    np.testing.assert_allclose(error, -native.evaluateError(rot_i, rot_j, bias), atol=1e-9)
    eps = 1e-6
    unit = np.eye(3)

    def perturbed(which: int, axis: int) -> np.ndarray:
        step = gtsam.Rot3.Expmap(eps * unit[axis]).matrix()
        if which == 0:
            return gyro_rotation_error(pre, rot_i.matrix() @ step, rot_j.matrix(), bias)[0]
        if which == 1:
            return gyro_rotation_error(pre, rot_i.matrix(), rot_j.matrix() @ step, bias)[0]
        return gyro_rotation_error(pre, rot_i.matrix(), rot_j.matrix(), bias + eps * unit[axis])[0]

    for which, analytic in enumerate((d_i, d_j, d_b)):
        numeric = np.stack([(perturbed(which, a) - error) / eps for a in range(3)], axis=1)
        np.testing.assert_allclose(analytic, numeric, atol=1e-5)


@pytest.mark.parametrize(("roll_deg", "pitch_deg"), [(10.0, -20.0), (-35.0, 5.0), (0.0, 0.0)])
def test_gravity_alignment_recovers_a_known_tilt(roll_deg, pitch_deg):
    rng = np.random.default_rng(7)
    yaw = 1.1  # unobservable: must not matter
    world_from_body = gtsam.Rot3.Ypr(yaw, np.radians(pitch_deg), np.radians(roll_deg)).matrix()
    specific_force = world_from_body.T @ np.array([0.0, 0.0, GRAVITY])
    accel = specific_force + rng.normal(0.0, 0.03, size=(200, 3))
    rotation = gravity_aligned_rotation(accel)
    estimate = gtsam.Rot3(rotation)
    assert np.degrees(estimate.roll()) == pytest.approx(roll_deg, abs=0.05)
    assert np.degrees(estimate.pitch()) == pytest.approx(pitch_deg, abs=0.05)
    assert np.degrees(estimate.yaw()) == pytest.approx(0.0, abs=1e-9)
    # The body's measured "up" maps onto world z.
    up = rotation @ (specific_force / np.linalg.norm(specific_force))
    np.testing.assert_allclose(up, [0.0, 0.0, 1.0], atol=1e-3)


@pytest.mark.euroc
def test_gravity_alignment_on_real_standstill_matches_ground_truth_tilt(euroc_v101_micro):
    imu = read_euroc_imu(euroc_v101_micro / "mav0/imu0/data.csv")
    truth = read_euroc_ground_truth(euroc_v101_micro / "mav0/state_groundtruth_estimate0/data.csv")
    window = imu.between(int(imu.timestamps_ns[0]), int(imu.timestamps_ns[0]) + 200_000_000)
    rotation = gravity_aligned_rotation(window.accel)
    true_up = truth.poses[0, :3, :3].T @ np.array([0.0, 0.0, 1.0])  # world z in the body
    measured_up = rotation.T @ np.array([0.0, 0.0, 1.0])
    angle = np.degrees(np.arccos(np.clip(true_up @ measured_up, -1.0, 1.0)))
    # The accelerometer bias (~0.1 m/s^2 on this sensor) limits this to about a degree.
    assert angle < 1.5, f"gravity direction off by {angle:.2f} deg"


def test_gravity_alignment_rejects_bad_windows():
    with pytest.raises(ValueError, match="at least one"):
        gravity_aligned_rotation(np.zeros((0, 3)))
    with pytest.raises(ValueError, match="far from gravity"):
        gravity_aligned_rotation(np.full((10, 3), 0.1))
    with pytest.raises(ValueError, match="NaN"):
        gravity_aligned_rotation(np.array([[np.nan, 0.0, 9.8]]))


def test_buffer_drops_repeats_and_cuts_windows():
    buffer = ImuBuffer()
    stamps = np.arange(0, 100, 10, dtype=np.int64)
    batch = ImuBatch(stamps, np.ones((10, 3)), np.ones((10, 3)))
    buffer.extend(batch)
    buffer.extend(batch.between(40, 100))  # repeats: ignored
    assert len(buffer) == 10
    window_stamps = buffer.window(25, 45).timestamps_ns
    np.testing.assert_array_equal(window_stamps, [20, 30, 40, 50])
    assert buffer.covers(0, 90, max_gap_ns=10)
    assert not buffer.covers(0, 150, max_gap_ns=10)
    buffer.drop_before(45)
    assert buffer.timestamps_ns[0] == 40
    with pytest.raises(ValueError, match="strictly increasing"):
        buffer.extend(ImuBatch(np.array([200, 200]), np.ones((2, 3)), np.ones((2, 3))))
    with pytest.raises(ValueError, match="sizes differ"):
        buffer.extend(ImuBatch(np.array([300]), np.ones((2, 3)), np.ones((2, 3))))


# ----------------------------------------------------------------------------- standstill


def _rest_imu(
    rng: np.random.Generator, seconds: float, noise: ImuNoise, bias: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A still, tilted IMU: EuRoC white noise around its bias and the reaction to gravity."""
    count = round(seconds * noise.rate_hz)
    stamps = np.arange(count, dtype=np.int64) * round(1e9 / noise.rate_hz)
    up = gtsam.Rot3.Ypr(0.3, 0.1, -0.2).matrix().T @ np.array([0.0, 0.0, GRAVITY])
    gyro_sigma = noise.gyro_noise_density * np.sqrt(noise.rate_hz)
    accel_sigma = noise.accel_noise_density * np.sqrt(noise.rate_hz)
    gyro = bias + rng.normal(0.0, gyro_sigma, (count, 3))
    accel = up + rng.normal(0.0, accel_sigma, (count, 3))
    return stamps, gyro, accel


def test_standstill_detector_accepts_rest_and_rejects_motion():
    from estimator.backend.rest import RestWindow, at_rest
    from estimator.rendered.trajectory import loop_for_length, simulate_imu, start_after_rest

    noise = ImuNoise()
    rng = np.random.default_rng(0)
    bias = np.array([0.004, -0.002, 0.003])
    stamps, gyro, accel = _rest_imu(rng, 10.0, noise, bias)
    # Every frame interval (10 samples) and the whole window pass, also against the window
    # before them.
    windows = np.arange(len(stamps)).reshape(-1, 10)
    assert all(at_rest(gyro[w], accel[w], noise) for w in windows)
    reference = RestWindow.of(stamps[:200], gyro[:200], accel[:200])
    assert all(at_rest(gyro[w], accel[w], noise, reference=reference) for w in windows[20:])
    assert at_rest(gyro, accel, noise)

    # A flight: every 0.5 s piece is rejected on its own.
    trajectory = loop_for_length(20.0, 10.0)
    flight = trajectory.state(np.arange(2000) / noise.rate_hz)
    gyro_m, accel_m, _, _ = simulate_imu(flight, noise, np.random.default_rng(1))
    pieces = np.arange(2000).reshape(-1, 100)
    assert not any(at_rest(gyro_m[p], accel_m[p], noise) for p in pieces)

    # The first 50 ms of a smooth start from rest hardly raise the variance, but the mean
    # specific force moves away from the rest window's.
    t = np.arange(-400, 10) / noise.rate_hz
    start = start_after_rest(trajectory, t, 1.0)
    gyro_s, accel_s, _, _ = simulate_imu(start, noise, np.random.default_rng(2))
    rest = RestWindow.of(np.arange(400) * 5_000_000, gyro_s[:400], accel_s[:400])
    assert at_rest(gyro_s[:400], accel_s[:400], noise)
    assert not at_rest(gyro_s[400:], accel_s[400:], noise, reference=rest)


def test_rest_bias_estimate_is_as_accurate_as_the_noise_density_says():
    from estimator.backend.rest import RestWindow

    noise = ImuNoise()
    errors = []
    for seed in range(40):
        rng = np.random.default_rng(seed)
        bias = rng.normal(0.0, 0.01, 3)
        stamps, gyro, accel = _rest_imu(rng, 2.0, noise, bias)
        window = RestWindow.of(stamps, gyro, accel)
        sigma = window.bias_sigma(noise)
        # density / sqrt(T) (plus a negligible walk term over 2 s).
        assert sigma == pytest.approx(noise.gyro_noise_density / np.sqrt(2.0), rel=0.02)
        errors.append((window.gyro_mean - bias) / sigma)
    errors = np.concatenate(errors)
    # 120 normalised errors: none beyond 4 sigma, spread 1 within sampling noise (~7 %).
    assert np.abs(errors).max() < 4.0
    assert 0.75 < float(np.sqrt(np.mean(errors**2))) < 1.25


def test_an_interval_cut_once_preintegrates_as_when_each_signal_cuts_it() -> None:
    """``ImuTerms.preintegrate`` hands the gyro's pieces to both preintegrations: the same
    rotation, bias Jacobian, covariance and specific-force increments, to the last bit."""
    from estimator.backend.imu import preintegrate_specific_force
    from estimator.backend.imu_terms import ImuTerms
    from estimator.config import BackendConfig

    rng = np.random.default_rng(4)
    stamps = np.arange(0, 300_000_000, 4_900_000, dtype=np.int64) + 1_234_567
    gyro = rng.normal(size=(len(stamps), 3)) * 0.3
    accel = rng.normal(size=(len(stamps), 3)) + np.array([0.0, 0.0, GRAVITY])
    noise = ImuNoise()
    terms = ImuTerms(BackendConfig(), noise, use_accel=True)
    terms.buffer.extend(ImuBatch(stamps, gyro, accel))
    bias = np.array([1e-3, -2e-3, 5e-4])
    start, end = 50_000_000, 150_000_000
    window = terms.buffer.window(start, end)
    gyro_alone = preintegrate_gyro(
        window.timestamps_ns, window.gyro, start, end, terms.params, bias
    )
    force_alone = preintegrate_specific_force(
        window.timestamps_ns, window.gyro, window.accel, start, end, bias
    )
    shared, force = terms.preintegrate(start, end, bias)
    assert shared is not None and force is not None
    for name in ("delta_rotation", "bias_jacobian", "covariance", "bias_hat"):
        assert np.array_equal(getattr(shared, name), getattr(gyro_alone, name)), name
    assert np.array_equal(force.delta_position, force_alone.delta_position)
    assert np.array_equal(force.delta_velocity, force_alone.delta_velocity)
    assert shared.duration_s == gyro_alone.duration_s == force.duration_s
