"""The rig declares whether its calibration is exact, and the calibration error in the
covariances reported without a gyro follows from it (estimator.rig_settings)."""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import pytest
from fastapi.testclient import TestClient
from test_driving import _rig
from test_service_units import A, FakeFactory, settings_for

from estimator.backend.systematic_noise import (
    CALIBRATION_ROTATION_GAIN,
    CALIBRATION_TRANSLATION_GAIN,
    EXACT_RIG_FIT_FLOOR,
    REAL_RIG_FIT_FLOOR,
    calibration_gains,
    fit_floor,
)
from estimator.cli.main import main
from estimator.config import BackendConfig, SwarmvoConfig
from estimator.formats.calibration import StereoRig
from estimator.formats.calibration_files import load_kitti_rig
from estimator.formats.datasets import open_sequence
from estimator.rendered.synthetic import SynthOptions, synthesize
from estimator.rig_settings import apply_rig_settings
from service.app import create_app

GAINS = ("calibration_rotation_gain", "calibration_translation_gain")
FLOORS = ("fit_min_rotation_sigma_rad", "fit_min_translation_sigma_m")
WEIGHTS = ("robust_parameter", "answer_smoothing_s", "keyframe_error_correlation")


def _gains(config: SwarmvoConfig) -> tuple[float | None, float | None]:
    return tuple(getattr(config.backend, name) for name in GAINS)  # type: ignore[return-value]


def _floors(config: SwarmvoConfig) -> tuple[float | None, float | None]:
    return tuple(getattr(config.backend, name) for name in FLOORS)  # type: ignore[return-value]


@pytest.fixture(scope="module")
def synthesized(tmp_path_factory) -> dict[str, Path]:
    """A tiny rendered flight in both layouts, as ``swarmvo synth`` writes them."""
    roots = {}
    for layout in ("euroc", "kitti"):
        root = tmp_path_factory.mktemp(layout)
        synthesize(root, SynthOptions(frames=12, length_m=1.0, seed=1, layout=layout))
        roots[layout] = root
    return roots


@pytest.mark.parametrize("layout", ["euroc", "kitti"])
def test_a_synthesized_flight_opened_from_disk_is_exact_and_has_zero_gains(
    synthesized, layout
) -> None:
    rig = open_sequence(synthesized[layout]).rig
    assert rig.calibration_exact is True
    config, derived = apply_rig_settings(SwarmvoConfig(), rig, 0.05)
    assert _gains(config) == (0.0, 0.0)
    assert _floors(config) == EXACT_RIG_FIT_FLOOR
    backend = {s.name: s for s in derived if s.section == "backend"}
    assert set(backend) == {*GAINS, *FLOORS, *WEIGHTS}
    # Consistent covariances: the chi-square kernel and the answer spread over the lag.
    assert config.backend.robust_parameter == pytest.approx(12.3, abs=0.01)
    assert config.backend.answer_smoothing_s == config.backend.smoother_lag_s
    assert config.backend.keyframe_error_correlation == 0.5
    assert all(not s.overridden and "exact" in s.reason for s in backend.values())
    # The flag survives the plain form (what the service stores and load_rig reads).
    assert StereoRig.from_dict(rig.to_dict()).calibration_exact is True


def test_the_real_mh01_rig_gets_the_default_gains(euroc_mh01_moving) -> None:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        rig = open_sequence(euroc_mh01_moving).rig
    assert rig.calibration_exact is False
    assert "calibration_exact" not in rig.to_dict()
    config, _ = apply_rig_settings(SwarmvoConfig(), rig, 0.05)
    assert _gains(config) == (0.01, 0.02)
    assert (CALIBRATION_ROTATION_GAIN, CALIBRATION_TRANSLATION_GAIN) == (0.01, 0.02)
    # The real rig keeps the graph's floor it was tuned with; unset, the floor is the same.
    assert _floors(config) == REAL_RIG_FIT_FLOOR == (1e-4, 5e-4)
    assert fit_floor(BackendConfig()) == REAL_RIG_FIT_FLOOR
    # ... and the kernel and the answer it was tuned with.
    assert (config.backend.robust_parameter, config.backend.answer_smoothing_s) == (3.0, 0.0)
    # No widening of the fused pose covariance: the floor and the placement priors cover it.
    assert config.backend.keyframe_error_correlation == 0.0


def test_an_explicit_fit_floor_wins_on_an_exact_rig(synthesized) -> None:
    rig = open_sequence(synthesized["euroc"]).rig
    backend = BackendConfig(fit_min_rotation_sigma_rad=3e-4)
    config, derived = apply_rig_settings(SwarmvoConfig(backend=backend), rig, 0.05)
    assert _floors(config) == (3e-4, EXACT_RIG_FIT_FLOOR[1])
    rotation = next(s for s in derived if s.name == "fit_min_rotation_sigma_rad")
    assert rotation.overridden and "configured" in rotation.reason
    # The exact rig's floor is smaller in both rotation and translation.
    assert all(e < r for e, r in zip(EXACT_RIG_FIT_FLOOR, REAL_RIG_FIT_FLOOR, strict=True))


