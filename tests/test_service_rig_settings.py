"""Rig-derived frontend settings in the service: at session creation (declared rate) or from
the first two frames' stamps; explicit config values win; recorded in the session's config."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from fastapi.testclient import TestClient
from test_driving import RIGS, _rig
from test_service_units import A, FakeFactory, settings_for

from estimator.config import SwarmvoConfig
from estimator.rig_settings import derive_rig_settings
from estimator.types import StereoFrame
from service.app import create_app
from service.estimator_adapter import EstimatorFactory, IntervalSettings


def _expected(name: str, rate: float) -> dict[str, float]:
    width, height, focal, baseline, _ = RIGS[name]
    rig = _rig(width, height, focal, baseline)
    return {s.name: s.value for s in derive_rig_settings(rig, 1 / rate, SwarmvoConfig().frontend)}


def _create(client: TestClient, name: str, **body) -> dict:
    width, height, focal, baseline, _ = RIGS[name]
    response = client.post("/v1/sessions", headers=A,
                           json={"calibration": _rig(width, height, focal, baseline).to_dict(),
                                 **body})
    assert response.status_code == 201, response.text
    return response.json()["config"]


def test_sessions_get_the_settings_of_their_rig(tmp_path: Path) -> None:
    with TestClient(create_app(settings_for(tmp_path), FakeFactory())) as client:
        kitti = _expected("kitti", 10.0)
        config = _create(client, "kitti", frame_rate_hz=10.0)
        assert config["frontend"]["max_depth_m"] == kitti["max_depth_m"] > 200
        assert config["frontend"]["search_radius_px"] == kitti["search_radius_px"] > 100
        record = config["rig_settings"]
        assert record["frame_rate_hz"] == 10.0 and record["from_stamps"] is False
        assert {s["name"] for s in record["settings"]} == {
            "frontend.max_depth_m", "frontend.max_features", "frontend.search_radius_px",
            "frontend.min_search_radius_px", "frontend.chain_common_rotation_bias",
            "backend.calibration_rotation_gain", "backend.calibration_translation_gain",
            "backend.fit_min_rotation_sigma_rad", "backend.fit_min_translation_sigma_m",
            "backend.robust_parameter", "backend.answer_smoothing_s",
            "backend.keyframe_error_correlation"}
        assert config["frontend"]["max_features"] == kitti["max_features"] > 1200
        # Explicit values win; the record says so.
        config = _create(client, "kitti", frame_rate_hz=10.0,
                         config={"frontend": {"max_depth_m": 55.0}})
        assert config["frontend"]["max_depth_m"] == 55.0
        assert config["frontend"]["search_radius_px"] == kitti["search_radius_px"]
        depth = next(s for s in config["rig_settings"]["settings"]
                     if s["name"] == "frontend.max_depth_m")
        assert depth["overridden"] is True
        # No rate: the depth now, the search window from the first frames' stamps.
        config = _create(client, "realsense_d435")
        assert config["frontend"]["max_depth_m"] == _expected("realsense_d435", 30)["max_depth_m"]
        assert config["frontend"]["search_radius_px"] == SwarmvoConfig().frontend.search_radius_px
        assert config["rig_settings"]["from_stamps"] is True
        assert _create(client, "zed", config={"frontend": {"search_radius_px": 33.0}})[
            "rig_settings"]["from_stamps"] is False  # set by the user: nothing to derive
        # A session's config sent back as is (with its record) is accepted.
        again = _create(client, "kitti", config=config)
        assert again["frontend"]["max_depth_m"] == config["frontend"]["max_depth_m"]
        for rate in (0, -5, 1e9):
            response = client.post("/v1/sessions", headers=A, json={
                "calibration": _rig(*RIGS["kitti"][:4]).to_dict(), "frame_rate_hz": rate})
            assert response.status_code == 422


def test_euroc_upload_takes_the_rate_of_its_sensor_yaml(tmp_path: Path, euroc_v101_micro) -> None:
    cam = euroc_v101_micro / "mav0"
    files = {name: (f"{name}.yaml", (cam / name / "sensor.yaml").read_bytes())
             for name in ("cam0", "cam1")}
    with TestClient(create_app(settings_for(tmp_path), FakeFactory())) as client:
        response = client.post("/v1/sessions/euroc", headers=A, files=files)
    assert response.status_code == 201, response.text
    config = response.json()["config"]
    assert config["rig_settings"]["frame_rate_hz"] == 20.0
    # The rig the defaults were tuned on keeps them.
    assert config["frontend"]["search_radius_px"] == pytest.approx(40.0, rel=0.01)
    assert config["frontend"]["max_depth_m"] == pytest.approx(30.0, rel=0.01)


def test_the_search_window_follows_the_first_frames_stamps() -> None:
    factory = EstimatorFactory()
    rig = _rig(*RIGS["kitti"][:4])
    prepared = factory.prepare(rig.to_dict(), {}, None)
    pipeline = factory.create(prepared, None, 0)
    assert isinstance(pipeline, IntervalSettings)
    odometry = pipeline.answers.odometry
    default = SwarmvoConfig().frontend.search_radius_px
    assert odometry.config.frontend.search_radius_px == default
    image = np.zeros((rig.size[1], rig.size[0]), dtype=np.uint8)
    pipeline.process(StereoFrame(0, image, image))
    assert odometry.config.frontend.search_radius_px == default  # one stamp: no interval yet
    pipeline.process(StereoFrame(100_000_000, image, image))  # 10 Hz
    assert odometry.config.frontend.search_radius_px == _expected("kitti", 10.0)[
        "search_radius_px"]
    assert odometry.config.frontend.max_depth_m == _expected("kitti", 10.0)["max_depth_m"]
    # With a declared rate nothing waits for the stamps.
    declared = factory.create(factory.prepare(rig.to_dict(), {}, None, 10.0), None, 0)
    assert not isinstance(declared, IntervalSettings)


def test_a_session_with_swapped_cameras_is_refused_with_the_reason(tmp_path: Path) -> None:
    """The same check as ``swarmvo run``'s: a 4xx naming the swap, no session created."""
    width, height, focal, baseline, _ = RIGS["euroc"]
    calibration = _rig(width, height, focal, baseline).to_dict()
    calibration["left"], calibration["right"] = calibration["right"], calibration["left"]
    with TestClient(create_app(settings_for(tmp_path), FakeFactory())) as client:
        response = client.post("/v1/sessions", headers=A, json={"calibration": calibration})
        assert response.status_code == 422, response.text
        assert "left and right are swapped" in response.text
        assert client.get("/v1/sessions", headers=A).json()["sessions"] == []
