"""Service internals with an in-process app: validation, ownership, queueing, persistence.

The odometry is replaced by a small deterministic pipeline (defined here) so these tests are
fast and can make frames slow on purpose; the real pipeline is exercised against a real server
in test_service_server.py.
"""

from __future__ import annotations

import json
import os
import signal
import struct
import threading
import time
import zlib
from pathlib import Path

import cv2
import numpy as np
import pytest
from fastapi.testclient import TestClient
from pydantic import ValidationError
from test_service_server import process_alive

from estimator.types import FrameReport, FrameStatus, ImuBatch, StereoFrame
from service.answer import FrameAnswer, flat_of, matrix_of
from service.app import create_app
from service.auth import AuthError, owner_for
from service.estimator_adapter import EstimatorFactory, PreparedSession
from service.images import ImageError, ImageLimits, decode_image, decode_pair, image_size
from service.messages import SERVER_MESSAGE
from service.settings import ServiceSettings, hash_key
from service.storage import Store

WIDTH, HEIGHT = 64, 48
KEY_A, KEY_B = "key-alpha", "key-bravo"
A = {"Authorization": f"Bearer {KEY_A}"}
B = {"Authorization": f"Bearer {KEY_B}"}


def calibration(width: int = WIDTH, height: int = HEIGHT) -> dict:
    def camera(x: float) -> dict:
        transform = np.eye(4)
        transform[0, 3] = x
        return {
            "width": width,
            "height": height,
            "fx": 50.0,
            "fy": 50.0,
            "cx": width / 2,
            "cy": height / 2,
            "distortion_model": "none",
            "distortion": [],
            "T_BS": transform.tolist(),
        }

    return {"left": camera(0.0), "right": camera(0.1)}


class RecordingPipeline:
    """Moves 1 cm along x per frame; records what it was given; optionally slow."""

    def __init__(self, initial_pose: np.ndarray | None, first_index: int, delay: float) -> None:
        self.pose = np.eye(4) if initial_pose is None else initial_pose.copy()
        self.index = first_index - 1
        self.delay = delay
        self.initial_pose = initial_pose
        self.imu_seen: list[ImuBatch | None] = []
        self.last_ns: int | None = None
        self.busy: list[tuple[float, float]] = []  # (start, end) of each frame's work

    def process(self, frame: StereoFrame, imu: ImuBatch | None = None) -> FrameReport:
        if self.last_ns is not None and frame.timestamp_ns <= self.last_ns:
            raise ValueError("timestamps must increase")
        if frame.left.shape[:2] != (HEIGHT, WIDTH):
            raise ValueError("wrong image size")
        started = time.perf_counter()
        time.sleep(self.delay)
        self.busy.append((started, time.perf_counter()))
        self.imu_seen.append(imu)
        self.index += 1
        relative = np.eye(4)
        if self.last_ns is not None:
            relative[0, 3] = 0.01
        self.pose = self.pose @ relative
        self.last_ns = frame.timestamp_ns
        return FrameReport(
            index=self.index,
            timestamp_ns=frame.timestamp_ns,
            pose=self.pose.copy(),
            frontend_pose=self.pose.copy(),
            relative_pose=relative,
            status=FrameStatus.OK,
            matches=10,
            inliers=8,
            support=9,
            timings_s={"fake": 0.001},
        )


class FakeFactory(EstimatorFactory):
    """Real calibration/config validation, fake odometry."""

    def __init__(self, delay: float = 0.0) -> None:
        self.delay = delay
        self.created: list[RecordingPipeline] = []

    def create(self, prepared: PreparedSession, initial_pose, first_index):  # type: ignore[override]
        pipeline = RecordingPipeline(initial_pose, first_index, self.delay)
        self.created.append(pipeline)
        return pipeline


def png(width: int = WIDTH, height: int = HEIGHT, value: int = 0, dtype=np.uint8) -> bytes:
    image = (np.arange(width * height).reshape(height, width) + value).astype(dtype)
    ok, data = cv2.imencode(".png", image)
    assert ok
    return data.tobytes()


def settings_for(tmp_path: Path, **overrides) -> ServiceSettings:
    """Thread executor unless overridden: the test doubles are inspected in this process."""
    values = {"data_dir": tmp_path, "api_keys": f"{KEY_A},{KEY_B}", "workers": 2,
              "executor": "thread"}
    values.update(overrides)
    return ServiceSettings(**values)


@pytest.fixture
def factory() -> FakeFactory:
    return FakeFactory()


@pytest.fixture
def client(tmp_path: Path, factory: FakeFactory):
    with TestClient(create_app(settings_for(tmp_path), factory)) as test_client:
        yield test_client


def new_session(client: TestClient, headers=A, **body) -> str:
    response = client.post(
        "/v1/sessions", headers=headers, json={"calibration": calibration(), **body}
    )
    assert response.status_code == 201, response.text
    return response.json()["id"]


def send(client: TestClient, sid: str, t: int, headers=A, imu=None, left=None, right=None):
    data = {"timestamp_ns": str(t)}
    if imu is not None:
        data["imu"] = json.dumps({"samples": imu})
    files = {"left": ("l.png", left or png()), "right": ("r.png", right or png(value=3))}
    return client.post(f"/v1/sessions/{sid}/frames", headers=headers, data=data, files=files)


# ----------------------------------------------------------------------------- images


