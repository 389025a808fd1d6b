"""The covariance scale measured online against the gyro (estimator.backend.covariance_scale)."""

from __future__ import annotations

import json

import gtsam
import numpy as np
import pytest

from estimator.backend import FusionBackend
from estimator.backend.covariance_scale import (
    _CHI2_3_MEDIAN,
    ChainDisagreement,
    CovarianceScale,
    _median,
    disagreement_spectra,
    solve_factor,
)
from estimator.config import BackendConfig
from estimator.geometry import invert_pose
from estimator.rendered.scenario import CAMERA_MOUNT, smooth_trajectory
from estimator.types import ImuNoise

VISION_SIGMAS = np.array([1e-3] * 3 + [4e-3] * 3)  # rotation rad, translation m


def _observe_all(scale: CovarianceScale, factor: float, gyro_sigma: float, seed: int) -> float:
    """Comparisons whose vision error has ``factor`` times the stated covariance."""
    rng = np.random.default_rng(seed)
    vision = np.diag([1e-3, 2e-3, 1.5e-3]) ** 2
    gyro = np.eye(3) * gyro_sigma**2
    for _ in range(300):
        error = rng.multivariate_normal(np.zeros(3), factor * vision + gyro)
        truth = gtsam.Rot3.Expmap(rng.normal(size=3) * 0.1).matrix()
        scale.observe(truth @ gtsam.Rot3.Expmap(error).matrix(), vision, truth, gyro, 0.1)
    return scale.value


@pytest.mark.parametrize("factor", [0.2, 1.0, 5.0])
def test_the_factor_of_a_known_noise_level_is_recovered(factor: float) -> None:
    # The gyro's own noise (a quarter of the smallest vision sigma) is accounted for.
    value = _observe_all(CovarianceScale(bias_sigma=0.0), factor, 2.5e-4, seed=3)
    assert value == pytest.approx(factor, rel=0.3)


def test_the_factor_is_one_until_enough_comparisons_and_stays_bounded() -> None:
    scale = CovarianceScale(min_samples=20, bounds=(0.5, 4.0))
    rng = np.random.default_rng(0)
    for _ in range(19):
        error = rng.normal(size=3) * 0.1  # hugely beyond the 1 mrad stated
        scale.observe(
            gtsam.Rot3.Expmap(error).matrix(), np.eye(3) * 1e-6, np.eye(3), np.zeros((3, 3)), 0.05
        )
    assert scale.value == 1.0
    scale.observe(
        np.eye(3), np.eye(3) * 1e-6, gtsam.Rot3.Expmap([0.1, 0, 0]).matrix(), np.zeros((3, 3)), 0.05
    )
    assert scale.value == 4.0
    with pytest.raises(ValueError, match="enclose 1"):
        CovarianceScale(bounds=(2.0, 4.0))


def _fused(vision_flight, factor: float, mode: str = "gyro", frames: int = 160) -> list:
    """The conftest flight (noise seed 11) with the covariance scale ``mode``."""
    config = BackendConfig(covariance_scale=mode)
    return vision_flight(factor, config, frames, 11, VISION_SIGMAS)[0]


@pytest.mark.parametrize("factor", [0.25, 4.0])
def test_the_back_end_measures_an_injected_noise_level_without_changing_the_trajectory(
    factor: float, vision_flight
) -> None:
    calibrated = _fused(vision_flight, factor)
    # The factor also covers the floors the back end adds (0.1 mrad on 1 mrad: 1 %).
    assert calibrated[-1].covariance_scale == pytest.approx(factor, rel=0.4)
    assert calibrated[0].covariance_scale == 1.0  # nothing measured yet
    fixed = _fused(vision_flight, factor, mode="off")
    assert all(e.covariance_scale == 1.0 for e in fixed)
    np.testing.assert_allclose([e.pose for e in calibrated], [e.pose for e in fixed], atol=1e-12)


def test_the_frame_interval_is_the_median_of_the_first_intervals() -> None:
    from estimator.rig_settings import FrameIntervalEstimate

    estimate = FrameIntervalEstimate(count=5, tolerance=0.1)
    assert estimate.add(0) is None  # one stamp: no interval yet
    # The first interval is short (a late first frame): taken, then corrected by the median.
    assert estimate.add(30_000_000) == pytest.approx(0.03)
    answers = [estimate.add(t) for t in (130_000_000, 230_000_000, 430_000_000, 530_000_000)]
    assert answers[0] == pytest.approx(0.065)  # median of 30 and 100 ms
    assert answers[1] == pytest.approx(0.1)  # median of 30, 100, 100 ms
    assert answers[2] is None and answers[3] is None  # a dropped frame does not move it
    assert estimate.interval_s == pytest.approx(0.1)
    assert estimate.add(2_000_000_000) is None  # only the first intervals count


