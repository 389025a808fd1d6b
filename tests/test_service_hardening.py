"""Abuse of the API in-process: work limits and validation at creation, deleted sessions,
strict input, refusals counted, the published schema, and a schemathesis run with 0 5xx."""

from __future__ import annotations

import json
import re

import numpy as np
import pytest
from fastapi.testclient import TestClient
from starlette.websockets import WebSocketDisconnect
from test_service_units import (
    A,
    B,
    FakeFactory,
    _ws_frame,
    calibration,
    new_session,
    png,
    send,
    settings_for,
)

from service.app import create_app
from service.images import ImageLimits, decode_image
from service.limits import CONFIG_BOUNDS, OPTION_BOUNDS


@pytest.fixture
def client(tmp_path):
    with TestClient(create_app(settings_for(tmp_path), FakeFactory())) as test_client:
        yield test_client


def _errors(client: TestClient) -> dict[str, float]:
    text = client.get("/metrics").text
    pattern = r'^swarmvo_errors_total\{kind="([^"]+)"\} (\S+)$'
    return {kind: float(value) for kind, value in re.findall(pattern, text, re.M)}


def _camera(model: str, side: str = "left") -> dict:
    camera = calibration()[side]
    distortion = [0.01, 0.0, 0.0, 0.0] if model != "none" else []
    return {**camera, "distortion_model": model, "distortion": distortion}


# ----------------------------------------------------------------------------- creation


@pytest.mark.parametrize(
    ("body", "words"),
    [
        ({"config": {"frontend": {"max_features": 10**9}}}, "frontend.max_features"),
        (
            {"config": {"registration": {"options": {
                "particles": 20000, "max_iterations": 20000, "stagnation": 20000}}}},
            "registration.options.particles",
        ),
        ({"config": {"registration": {"method": "msac", "options": {"max_iterations": 10**6}}}},
         "registration.options.max_iterations"),
        ({"config": {"frontend": {"detector": "sift"}}}, "detector"),
        ({"config": {"backend": {"smoother_lag_s": 30}}}, "smoother_lag_s"),
        ({"calibration": {"left": _camera("equidistant"), "right": _camera("radtan", "right")}},
         "mixed equidistant"),
        ({"config": {"frontend": {"min_depth_m": 50, "max_depth_m": 1}}}, "min_depth_m"),
        ({"config": {"seed": -1}}, "seed: Input should be greater than or equal to 0"),
        ({"config": {"registration": {"options": {"bogus": 1}}}}, "bogus"),
        ({"config": {"registration": {"options": {"particles": "many"}}}}, "registration"),
        ({"calibration": calibration(width=100_000)}, "exceeds the maximum image size"),
    ],
)
def test_sessions_that_cannot_run_are_refused_at_creation(
    client: TestClient, body: dict, words: str
) -> None:
    before = _errors(client).get("bad_session", 0.0)
    response = client.post("/v1/sessions", headers=A, json={"calibration": calibration(), **body})
    assert response.status_code == 422, response.text
    assert words in response.json()["detail"]
    assert _errors(client)["bad_session"] == before + 1
    assert client.get("/v1/sessions", headers=A).json()["sessions"] == []


def test_the_most_expensive_session_within_the_limits_is_accepted(client: TestClient) -> None:
    config: dict = {"frontend": {}, "registration": {}, "backend": {}}
    for bound in CONFIG_BOUNDS:
        config[bound.section][bound.key] = bound.maximum
    config["registration"]["options"] = dict(OPTION_BOUNDS["pso-robust"])
    sid = new_session(client, config=config)
    stored = client.get(f"/v1/sessions/{sid}", headers=A).json()["config"]
    assert stored["frontend"]["max_features"] == config["frontend"]["max_features"]
    assert send(client, sid, 1).status_code == 200


# ----------------------------------------------------------------------------- deletion


def test_deleting_a_streamed_session_closes_the_stream_and_forgets_it(
    client: TestClient,
) -> None:
    sid = new_session(client)
    with client.websocket_connect(f"/v1/sessions/{sid}/stream", headers=A) as ws:
        ws.receive_json()
        _ws_frame(ws, 10)
        assert ws.receive_json()["type"] == "pose"
        assert client.get("/healthz").json()["sessions_active"] == 1
        assert client.delete(f"/v1/sessions/{sid}", headers=A).status_code == 204
        with pytest.raises(WebSocketDisconnect) as closed:
            for _ in range(3):
                ws.receive_json()
        assert (closed.value.code, closed.value.reason) == (4404, "session deleted")
    assert send(client, sid, 20).status_code == 404
    imu = {"samples": [{"timestamp_ns": 30, "gyro": [0, 0, 0], "accel": [0, 0, 9.8]}]}
    assert client.post(f"/v1/sessions/{sid}/imu", headers=A, json=imu).status_code == 404
    assert client.delete(f"/v1/sessions/{sid}", headers=A).status_code == 404
    assert client.get("/healthz").json()["sessions_active"] == 0
    with pytest.raises(Exception) as refused, client.websocket_connect(
        f"/v1/sessions/{sid}/stream", headers=A
    ):
        pass
    assert getattr(refused.value, "status_code", None) == 404


def test_a_session_looked_up_before_its_deletion_stays_deleted(client: TestClient) -> None:
    sid = new_session(client)
    state = client.app.state.swarmvo
    record = state.store.get_session(sid)
    assert client.delete(f"/v1/sessions/{sid}", headers=A).status_code == 204
    from service.sessions import SessionGone

    with pytest.raises(SessionGone):
        state.manager.live_session(record)  # a request that passed its lookup just before
    assert sid not in state.manager.live