def test_image_headers_and_decoding_16bit_and_colour() -> None:
    limits = ImageLimits(100, 100, 10_000)
    assert image_size(png(), "x") == (WIDTH, HEIGHT)
    grey16 = decode_image(png(dtype=np.uint16, value=4000), "x", limits)
    assert grey16.dtype == np.uint16 and grey16.shape == (HEIGHT, WIDTH)
    colour = np.zeros((HEIGHT, WIDTH, 3), np.uint8)
    colour[..., 2] = 200
    jpeg = cv2.imencode(".jpg", colour)[1].tobytes()
    assert image_size(jpeg, "x") == (WIDTH, HEIGHT)
    assert decode_image(jpeg, "x", limits).shape == (HEIGHT, WIDTH, 3)
    bgra = cv2.imencode(".png", np.zeros((HEIGHT, WIDTH, 4), np.uint8))[1].tobytes()
    assert decode_image(bgra, "x", limits).shape == (HEIGHT, WIDTH, 3)


def _png_header_only(width: int, height: int) -> bytes:
    ihdr = struct.pack(">IIBBBBB", width, height, 8, 0, 0, 0, 0)
    chunk = struct.pack(">I", 13) + b"IHDR" + ihdr + struct.pack(">I", zlib.crc32(b"IHDR" + ihdr))
    end = struct.pack(">I", 0) + b"IEND" + struct.pack(">I", zlib.crc32(b"IEND"))
    return b"\x89PNG\r\n\x1a\n" + chunk + end