def test_an_explicit_config_value_wins(synthesized) -> None:
    rig = open_sequence(synthesized["euroc"]).rig
    configured = SwarmvoConfig(backend=BackendConfig(calibration_translation_gain=0.03))
    config, derived = apply_rig_settings(configured, rig, 0.05)
    assert _gains(config) == (0.0, 0.03)
    translation = next(s for s in derived if s.name == "calibration_translation_gain")
    assert translation.overridden and "the rig suggests 0" in translation.reason
    # Applying again (a derived config handed back) changes nothing.
    assert _gains(apply_rig_settings(config, rig, 0.05)[0]) == (0.0, 0.03)
    explicit_zero = BackendConfig(calibration_rotation_gain=0.0)
    assert calibration_gains(explicit_zero, calibration_exact=False) == (0.0, 0.02)
    # Unset gains and a rig not known to be exact: the real-rig defaults.
    assert calibration_gains(BackendConfig(), calibration_exact=False) == (0.01, 0.02)


def test_swarmvo_config_lists_the_derived_gains_and_reads_them_back(synthesized, capsys) -> None:
    assert main(["config"]) == 0
    assert "calibration_rotation_gain: null" in capsys.readouterr().out  # from the rig
    assert main(["config", str(synthesized["kitti"])]) == 0
    out = capsys.readouterr().out
    assert "backend.calibration_rotation_gain = 0  (the rig's calibration is exact)" in out
    assert "backend.calibration_translation_gain = 0  (the rig's calibration is exact)" in out


def test_calibration_files_with_a_malformed_flag_are_refused(tmp_path, synthesized) -> None:
    calib = (synthesized["kitti"] / "calib.txt").read_text()
    assert "calibration_exact: 1" in calib
    path = tmp_path / "calib.txt"
    path.write_text(calib.replace("calibration_exact: 1", "calibration_exact: 2"))
    with pytest.raises(ValueError, match="calibration_exact must be 0 or 1"):
        load_kitti_rig(path, (64, 48))
    path.write_text(calib.replace("calibration_exact: 1", "calibration_exact: 0"))
    assert load_kitti_rig(path, (64, 48)).calibration_exact is False
    mav0 = synthesized["euroc"] / "mav0"
    bad = tmp_path / "cam0.yaml"
    bad.write_text((mav0 / "cam0/sensor.yaml").read_text().replace(
        "calibration_exact: true", "calibration_exact: maybe"))
    from estimator.formats.calibration_files import load_euroc_rig

    with pytest.raises(ValueError, match="calibration_exact must be true or false"):
        load_euroc_rig(bad, mav0 / "cam1/sensor.yaml")
    # One camera file without the declaration: the rig is not known to be exact.
    plain = tmp_path / "cam1.yaml"
    plain.write_text((mav0 / "cam1/sensor.yaml").read_text().replace(
        "calibration_exact: true\n", ""))
    assert load_euroc_rig(mav0 / "cam0/sensor.yaml", plain).calibration_exact is False
    with pytest.raises(ValueError, match="calibration_exact"):
        StereoRig.from_dict({**_rig(64, 48, 50.0, 0.1).to_dict(), "calibration_exact": "yes"})


def test_service_sessions_take_the_flag_from_the_calibration_payload(tmp_path: Path) -> None:
    rig = _rig(320, 240, 300.0, 0.1)
    with TestClient(create_app(settings_for(tmp_path), FakeFactory())) as client:
        configs = []
        for payload in (rig.to_dict(), {**rig.to_dict(), "calibration_exact": True}):
            response = client.post("/v1/sessions", headers=A, json={"calibration": payload})
            assert response.status_code == 201, response.text
            configs.append(response.json()["config"])
        response = client.post("/v1/sessions", headers=A, json={
            "calibration": {**rig.to_dict(), "calibration_exact": "yes"}})
        assert response.status_code == 422
    real, exact = (tuple(c["backend"][name] for name in GAINS) for c in configs)
    assert (real, exact) == ((0.01, 0.02), (0.0, 0.0))
    names = {s["name"] for s in configs[1]["rig_settings"]["settings"]}
    assert {f"backend.{name}" for name in GAINS} <= names


def test_rendered_covariances_without_the_gyro_follow_the_flag(synthesized) -> None:
    """The same rendered frames, read as an exact and as a not-exact rig: the reported
    covariances of the moving frames differ by the calibration term only."""
    from estimator.pipeline import build_config, odometry_messages, run_sequence

    sequence = open_sequence(synthesized["euroc"])
    config = build_config(backend=False, imu=False)
    exact = odometry_messages(run_sequence(sequence, config, use_imu=False))
    sequence.rig = StereoRig(sequence.rig.left, sequence.rig.right)  # as a real rig
    real = odometry_messages(run_sequence(sequence, config, use_imu=False))
    traces = [np.trace(m[-1].pose_covariance) for m in (exact, real)]
    assert traces[1] > traces[0] > 0


def test_an_isotropic_registration_keeps_the_real_rig_weights_on_an_exact_rig(synthesized) -> None:
    """The exact rig's floors and weights presume consistent (per-point) covariances; the
    isotropic registration's are not, so it keeps the real-rig values (the gains stay exact)."""
    rig = open_sequence(synthesized["euroc"]).rig
    isotropic = SwarmvoConfig(registration={"use_point_sigmas": False})
    config, derived = apply_rig_settings(isotropic, rig, 0.05)
    assert _gains(config) == (0.0, 0.0)
    assert _floors(config) == REAL_RIG_FIT_FLOOR
    weights = tuple(getattr(config.backend, name) for name in WEIGHTS)
    assert weights == (3.0, 0.0, 0.0)
    floor = next(s for s in derived if s.name == "fit_min_rotation_sigma_rad")
    assert "isotropic" in floor.reason