def _keyframe_flight(
    scale: CovarianceScale, local: ChainDisagreement, factors: list[float], seed: int = 5
) -> list[tuple[float, float]]:
    """Frames at 20 Hz, each measured against its keyframe (a new one every 4 frames), the
    vision rotation error of frame k being ``factors[k]`` times its stated covariance and the
    gyro exact; (session factor, local factor) after each frame."""
    rng = np.random.default_rng(seed)
    vision = np.diag([1e-3, 2e-3, 1.5e-3]) ** 2
    gyro = np.eye(3) * 1e-10
    step = 50_000_000
    out = []
    for k in range(1, len(factors)):
        reference = (k - 1) // 4 * 4
        truth = gtsam.Rot3.Expmap(rng.normal(size=3) * 0.05).matrix()
        error = rng.multivariate_normal(np.zeros(3), factors[k] * vision)
        measured = truth @ gtsam.Rot3.Expmap(error).matrix()
        duration = (k - reference) * step * 1e-9
        scale.observe(measured, vision, truth, gyro, duration)
        local.add(k * step, reference * step, measured, vision, truth, gyro)
        out.append((scale.value, local.value))
    return out


def test_the_local_factor_follows_an_episode_that_the_session_median_misses() -> None:
    # 6 s calm, 1 s with errors 25 times the stated covariance, 3 s calm again.
    factors = [1.0] * 120 + [25.0] * 20 + [1.0] * 60
    values = _keyframe_flight(
        CovarianceScale(bias_sigma=0.0), ChainDisagreement(bias_sigma=0.0), factors
    )
    session, local = np.array(values).T
    assert 0.4 < np.median(local[40:118]) < 2.5  # calm: about 1
    assert local[118:145].max() > 8.0  # the episode is seen within a second
    assert session[118:145].max() < 2.0  # the session median hardly moves
    assert local[-1] < 3.0  # and forgotten a second or two after it


def test_the_local_factor_is_bounded_and_starts_without_inflation() -> None:
    local = ChainDisagreement(bounds=(0.25, 4.0), bias_sigma=0.0)
    assert local.value == 0.25  # no stretch yet
    values = _keyframe_flight(CovarianceScale(), local, [400.0] * 60)
    assert values[-1][1] == 4.0


def _run(backend: FusionBackend, frames: range, factor: float = 9.0, seed: int = 11) -> list:
    """Frames of the simulated flight (``_fused``) handed to ``backend``."""
    scenario = smooth_trajectory(200, seed=4)
    camera = scenario.body_poses @ CAMERA_MOUNT
    rng = np.random.default_rng(seed)
    covariance = np.diag(VISION_SIGMAS**2)
    stamps, out = scenario.timestamps_ns, []
    for k in frames:
        start = stamps[k - 1] if k else stamps[0] - 10**8
        relative = None
        if k != frames[0]:
            error = rng.multivariate_normal(np.zeros(6), factor * covariance)
            relative = invert_pose(camera[k - 1]) @ camera[k] @ gtsam.Pose3.Expmap(error).matrix()
        imu = scenario.imu.between(int(start), int(stamps[k]))
        out.append(
            backend.add_frame(
                int(stamps[k]),
                relative,
                None,
                100,
                imu,
                covariance=covariance if relative is not None else None,
            )
        )
    return out


def test_a_restored_back_end_continues_with_the_stored_factors() -> None:
    first = FusionBackend(BackendConfig(), CAMERA_MOUNT, ImuNoise())
    stored = _run(first, range(0, 100))[-1].covariance_scale
    assert stored > 3.0  # the injected 9 is being measured
    state = json.loads(json.dumps(first.state()))  # as the service stores it
    resumed = FusionBackend(BackendConfig(), CAMERA_MOUNT, ImuNoise())
    resumed.restore(state)
    continued = _run(resumed, range(100, 110))
    assert continued[0].covariance_scale == pytest.approx(stored, rel=1e-9)
    assert all(abs(np.log(e.covariance_scale / stored)) < np.log(2.0) for e in continued)
    # the pose's factor is the session's raised by the local one, never below it
    assert all(e.pose_covariance_scale >= e.covariance_scale for e in continued)
    fresh = _run(FusionBackend(BackendConfig(), CAMERA_MOUNT, ImuNoise()), range(100, 110))
    assert fresh[0].covariance_scale == 1.0  # without the state: from 1 again