@pytest.mark.parametrize(
    ("data", "status", "words"),
    [
        (b"", 422, "empty"),
        (b"GIF89a....", 422, "not a PNG or JPEG"),
        (png()[: len(png()) // 2], 422, "truncated PNG"),
        (_png_header_only(100_000, 100_000), 413, "exceeds"),
        (_png_header_only(90, 90), 413, "pixels"),
        (_png_header_only(50, 50), 422, "could not be decoded"),
        (cv2.imencode(".jpg", np.zeros((8, 8), np.uint8))[1].tobytes()[:-40], 422, "JPEG"),
    ],
)
def test_bad_images_are_refused_with_a_reason(data: bytes, status: int, words: str) -> None:
    with pytest.raises(ImageError) as info:
        decode_image(data, "left", ImageLimits(200_000, 200_000, 8000))
    assert info.value.status_code == status
    assert words in str(info.value)


def test_pair_must_match_each_other_and_the_calibration() -> None:
    limits = ImageLimits(1000, 1000, 10**6)
    with pytest.raises(ImageError, match="differ"):
        decode_pair(png(), png(width=WIDTH + 2), limits, (WIDTH, HEIGHT))
    with pytest.raises(ImageError, match="calibration is for"):
        decode_pair(png(), png(), limits, (WIDTH + 1, HEIGHT))


# ----------------------------------------------------------------------------- auth, settings


def test_auth_rules() -> None:
    closed = ServiceSettings(api_keys="a, b")
    assert owner_for("a", closed) == hash_key("a")
    for token in (None, "c"):
        with pytest.raises(AuthError):
            owner_for(token, closed)
    with pytest.raises(ValueError, match="no API keys"):
        ServiceSettings().check_startable()
    ServiceSettings(open=True).check_startable()
    assert owner_for(None, ServiceSettings(open=True)) != owner_for("x", ServiceSettings(open=True))


def test_keys_are_stored_hashed(client: TestClient, tmp_path: Path) -> None:
    new_session(client)
    raw = b"".join(p.read_bytes() for p in tmp_path.glob("swarmvo.sqlite3*"))  # + WAL file
    assert KEY_A.encode() not in raw
    assert hash_key(KEY_A).encode() in raw


# ----------------------------------------------------------------------------- sessions


def test_session_crud_and_ownership(client: TestClient) -> None:
    sid = new_session(client, name="robot-1", config={"seed": 5})
    got = client.get(f"/v1/sessions/{sid}", headers=A).json()
    assert got["name"] == "robot-1" and got["config"]["seed"] == 5
    assert (got["image_width"], got["image_height"]) == (WIDTH, HEIGHT)
    assert client.get(f"/v1/sessions/{sid}", headers=B).status_code == 404
    assert [s["id"] for s in client.get("/v1/sessions", headers=A).json()["sessions"]] == [sid]
    assert client.get("/v1/sessions", headers=B).json()["sessions"] == []
    assert send(client, sid, 1, headers=B).status_code == 404
    assert client.delete(f"/v1/sessions/{sid}", headers=B).status_code == 404
    assert client.delete(f"/v1/sessions/{sid}", headers=A).status_code == 204
    assert client.get(f"/v1/sessions/{sid}", headers=A).status_code == 404


@pytest.mark.parametrize(
    ("body", "words"),
    [
        ({"calibration": {"left": {}}}, "right"),
        ({"calibration": {**calibration(), "left": {**calibration()["left"], "fx": -1}}}, "focal"),
        ({"calibration": calibration(), "config": {"bogus": 1}}, "bogus"),
        ({"calibration": calibration(), "config": {"seed": "x"}}, "seed"),
        ({"calibration": calibration(), "imu_noise": {"rate_hz": 0}}, "rate_hz"),
        ({"calibration": calibration(), "extra": 1}, "extra"),
    ],
)
def test_bad_session_bodies_get_422(client: TestClient, body: dict, words: str) -> None:
    response = client.post("/v1/sessions", headers=A, json=body)
    assert response.status_code == 422, response.text
    assert words in response.json()["detail"]


@pytest.mark.parametrize("where", ["calibration", "config", "imu_noise"])
def test_nan_and_inf_are_refused_everywhere(client: TestClient, where: str) -> None:
    body: dict = {"calibration": calibration()}
    if where == "calibration":
        body["calibration"]["left"]["cx"] = float("nan")
    elif where == "config":
        body["config"] = {"registration": {"options": {"particles": float("inf")}}}
    else:
        body["imu_noise"] = {"gyro_noise_density": float("nan")}
    text = json.dumps(body)  # Python writes NaN/Infinity tokens
    response = client.post(
        "/v1/sessions", headers={**A, "content-type": "application/json"}, content=text
    )
    assert response.status_code == 422, response.text
    sid = new_session(client)
    imu = '{"samples": [{"timestamp_ns": 1, "gyro": [NaN, 0, 0], "accel": [0, 0, 9.8]}]}'
    response = client.post(
        f"/v1/sessions/{sid}/imu", headers={**A, "content-type": "application/json"}, content=imu
    )
    assert response.status_code == 422
    response = client.post(
        f"/v1/sessions/{sid}/frames",
        headers=A,
        data={"timestamp_ns": "5", "imu": imu},
        files={"left": png(), "right": png()},
    )
    assert response.status_code == 422


def test_session_limit_per_key(tmp_path: Path, factory: FakeFactory) -> None:
    with TestClient(create_app(settings_for(tmp_path, max_sessions_per_key=2), factory)) as c:
        new_session(c)
        new_session(c)
        response = c.post("/v1/sessions", headers=A, json={"calibration": calibration()})
        assert response.status_code == 429 and "limit" in response.json()["detail"]
        new_session(c, headers=B)  # the limit is per key


def test_euroc_and_kitti_uploads(client: TestClient, euroc_v101_micro: Path) -> None:
    mav0 = euroc_v101_micro / "mav0"
    response = client.post(
        "/v1/sessions/euroc",
        headers=A,
        files={
            "cam0": (mav0 / "cam0/sensor.yaml").read_bytes(),
            "cam1": (mav0 / "cam1/sensor.yaml").read_bytes(),
            "imu0": (mav0 / "imu0/sensor.yaml").read_bytes(),
        },
        data={"config": json.dumps({"seed": 2})},
    )
    assert response.status_code == 201, response.text
    body = response.json()
    assert (body["image_width"], body["image_height"]) == (752, 480)
    assert body["imu_noise"]["gyro_noise_density"] == pytest.approx(1.6968e-4)
    broken = client.post(
        "/v1/sessions/euroc", headers=A, files={"cam0": b"resolution: [1, 2", "cam1": b"x: 1"}
    )
    assert broken.status_code == 422
    assert "/tmp" not in broken.json()["detail"]
    calib = b"P0: 700 0 600 0 0 700 180 0 0 0 1 0\nP1: 700 0 600 -378 0 700 180 0 0 0 1 0\n"
    kitti = client.post(
        "/v1/sessions/kitti",
        headers=A,
        files={"calib": calib},
        data={"width": "1241", "height": "376"},
    )
    assert kitti.status_code == 201, kitti.text
    assert kitti.json()["calibration"]["right"]["T_BS"][0][3] == pytest.approx(0.54)
    no_size = client.post("/v1/sessions/kitti", headers=A, files={"calib": calib})
    assert no_size.status_code == 422


# ----------------------------------------------------------------------------- frames


def test_frames_poses_order_and_trajectory(client: TestClient) -> None:
    sid = new_session(client)
    for k, t in enumerate((100, 200, 300)):
        response = send(client, sid, t)
        assert response.status_code == 200, response.text
        body = response.json()
        assert body["index"] == k and body["timestamp_ns"] == t and body["status"] == "ok"
        assert body["pose"][0][3] == pytest.approx(0.01 * k)
        assert {"queue_wait", "decode", "odometry", "persist", "total"} <= set(body["timings_s"])
    late = send(client, sid, 250)
    assert late.status_code == 409 and "does not increase" in late.json()["detail"]
    # A resent frame is answered from its stored pose, not processed a second time.
    again = send(client, sid, 300)
    assert again.status_code == 200 and again.json()["index"] == 2
    assert again.json()["pose"] == body["pose"]
    wrong = send(client, sid, 400, left=png(width=WIDTH + 8), right=png(width=WIDTH + 8))
    assert wrong.status_code == 422 and "calibration" in wrong.json()["detail"]
    # The refused frame does not block a retry with its timestamp.
    assert send(client, sid, 400).status_code == 200
    trajectory = client.get(f"/v1/sessions/{sid}/trajectory", headers=A).json()["poses"]
    assert [p["timestamp_ns"] for p in trajectory] == [100, 200, 300, 400]
    tum = client.get(f"/v1/sessions/{sid}/trajectory?format=tum", headers=A).text.splitlines()
    assert tum[1].startswith("0.000000100 0 0 0") and len(tum) == 5
    kitti = client.get(f"/v1/sessions/{sid}/trajectory?format=kitti", headers=A).text
    assert len(kitti.splitlines()) == 4
    assert float(kitti.splitlines()[3].split()[3]) == pytest.approx(0.03)
    assert client.get(f"/v1/sessions/{sid}/trajectory?format=xml", headers=A).status_code == 422


def test_imu_buffer_is_split_by_frame_time(client: TestClient, factory: FakeFactory) -> None:
    sid = new_session(client)

    def sample(t: int) -> dict:
        return {"timestamp_ns": t, "gyro": [0.1, 0, 0], "accel": [0, 0, 9.81]}

    response = client.post(
        f"/v1/sessions/{sid}/imu", headers=A, json={"samples": [sample(t) for t in (50, 90, 150)]}
    )
    assert response.json() == {"accepted": 3, "buffered": 3}
    assert send(client, sid, 100).json()["imu_samples"] == 2  # 50, 90
    # Inline samples merge with the buffer; duplicates count once; stale ones are ignored.
    body = send(client, sid, 200, imu=[sample(80), sample(150), sample(180), sample(250)]).json()
    assert body["imu_samples"] == 2  # 150, 180
    assert send(client, sid, 300).json()["imu_samples"] == 1  # 250
    assert send(client, sid, 400).json()["imu_samples"] == 0
    seen = factory.created[0].imu_seen
    assert seen[0].timestamps_ns.tolist() == [50, 90]
    assert seen[1].timestamps_ns.tolist() == [150, 180]
    assert seen[2].timestamps_ns.tolist() == [250]
    assert seen[3] is None


def test_imu_batch_limits(tmp_path: Path, factory: FakeFactory) -> None:
    settings = settings_for(tmp_path, max_imu_batch=3, max_imu_buffer=4)
    with TestClient(create_app(settings, factory)) as c:
        sid = new_session(c)
        samples = [{"timestamp_ns": t, "gyro": [0, 0, 0], "accel": [0, 0, 0]} for t in range(4)]
        response = c.post(f"/v1/sessions/{sid}/imu", headers=A, json={"samples": samples})
        assert response.status_code == 413
        assert (
            c.post(f"/v1/sessions/{sid}/imu", headers=A, json={"samples": samples[:3]}).status_code
            == 200
        )
        full = c.post(f"/v1/sessions/{sid}/imu", headers=A, json={"samples": samples[:2]})
        assert full.status_code == 429 and "buffer" in full.json()["detail"]


def test_request_size_limit(tmp_path: Path, factory: FakeFactory) -> None:
    with TestClient(create_app(settings_for(tmp_path, max_request_bytes=4096), factory)) as c:
        sid = new_session(c)
        big = png(200, 200, dtype=np.uint16)
        assert len(big) > 4096
        response = send(c, sid, 1, left=big, right=big)
        assert response.status_code == 413
        assert "limit" in response.json()["detail"]

        def chunks():
            yield b"x" * 3000
            yield b"x" * 3000

        streamed = c.post(
            f"/v1/sessions/{sid}/imu",
            headers={**A, "content-type": "application/json"},
            content=chunks(),
        )
        assert streamed.status_code == 413


def test_restart_keeps_everything_and_resumes(tmp_path: Path) -> None:
    factory = FakeFactory()
    with TestClient(create_app(settings_for(tmp_path), factory)) as c:
        sid = new_session(c)
        first = [send(c, sid, t).json() for t in (10, 20, 30)]
    factory = FakeFactory()
    with TestClient(create_app(settings_for(tmp_path), factory)) as c:
        stored = c.get(f"/v1/sessions/{sid}/trajectory", headers=A).json()["poses"]
        assert [p["pose"] for p in stored] == [p["pose"] for p in first]
        assert send(c, sid, 25).status_code == 409  # order is kept across restarts
        resumed = send(c, sid, 40).json()
        assert resumed["resumed"] is True and "resumed from the stored pose" in resumed["message"]
        assert resumed["index"] == 3
        pipeline = factory.created[0]
        np.testing.assert_array_equal(pipeline.initial_pose, np.array(first[-1]["pose"]))
        assert send(c, sid, 50).json()["resumed"] is False
        assert c.get(f"/v1/sessions/{sid}", headers=A).json()["resume_count"] == 1
        assert len(c.get(f"/v1/sessions/{sid}/trajectory", headers=A).json()["poses"]) == 5


def test_pipeline_crash_is_contained(tmp_path: Path) -> None:
    class Exploding(FakeFactory):
        def create(self, prepared, initial_pose, first_index):  # type: ignore[override]
            pipeline = super().create(prepared, initial_pose, first_index)
            if len(self.created) == 1:

                def explode(frame, imu=None):
                    raise RuntimeError("boom")

                pipeline.process = explode  # type: ignore[method-assign]
            return pipeline

    factory = Exploding()
    with TestClient(create_app(settings_for(tmp_path), factory)) as c:
        sid = new_session(c)
        failed = send(c, sid, 1)
        assert failed.status_code == 500 and "boom" in failed.json()["detail"]
        ok = send(c, sid, 1)  # same timestamp may be retried; a fresh pipeline is built
        assert ok.status_code == 200
        assert c.get("/healthz").status_code == 200
        assert 'swarmvo_errors_total{kind="internal"} 1.0' in c.get("/metrics").text


# ----------------------------------------------------------------------------- WebSocket


def _ws_frame(ws, t: int, left: bytes | None = None, right: bytes | None = None, split=False):
    left, right = left or png(), right or png(value=2)
    ws.send_text(
        json.dumps(
            {"type": "frame", "timestamp_ns": t, "left_bytes": len(left), "right_bytes": len(right)}
        )
    )
    if split:
        ws.send_bytes(left)
        ws.send_bytes(right)
    else:
        ws.send_bytes(left + right)


def test_websocket_protocol_and_auth(client: TestClient) -> None:
    sid = new_session(client)
    with client.websocket_connect(f"/v1/sessions/{sid}/stream", headers=A) as ws:
        hello = ws.receive_json()
        assert hello["type"] == "hello" and hello["next_index"] == 0
        _ws_frame(ws, 10)
        _ws_frame(ws, 20, split=True)
        ws.send_text("not json")
        ws.send_bytes(b"orphan")
        _ws_frame(ws, 15)  # out of order
        ws.send_text(json.dumps({"type": "imu", "samples": [{"timestamp_ns": 25}]}))
        ws.send_text(
            json.dumps({"type": "frame", "timestamp_ns": "x", "left_bytes": 1, "right_bytes": 1})
        )
        _ws_frame(ws, 30, left=b"garbage!", right=b"garbage!")
        ws.send_text(json.dumps({"type": "ping"}))
        ws.send_text(json.dumps({"type": "nope"}))
        ws.send_text(json.dumps({"type": "close"}))
        replies = []
        while True:
            try:
                replies.append(ws.receive_json())
            except Exception:
                break
    kinds = [(r["type"], r.get("timestamp_ns")) for r in replies]
    assert kinds[:2] == [("pose", 10), ("pose", 20)]
    assert [r["type"] for r in replies[2:]] == [
        "error",
        "error",
        "rejected",
        "error",
        "rejected",
        "rejected",
        "pong",
        "error",
        "smoothed",  # the last message: the back end's flushed window (none here)
    ]
    assert replies[-1]["poses"] == []
    for reply in [hello, *replies]:  # every answer is one of the documented messages
        SERVER_MESSAGE.validate_python(reply)
    assert replies[4]["status"] == 409
    assert "samples.0.gyro: Field required" in replies[5]["detail"]
    assert replies[6]["timestamp_ns"] == "x" and "timestamp_ns: " in replies[6]["detail"]
    assert "unknown message type 'nope'" in replies[9]["detail"]
    assert replies[7]["status"] == 422 and "PNG or JPEG" in replies[7]["detail"]
    # with a token query parameter, and refused without credentials / for another key
    with client.websocket_connect(f"/v1/sessions/{sid}/stream?token={KEY_A}") as ws:
        assert ws.receive_json()["next_index"] == 2
    for url, headers in (
        (f"/v1/sessions/{sid}/stream", {}),
        (f"/v1/sessions/{sid}/stream", B),
        ("/v1/sessions/nope/stream", A),
    ):
        with pytest.raises(Exception) as info, client.websocket_connect(url, headers=headers):
            pass
        assert getattr(info.value, "status_code", None) in (401, 404)


@pytest.mark.parametrize("policy", ["reject", "drop_oldest"])
def test_websocket_queue_policy_answers_every_frame(tmp_path: Path, policy: str) -> None:
    factory = FakeFactory(delay=0.15)
    settings = settings_for(tmp_path, queue_size=2, queue_policy=policy)
    frames = 8
    with TestClient(create_app(settings, factory)) as c:
        sid = new_session(c)
        with c.websocket_connect(f"/v1/sessions/{sid}/stream", headers=A) as ws:
            assert ws.receive_json()["queue_policy"] == policy
            for k in range(frames):
                _ws_frame(ws, 100 + k)
            replies = [ws.receive_json() for _ in range(frames)]
        metrics = c.get("/metrics").text
    assert [r["timestamp_ns"] for r in replies] == [100 + k for k in range(frames)]
    kinds = [r["type"] for r in replies]
    expected_skip = "rejected" if policy == "reject" else "dropped"
    assert kinds[0] == "pose"
    if policy == "drop_oldest":
        assert kinds[-1] == "pose"  # the newest frame is never the one dropped
    assert expected_skip in kinds and set(kinds) == {"pose", expected_skip}
    skipped = kinds.count(expected_skip)
    assert f'swarmvo_frames_dropped_total{{policy="{policy}"}} {float(skipped)}' in metrics
    if policy == "reject":
        assert all(r["status"] == 429 for r in replies if r["type"] == "rejected")
    poses = [r for r in replies if r["type"] == "pose"]
    assert [p["index"] for p in poses] == list(range(len(poses)))


def test_a_full_queue_refuses_a_frame_from_its_header(tmp_path: Path) -> None:
    """With the queue full when a header arrives, the frame is refused at once: its images are
    not needed for the answer (the server neither keeps nor copies them)."""
    factory = FakeFactory(delay=2.0)
    settings = settings_for(tmp_path, queue_size=1, queue_policy="reject")
    with TestClient(create_app(settings, factory)) as c:
        sid = new_session(c)
        with c.websocket_connect(f"/v1/sessions/{sid}/stream", headers=A) as ws:
            ws.receive_json()
            _ws_frame(ws, 1)  # in the worker
            _ws_frame(ws, 2)  # queued: the queue is full
            left = png()
            ws.send_text(json.dumps({"type": "frame", "timestamp_ns": 3,
                                     "left_bytes": len(left), "right_bytes": len(left)}))
            _ws_frame(ws, 4)  # its header ends frame 3, whose images never came
            ws.send_text(json.dumps({"type": "close"}))
            replies = [ws.receive_json() for _ in range(5)]
    assert [(r["type"], r.get("timestamp_ns")) for r in replies] == [
        ("pose", 1), ("pose", 2), ("rejected", 3), ("rejected", 4), ("smoothed", None)]
    assert replies[2]["status"] == 429 and "queue full" in replies[2]["detail"]


def test_concurrent_sessions_use_the_pool(tmp_path: Path) -> None:
    """Two sessions' frames are worked on at the same time (two pool threads), not in turn."""
    factory = FakeFactory(delay=0.5)
    with TestClient(create_app(settings_for(tmp_path, workers=2), factory)) as c:
        sids = [new_session(c), new_session(c)]
        results: dict[str, list[int]] = {}

        def run(sid: str) -> None:
            results[sid] = [send(c, sid, t).status_code for t in (1, 2)]

        threads = [threading.Thread(target=run, args=(s,)) for s in sids]
        for thread in threads:
            thread.start()
        for thread in threads:
            thread.join()
    assert all(codes == [200, 200] for codes in results.values())
    first, second = (pipeline.busy for pipeline in factory.created)
    assert len(first) == len(second) == 2
    # Overlap, whatever the machine's load: one pool thread would run them one after the other.
    overlapping = [(a, b) for a in first for b in second if a[0] < b[1] and b[0] < a[1]]
    assert overlapping, (first, second)


def test_storage_round_trip_is_exact(tmp_path: Path) -> None:
    store = Store.open(f"sqlite:///{tmp_path / 'db.sqlite3'}")
    record = store.create_session("o", "n", calibration(), {}, None, (WIDTH, HEIGHT))
    rng = np.random.default_rng(0)
    values = [float(v) for v in rng.normal(size=16) * 1e-3 + np.pi]
    matrix = matrix_of(values)
    store.add_pose(FrameAnswer(
        session_id=record.id, index=0, timestamp_ns=2**62, pose=matrix, frontend_pose=matrix,
        relative_pose=matrix, status="ok", matches=0, inliers=0, support=0, timings_s={},
        message="", resumed=False,
    ))
    store.close()
    again = Store.open(f"sqlite:///{tmp_path / 'db.sqlite3'}")  # migrations are idempotent
    pose = again.last_pose(record.id)
    assert pose is not None and flat_of(pose.pose) == values and pose.timestamp_ns == 2**62
    assert again.get_session(record.id, "other") is None


def test_migrations_match_the_models_and_render_for_postgresql(tmp_path: Path) -> None:
    import io

    from alembic.autogenerate import compare_metadata
    from alembic.command import upgrade
    from alembic.config import Config
    from alembic.migration import MigrationContext

    from service.storage import MIGRATIONS_DIR, Base

    store = Store.open(f"sqlite:///{tmp_path / 'db.sqlite3'}")
    with store.engine.connect() as connection:
        differences = compare_metadata(MigrationContext.configure(connection), Base.metadata)
    store.close()
    assert differences == []
    config = Config(output_buffer=io.StringIO())
    config.set_main_option("script_location", str(MIGRATIONS_DIR))
    config.set_main_option("sqlalchemy.url", "postgresql+psycopg://user:pw@localhost/swarmvo")
    upgrade(config, "head", sql=True)  # offline: renders the DDL without a server
    ddl = config.output_buffer.getvalue()
    assert "CREATE TABLE poses" in ddl and "BIGINT" in ddl and "ON DELETE CASCADE" in ddl


def test_serve_refuses_to_start_without_keys(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    from estimator.cli.main import main

    for name in ("SWARMVO_API_KEYS", "SWARMVO_OPEN"):
        monkeypatch.delenv(name, raising=False)
    assert main(["serve", "--data-dir", str(tmp_path), "--port", "1"]) == 2
    error = capsys.readouterr().err
    assert "swarmvo serve: error: no API keys configured" in error and "--open" in error


def test_frames_of_a_client_that_hangs_up_are_still_stored(tmp_path: Path) -> None:
    factory = FakeFactory(delay=0.1)
    with TestClient(create_app(settings_for(tmp_path), factory)) as c:
        sid = new_session(c)
        with c.websocket_connect(f"/v1/sessions/{sid}/stream", headers=A) as ws:
            ws.receive_json()
            for t in (1, 2, 3):
                _ws_frame(ws, t)
            time.sleep(0.05)  # the frames reach the server; then the client vanishes
        deadline = time.monotonic() + 10
        stored: list = []
        while time.monotonic() < deadline and len(stored) < 3:
            time.sleep(0.1)
            stored = c.get(f"/v1/sessions/{sid}/trajectory", headers=A).json()["poses"]
        assert [p["timestamp_ns"] for p in stored] == [1, 2, 3]


def test_imu_sent_with_a_refused_frame_is_kept(client: TestClient, factory: FakeFactory) -> None:
    sid = new_session(client)
    samples = [{"timestamp_ns": t, "gyro": [0, 0, 0.1], "accel": [0, 0, 9.8]} for t in (50, 90)]
    refused = send(client, sid, 100, imu=samples, left=b"not an image", right=b"not an image")
    assert refused.status_code == 422
    assert send(client, sid, 100).json()["imu_samples"] == 2
    assert factory.created[0].imu_seen[0].timestamps_ns.tolist() == [50, 90]


def test_idle_pipelines_are_unloaded_beyond_the_cap_and_resume(tmp_path: Path) -> None:
    factory = FakeFactory()
    with TestClient(create_app(settings_for(tmp_path, max_active_sessions=1), factory)) as c:
        first, second = new_session(c), new_session(c)
        assert send(c, first, 1).json()["resumed"] is False
        assert send(c, second, 1).json()["resumed"] is False  # unloads the idle first one
        assert c.get("/healthz").json()["sessions_active"] == 1
        assert c.get("/healthz").json()["executor"] == "thread"  # as set by settings_for
        again = send(c, first, 2).json()
        assert again["resumed"] is True and again["index"] == 1
        assert len(factory.created) == 3


# ----------------------------------------------------------------------------- worker processes


class PidPipeline(RecordingPipeline):
    """Names the process it runs in; timestamp 666 kills that process outright."""

    def process(self, frame: StereoFrame, imu: ImuBatch | None = None) -> FrameReport:
        if frame.timestamp_ns == 666:
            os._exit(3)
        if frame.timestamp_ns == 777:
            time.sleep(3600)  # stuck
        report = super().process(frame, imu)
        report.message = f"pid={os.getpid()}"
        return report


class ProcessFactory(EstimatorFactory):
    """Picklable (module level, plain state), so it can be sent to worker processes."""

    def __init__(self, delay: float = 0.0) -> None:
        self.delay = delay

    def create(self, prepared: PreparedSession, initial_pose, first_index):  # type: ignore[override]
        return PidPipeline(initial_pose, first_index, self.delay)


class DescribingPipeline(PidPipeline):
    """A ``PidPipeline`` whose message is ``describe(frame, message)``: what a test reads back
    from inside the worker process."""

    def __init__(self, initial_pose, first_index: int, describe) -> None:
        super().__init__(initial_pose, first_index, 0.0)
        self.describe = describe

    def process(self, frame: StereoFrame, imu: ImuBatch | None = None) -> FrameReport:
        report = super().process(frame, imu)
        report.message = self.describe(frame, report.message)
        return report


class DescribingFactory(ProcessFactory):
    """``describe`` must be a module-level function (the factory is pickled to the workers)."""

    def __init__(self, describe) -> None:
        super().__init__()
        self.describe = describe

    def create(self, prepared: PreparedSession, initial_pose, first_index):  # type: ignore[override]
        return DescribingPipeline(initial_pose, first_index, self.describe)


def _pid(pose: dict) -> int:
    return int(pose["message"].rsplit("pid=", 1)[1])


def _parent_of(pid: int) -> int:
    return int(Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[1])


def test_process_mode_runs_sessions_in_their_own_worker_process_in_order(
    tmp_path: Path,
) -> None:
    # No executor given: the default (process) holds for an injected factory too.
    settings = ServiceSettings(data_dir=tmp_path, api_keys=f"{KEY_A},{KEY_B}", workers=2)
    app = create_app(settings, ProcessFactory(delay=0.02))
    stamps = [100 + 10 * k for k in range(8)]
    with TestClient(app) as c:
        assert c.get("/healthz").json()["executor"] == "process"
        pids = app.state.swarmvo.manager.runner.worker_pids()
        assert len(pids) == 2 and os.getpid() not in pids
        assert all(_parent_of(pid) == os.getpid() for pid in pids)
        sids = [new_session(c), new_session(c)]
        replies: dict[str, list[dict]] = {}

        def stream_all(sid: str) -> None:
            # Every frame is sent before any answer is read: order is the server's job.
            with c.websocket_connect(f"/v1/sessions/{sid}/stream", headers=A) as ws:
                ws.receive_json()
                for t in stamps:
                    _ws_frame(ws, t)
                replies[sid] = [ws.receive_json() for _ in stamps]

        threads = [threading.Thread(target=stream_all, args=(sid,)) for sid in sids]
        for thread in threads:
            thread.start()
        for thread in threads:
            thread.join(timeout=60)
        used = set()
        for sid in sids:
            answers = replies[sid]
            assert [r["type"] for r in answers] == ["pose"] * len(stamps), answers
            assert [r["timestamp_ns"] for r in answers] == stamps
            assert [r["index"] for r in answers] == list(range(len(stamps)))
            # The pipeline moves 1 cm per frame: a frame out of order would break the chain.
            assert [r["pose"][0][3] for r in answers] == pytest.approx(
                [0.01 * k for k in range(len(stamps))]
            )
            session_pids = {_pid(r) for r in answers}
            assert len(session_pids) == 1 and session_pids <= set(pids)  # pinned to one worker
            used |= session_pids
            stored = c.get(f"/v1/sessions/{sid}/trajectory", headers=A).json()["poses"]
            assert [p["pose"] for p in stored] == [r["pose"] for r in answers]
        assert used == set(pids)  # the two sessions were spread over both workers
    for pid in pids:  # shut down with the app: no process left behind
        assert not Path(f"/proc/{pid}").exists()


def test_a_dying_worker_fails_only_its_frame_and_the_session_resumes(tmp_path: Path) -> None:
    settings = settings_for(tmp_path, executor="process", workers=2)
    app = create_app(settings, ProcessFactory())
    with TestClient(app) as c:
        runner = app.state.swarmvo.manager.runner
        victim, bystander = new_session(c), new_session(c)
        before = [send(c, victim, t).json() for t in (10, 20)]
        assert send(c, bystander, 10).status_code == 200
        dead = _pid(before[0])
        died = send(c, victim, 666)
        assert died.status_code == 503 and "stopped unexpectedly" in died.json()["detail"]
        assert not Path(f"/proc/{dead}").exists() or _parent_of(dead) != os.getpid()
        again = send(c, victim, 30)
        assert again.status_code == 200, again.text
        body = again.json()
        assert body["resumed"] is True and body["index"] == 2 and _pid(body) != dead
        assert body["pose"] == before[-1]["pose"]  # restarted at the last stored pose
        assert send(c, bystander, 20).status_code == 200
        assert c.get("/healthz").status_code == 200
        stored = c.get(f"/v1/sessions/{victim}/trajectory", headers=A).json()["poses"]
        assert [p["timestamp_ns"] for p in stored] == [10, 20, 30]
        assert runner.restarts == 1
        # A worker killed while idle: the next frame goes to its replacement, nothing fails.
        idle = _pid(send(c, bystander, 30).json())
        os.kill(idle, signal.SIGKILL)
        deadline = time.monotonic() + 10
        while Path(f"/proc/{idle}").exists() and time.monotonic() < deadline:
            time.sleep(0.05)  # reaped once the server noticed
        after = send(c, bystander, 40)
        assert after.status_code == 200, after.text
        assert after.json()["resumed"] is True and _pid(after.json()) != idle
        assert runner.restarts == 2
        metrics = c.get("/metrics").text
        assert "swarmvo_worker_restarts_total 2.0" in metrics
        assert 'swarmvo_errors_total{kind="worker_died"} 1.0' in metrics
        pids = runner.worker_pids()
    for pid in pids:
        assert pid is None or not Path(f"/proc/{pid}").exists()


def test_a_stuck_worker_is_killed_after_the_frame_timeout(tmp_path: Path) -> None:
    # 5 s: well above a fresh worker's start-up under load (the frame after the kill runs on a
    # new process), far below the stuck frame's hour.
    settings = settings_for(tmp_path, executor="process", workers=1, frame_timeout_s=5.0)
    app = create_app(settings, ProcessFactory())
    with TestClient(app) as c:
        sid = new_session(c)
        first = send(c, sid, 10).json()
        started = time.monotonic()
        stuck = send(c, sid, 777)
        assert stuck.status_code == 503 and "not done after 5 s" in stuck.json()["detail"]
        assert time.monotonic() - started < 30
        assert not process_alive(_pid(first))
        again = send(c, sid, 20)
        assert again.status_code == 200, again.text
        assert again.json()["resumed"] is True and again.json()["index"] == 1
        assert 'swarmvo_errors_total{kind="worker_timeout"} 1.0' in c.get("/metrics").text


def test_the_executor_is_a_setting_with_two_kinds() -> None:
    assert ServiceSettings(open=True).executor == "process"
    with pytest.raises(ValidationError, match="executor"):
        ServiceSettings(open=True, executor="auto")


def test_process_mode_refuses_to_start_with_a_factory_it_cannot_send(tmp_path: Path) -> None:
    class Local(FakeFactory):  # defined in a function: not picklable
        pass

    app = create_app(settings_for(tmp_path, executor="process"), Local())
    with pytest.raises(RuntimeError, match="worker processes could not be started"):
        with TestClient(app):
            pass


def test_raw8_websocket_frames_skip_the_image_container(client: TestClient) -> None:
    sid = new_session(client)
    pixels = (np.arange(WIDTH * HEIGHT) % 251).astype(np.uint8).tobytes()

    def header(t: int, **extra) -> str:
        return json.dumps(
            {
                "type": "frame",
                "timestamp_ns": t,
                "encoding": "raw8",
                "width": WIDTH,
                "height": HEIGHT,
                "left_bytes": len(pixels),
                "right_bytes": len(pixels),
                **extra,
            }
        )

    with client.websocket_connect(f"/v1/sessions/{sid}/stream", headers=A) as ws:
        ws.receive_json()
        ws.send_text(header(10))
        ws.send_bytes(pixels + pixels)
        assert ws.receive_json()["type"] == "pose"
        for extra, words in (
            ({"width": HEIGHT, "height": WIDTH}, "calibration is for"),
            ({"left_bytes": 5}, "width*height"),
            ({"encoding": "tiff"}, "encoding: Input should be 'png', 'jpeg', 'image' or 'raw8'"),
            ({"width": "x"}, "width: Input should be a valid integer"),
            ({"encoding": "png", "width": 0}, "width: Input should be greater than 0"),
        ):
            ws.send_text(header(20, **extra))
            reply = ws.receive_json()
            assert reply["type"] == "rejected" and reply["status"] == 422
            assert words in reply["detail"], reply
        ws.send_text(header(20))
        ws.send_bytes(pixels + pixels)
        assert ws.receive_json()["index"] == 1


class StrictFactory(FakeFactory):
    """Refuses a non-rigid initial pose, like the estimator; can answer a skewed pose itself."""

    def __init__(self, skew: bool) -> None:
        super().__init__()
        self.skew = skew

    def create(self, prepared, initial_pose, first_index):  # type: ignore[override]
        if initial_pose is not None:
            rotation = initial_pose[:3, :3]
            if np.abs(rotation.T @ rotation - np.eye(3)).max() > 1e-9:
                raise ValueError("initial_pose must be a rigid transform")
        pipeline = super().create(prepared, initial_pose, first_index)
        if self.skew:
            pipeline.pose[0, 0] = 1.01
        return pipeline


def test_a_stored_pose_that_is_not_quite_rigid_still_resumes(tmp_path: Path) -> None:
    with TestClient(create_app(settings_for(tmp_path), StrictFactory(skew=True))) as c:
        sid = new_session(c)
        assert send(c, sid, 10).json()["pose"][0][0] == 1.01
    factory = StrictFactory(skew=False)
    with TestClient(create_app(settings_for(tmp_path), factory)) as c:
        resumed = send(c, sid, 20)
        assert resumed.status_code == 200, resumed.text
        body = resumed.json()
        assert body["resumed"] is True and "nearest rotation" in body["message"]
        rotation = factory.created[0].initial_pose[:3, :3]
        np.testing.assert_allclose(rotation.T @ rotation, np.eye(3), atol=1e-12)
        assert send(c, sid, 30).status_code == 200


def test_nul_characters_in_text_are_refused(client: TestClient) -> None:
    """No database text type stores NUL: refused up front on every backend, not a 500 later."""
    response = client.post(
        "/v1/sessions", headers=A, json={"calibration": calibration(), "name": "robot\x00one"}
    )
    assert response.status_code == 422, response.text
    sid = new_session(client, name="robot one")
    response = client.post(
        f"/v1/sessions/{sid}/frames",
        headers=A,
        data={"timestamp_ns": "10\x00"},
        files={"left": ("l.png", png()), "right": ("r.png", png(value=3))},
    )
    assert response.status_code == 422 and "NUL" in response.text
    assert client.get("/healthz").status_code == 200


def test_a_lost_database_answers_503_not_500(client: TestClient, monkeypatch) -> None:
    from sqlalchemy.exc import OperationalError

    def down(*_args, **_kwargs):
        raise OperationalError("SELECT 1", {}, ConnectionRefusedError("connection refused"))

    store = client.app.state.swarmvo.store
    monkeypatch.setattr(store, "list_sessions", down)
    response = client.get("/v1/sessions", headers=A)
    assert response.status_code == 503, response.text
    assert "database unavailable" in response.json()["detail"]
    assert response.headers["retry-after"] == "1"
    monkeypatch.undo()
    assert client.get("/v1/sessions", headers=A).status_code == 200