def test_database_errors_never_reach_a_client(client: TestClient, monkeypatch) -> None:
    from sqlalchemy.exc import IntegrityError

    sid = new_session(client)
    store = client.app.state.swarmvo.store

    def broken(*_args, **_kwargs):
        raise IntegrityError(
            "INSERT INTO poses (session_id, frame_index) VALUES (?, ?)", ("secret-id", 0),
            Exception("FOREIGN KEY constraint failed"),
        )

    monkeypatch.setattr(store, "add_poses", broken)
    response = send(client, sid, 10)
    assert response.status_code == 503
    detail = response.json()["detail"]
    assert "could not be stored" in detail
    for leak in ("INSERT", "sqlalchemy", "FOREIGN KEY", "secret-id", "poses"):
        assert leak not in detail
    monkeypatch.undo()
    assert send(client, sid, 10).status_code == 200


# ----------------------------------------------------------------------------- strict input


@pytest.mark.parametrize("text", ["1_403_715_273_312_143_104", "  5  ", "\u0665", "+5", "5.0"])
def test_timestamps_are_plain_ascii_digits(client: TestClient, text: str) -> None:
    sid = new_session(client)
    response = client.post(
        f"/v1/sessions/{sid}/frames", headers=A, data={"timestamp_ns": text},
        files={"left": ("l.png", png()), "right": ("r.png", png(value=3))},
    )
    assert response.status_code == 422 and "ASCII digits" in response.json()["detail"]
    assert send(client, sid, 5).status_code == 200


@pytest.mark.parametrize("vector", [[False, 0, 0], [0, True, 0], ["1", 0, 0]])
def test_imu_vectors_take_numbers_only(client: TestClient, vector: list) -> None:
    sid = new_session(client)
    sample = {"timestamp_ns": 1, "gyro": vector, "accel": [0, 0, 9.8]}
    response = client.post(f"/v1/sessions/{sid}/imu", headers=A, json={"samples": [sample]})
    assert response.status_code == 422, response.text
    ok = {**sample, "gyro": [0, 0.5, 1]}  # integers are numbers
    assert client.post(f"/v1/sessions/{sid}/imu", headers=A, json={"samples": [ok]}).json() == {
        "accepted": 1, "buffered": 1}


def test_a_png_with_bytes_after_iend_is_accepted(client: TestClient) -> None:
    padded = png() + b"\x00" * 16
    limits = ImageLimits(1000, 1000, 10**6)
    np.testing.assert_array_equal(decode_image(padded, "left", limits),
                                  decode_image(png(), "left", limits))
    with pytest.raises(ValueError, match="truncated PNG"):
        decode_image(png()[:-20] + b"IEND" + b"\x00" * 8, "left", limits)
    sid = new_session(client)
    assert send(client, sid, 1, left=padded, right=png(value=3) + b"junk").status_code == 200


def test_every_refusal_is_counted_by_kind(client: TestClient) -> None:
    sid = new_session(client)
    frames = f"/v1/sessions/{sid}/frames"
    refusals = [
        (lambda: client.post(frames, headers={**A, "content-type": "text/plain"}, content=b"x"),
         415, "media_type"),
        (lambda: client.post(frames, headers=A, files={"left": png()}), 422, "validation"),
        (lambda: client.post(
            frames, headers={**A, "content-type": "multipart/form-data"}, content=b"garbage"),
         400, "malformed"),
        (lambda: client.get("/v1/sessions", headers={"Authorization": "Bearer nope"}), 401,
         "auth"),
        (lambda: client.get("/v1/sessions/" + "0" * 32, headers=A), 404, "unknown_session"),
        (lambda: client.get("/nowhere"), 404, "not_found"),
        (lambda: send(client, sid, 10, left=b"junk", right=b"junk"), 422, "bad_image"),
    ]
    for request, status, kind in refusals:
        before = _errors(client).get(kind, 0.0)
        response = request()
        assert response.status_code == status, response.text
        assert _errors(client).get(kind) == before + 1, kind


# ----------------------------------------------------------------------------- schema


def test_the_schema_documents_the_text_trajectory(client: TestClient) -> None:
    schema = client.get("/openapi.json").json()
    for path in ("/v1/sessions/{session_id}/trajectory", "/v1/sessions/{session_id}/smoothed"):
        answers = schema["paths"][path]["get"]["responses"]
        assert {"application/json", "text/plain"} <= set(answers["200"]["content"]), path
    sid = new_session(client)
    send(client, sid, 1)
    tum = client.get(f"/v1/sessions/{sid}/trajectory?format=tum", headers=A)
    assert tum.headers["content-type"].startswith("text/plain")


def test_schemathesis_finds_no_server_error(client: TestClient) -> None:
    """Every operation of the published schema with generated input: never a 5xx."""
    import schemathesis
    from hypothesis import HealthCheck, given, settings

    sid = new_session(client)
    new_session(client, headers=B)
    schema = schemathesis.openapi.from_asgi("/openapi.json", client.app)
    failures: list[str] = []
    calls = 0

    for operation in schema.get_all_operations():
        operation = operation.ok()

        @settings(max_examples=6, deadline=None, derandomize=True,
                  suppress_health_check=list(HealthCheck))
        @given(case=operation.as_strategy())
        def check(case) -> None:
            nonlocal calls
            if "session_id" in (case.path_parameters or {}) and calls % 2:
                case.path_parameters["session_id"] = sid  # reach the session's code paths
            response = case.call(headers=A)
            calls += 1
            if response.status_code >= 500:
                failures.append(f"{case.method} {case.formatted_path}: {response.status_code}")

        check()
    assert calls >= 50
    assert failures == [], failures
    assert client.get("/healthz").status_code == 200
    assert json.loads(client.get("/openapi.json").text)["openapi"]