def test_the_decomposed_disagreement_equals_the_direct_solve() -> None:
    """q(s) = sum f^2 / (s lambda + 1) (decomposed once) against e^T (s V + G)^-1 e solved
    directly; a singular gyro covariance takes the direct path."""
    rng = np.random.default_rng(11)
    count = 200
    a = rng.normal(size=(count, 3, 3)) * 1e-3
    vision = a @ a.transpose(0, 2, 1)
    b = rng.normal(size=(count, 3, 3)) * 1e-3
    gyro = b @ b.transpose(0, 2, 1) + 1e-9 * np.eye(3)
    errors = rng.normal(size=(count, 3)) * 2e-3
    spectra = disagreement_spectra(errors, vision, gyro)
    assert spectra is not None
    for log_scale in (-2.0, 0.0, 1.5):
        covariance = np.exp(log_scale) * vision + gyro
        solution = np.linalg.solve(covariance, errors[..., None])[..., 0]
        direct = np.einsum("ni,ni->n", errors, solution)
        decomposed = (spectra[1] / (np.exp(log_scale) * spectra[0] + 1.0)).sum(axis=1)
        np.testing.assert_allclose(decomposed, direct, rtol=1e-9)
    factor = solve_factor(np.median, 2.366, errors, vision, gyro, (1 / 16, 16.0))
    assert 1 / 16 < factor < 16.0
    singular = gyro.copy()
    singular[0] = np.zeros((3, 3))  # not positive definite: the direct path
    assert disagreement_spectra(errors, vision, singular) is None
    assert 1 / 16 <= solve_factor(np.mean, 3.0, errors, vision, singular, (1 / 16, 16.0)) <= 16.0


def test_the_per_sample_spectra_give_the_factor_of_the_whole_window() -> None:
    """CovarianceScale decomposes each comparison once; its factor is that of the window."""
    rng = np.random.default_rng(13)
    scale = CovarianceScale(window=50, min_samples=5, bias_sigma=2e-4)
    errors, visions, gyros = [], [], []
    for _ in range(60):
        a = rng.normal(size=(3, 3)) * 1e-3
        vision = a @ a.T + 1e-8 * np.eye(3)
        gyro_rotation = gtsam.Rot3.Expmap(rng.normal(size=3) * 1e-3).matrix()
        scale.observe(np.eye(3), vision, gyro_rotation, 1e-8 * np.eye(3), 0.05)
        errors.append(np.asarray(gtsam.Rot3.Logmap(gtsam.Rot3(gyro_rotation.T))))
        visions.append(vision)
        gyros.append(1e-8 * np.eye(3) + (2e-4 * 0.05) ** 2 * np.eye(3))
    window = slice(-50, None)
    expected = solve_factor(
        np.median, _CHI2_3_MEDIAN, np.array(errors[window]), np.array(visions[window]),
        np.array(gyros[window]), scale.bounds,
    )  # fmt: skip
    assert scale.value == pytest.approx(expected, rel=1e-9)


def test_the_bisection_median_is_numpys() -> None:
    rng = np.random.default_rng(12)
    for count in (1, 2, 3, 10, 11, 400):
        values = rng.lognormal(size=count)
        assert _median(values) == float(np.median(values))
    assert np.isnan(_median(np.array([1.0, np.nan, 2.0])))


def test_the_chi_square_median_is_scipys() -> None:
    from scipy.stats import chi2

    assert float(chi2.ppf(0.5, 3)) == _CHI2_3_MEDIAN


def test_the_local_factor_from_per_sample_spectra_is_that_of_its_samples() -> None:
    factors = [1.0] * 60 + [9.0] * 20
    local = ChainDisagreement(bias_sigma=2e-4)
    _keyframe_flight(CovarianceScale(bias_sigma=2e-4), local, factors)
    errors, vision, gyro = (np.array(part) for part in zip(*local.samples, strict=True))
    expected = solve_factor(np.mean, 3.0, errors, vision, gyro, local.bounds)
    assert local.value == pytest.approx(expected, rel=1e-9)
    assert local.value > 1.5  # the last stretches disagree: the test would see a stale factor
