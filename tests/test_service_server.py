"""The service as deployed: a real ``swarmvo serve`` subprocess on 127.0.0.1, the real odometry.

- replaying EuRoC frames over HTTP and over the WebSocket gives exactly the offline trajectory
  (same seed) and the stored trajectory equals what was answered;
- a server killed mid-sequence (SIGKILL: no chance to flush anything) loses no answered pose,
  and the session continues from its last stored pose, saying so;
- malformed requests of every kind get 4xx, never 5xx, and the server stays healthy.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import os
import re
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import httpx
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from swarmvo_client import (
    AsyncClient,
    AuthenticationError,
    Client,
    NotFoundError,
    Pose,
    open_local_sequence,
    replay,
    stream,
)

PROJECT_ROOT = Path(__file__).resolve().parents[1]
KEY = "test-key-1"
OTHER_KEY = "test-key-2"
AUTH = {"Authorization": f"Bearer {KEY}"}
SEED = 3
FRAMES = 30


def _free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


class Server:
    """``swarmvo serve`` in a subprocess; stopped gracefully or killed outright."""

    def __init__(self, data_dir: Path, log: Path, *extra: str) -> None:
        self.port = _free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        env = {**os.environ, "SWARMVO_API_KEYS": f"{KEY},{OTHER_KEY}", "OMP_NUM_THREADS": "1"}
        self.log = log
        self.process = subprocess.Popen(
            [
                sys.executable,
                "-m",
                "estimator.cli.main",
                "serve",
                "--host",
                "127.0.0.1",
                "--port",
                str(self.port),
                "--data-dir",
                str(data_dir),
                "--workers",
                "2",
                "--log-level",
                "warning",
                *extra,
            ],
            cwd=PROJECT_ROOT,
            env=env,
            stdout=log.open("ab"),
            stderr=subprocess.STDOUT,
        )
        # The workers warm up before the server answers: 10 s idle, 45-50 s at load 35 on 2 cores.
        deadline = time.monotonic() + 180
        while time.monotonic() < deadline:
            if self.process.poll() is not None:
                raise RuntimeError(f"server exited early:\n{log.read_text()}")
            with contextlib.suppress(httpx.HTTPError):
                if httpx.get(f"{self.url}/healthz", timeout=1).status_code == 200:
                    return
            time.sleep(0.2)
        self.kill()
        raise RuntimeError(f"server did not become healthy in 180 s:\n{log.read_text()}")

    def stop(self) -> bool:
        """SIGTERM; uvicorn drains, shuts down and re-raises the signal (exit -15)."""
        self.process.send_signal(signal.SIGTERM)
        return self.process.wait(timeout=30) in (0, -signal.SIGTERM)

    def kill(self) -> None:
        self.process.kill()
        self.process.wait(timeout=30)

    def children(self) -> list[int]:
        """Process ids of the server's direct children (its worker processes)."""
        pids = []
        for task in Path(f"/proc/{self.process.pid}/task").iterdir():
            pids += [int(pid) for pid in (task / "children").read_text().split()]
        return pids


def process_alive(pid: int) -> bool:
    """Running (a zombie waiting to be reaped by init counts as gone)."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except OSError:
        return False
    return fields[0] != "Z"


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Server]:
    """One server for the tests that do not restart it (starting one costs seconds)."""
    folder = tmp_path_factory.mktemp("service")
    running = Server(folder / "data", folder / "server.log")
    yield running
    if running.process.poll() is None:
        assert running.stop()
    assert "Traceback" not in running.log.read_text(), running.log.read_text()


def _offline(dataset: Path, limit: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    from estimator.formats.datasets import open_sequence
    from estimator.pipeline import build_config, run_sequence

    result = run_sequence(
        open_sequence(dataset), build_config("pso-robust", SEED, True, True), limit=limit
    )
    return result.timestamps_ns, result.poses("pose"), result.poses("frontend_pose")


def _offline_odometry(dataset: Path, limit: int) -> tuple[list[dict], dict[int, np.ndarray]]:
    """The offline run's odometry messages (as the service answers them) and smoothed poses."""
    from estimator.formats.datasets import open_sequence
    from estimator.pipeline import build_config, odometry_messages, run_sequence

    config = build_config("pso-robust", SEED, True, True)
    result = run_sequence(open_sequence(dataset), config, limit=limit)
    return [message.to_dict() for message in odometry_messages(result)], result.smoothed


def _stored(url: str, session_id: str) -> list[Pose]:
    with Client(url, KEY) as client:
        poses = client.trajectory(session_id)
    assert isinstance(poses, list)
    return poses


@pytest.mark.slow
@pytest.mark.euroc
def test_http_and_websocket_replay_equal_the_offline_run(
    server: Server, euroc_v101_micro: Path, tmp_path: Path
) -> None:
    times, offline, offline_frontend = _offline(euroc_v101_micro, FRAMES)
    odometry, smoothed = _offline_odometry(euroc_v101_micro, FRAMES)
    for use_ws in (False, True):
        result = replay(
            server.url,
            euroc_v101_micro,
            KEY,
            use_ws=use_ws,
            limit=FRAMES,
            config={"seed": SEED},
            progress=False,
        )
        assert not result.dropped and not result.rejected
        assert result.timestamps_ns.tolist() == times.tolist()
        np.testing.assert_allclose(result.matrices, offline, rtol=0, atol=1e-9)
        frontend = np.array([p.frontend_pose for p in result.poses])
        np.testing.assert_allclose(frontend, offline_frontend, rtol=0, atol=1e-9)
        assert [p.index for p in result.poses] == list(range(FRAMES))
        assert result.error is not None and result.error.pairs == FRAMES
        # What the server stored is exactly what it answered.
        stored = _stored(server.url, result.session.id)
        assert [p.pose.tolist() for p in stored] == [p.pose.tolist() for p in result.poses]
        assert all(p.imu_samples > 0 for p in result.poses[1:])  # EuRoC IMU went through
        # The odometry message of each answer is the offline one (odom, covariances, twist).
        for answered, expected in zip(result.poses, odometry, strict=True):
            assert answered.odometry is not None
            assert answered.odometry["header"] == expected["header"]
            np.testing.assert_allclose(
                answered.odometry["pose"]["covariance"], expected["pose"]["covariance"],
                rtol=1e-6, atol=1e-15,
            )
            np.testing.assert_allclose(
                answered.odometry["camera_pose"], expected["camera_pose"], rtol=0, atol=1e-9
            )
        # The smoother's final estimates arrive online, each frame once, as offline.
        finished = [item for pose in result.poses for item in pose.smoothed]
        assert len({stamp for stamp, _ in finished}) == len(finished) > FRAMES // 2
        for stamp, pose in finished:
            np.testing.assert_allclose(pose, smoothed[stamp], rtol=0, atol=1e-9)
        # Over the WebSocket the stream's end flushes the rest: then every frame is there.
        finished += result.final_smoothed
        if use_ws:
            assert [stamp for stamp, _ in finished] == times.tolist()
        for stamp, pose in result.final_smoothed:
            np.testing.assert_allclose(pose, smoothed[stamp], rtol=0, atol=1e-9)
        with Client(server.url, KEY) as client:
            queried = client.smoothed(result.session.id)  # as stored
        assert [stamp for stamp, _ in queried] == [stamp for stamp, _ in finished]
        assert all(np.array_equal(a, b) for (_, a), (_, b) in zip(queried, finished, strict=True))
    # The TUM export reads back as the offline trajectory too.
    from estimator.formats.trajectory_io import read_tum

    with Client(server.url, KEY) as client:
        tum = client.trajectory(result.session.id, format="tum")
    assert isinstance(tum, str)
    (tmp_path / "export.tum").write_text(tum)
    tum_times, tum_poses = read_tum(tmp_path / "export.tum")
    assert tum_times.tolist() == times.tolist()
    np.testing.assert_allclose(tum_poses, offline, rtol=0, atol=1e-9)


@pytest.mark.slow
@pytest.mark.euroc
def test_restart_mid_sequence_loses_nothing_and_resumes(
    euroc_v101_micro: Path, tmp_path: Path
) -> None:
    data, log = tmp_path / "data", tmp_path / "server.log"
    first = Server(data, log)
    workers = first.children()
    try:
        result = replay(
            first.url, euroc_v101_micro, KEY, limit=8, config={"seed": SEED}, progress=False
        )
    finally:
        first.kill()  # SIGKILL: whatever was answered must already be committed
    answered = [p.pose.tolist() for p in result.poses]
    assert len(answered) == 8
    # The worker processes notice that their server is gone and exit: no orphans.
    assert len(workers) >= 2
    deadline = time.monotonic() + 15
    while any(process_alive(pid) for pid in workers) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert not any(process_alive(pid) for pid in workers)

    second = Server(data, log)
    try:
        session_id = result.session.id
        assert [p.pose.tolist() for p in _stored(second.url, session_id)] == answered
        continued = replay(
            second.url,
            euroc_v101_micro,
            KEY,
            use_ws=True,
            limit=6,
            session_id=session_id,
            progress=False,
        )
        assert [p.index for p in continued.poses] == list(range(8, 14))
        assert continued.poses[0].resumed and "resumed from the stored pose" in (
            continued.poses[0].message
        )
        assert not any(p.resumed for p in continued.poses[1:])
        # The estimator restarted at the last stored pose: the drone stands still, so the
        # continued poses stay within centimetres of it.
        last = np.array(answered[-1])
        shift = [np.linalg.norm(p.pose[:3, 3] - last[:3, 3]) for p in continued.poses]
        assert max(shift) < 0.05, shift
        stored = _stored(second.url, session_id)
        assert [p.pose.tolist() for p in stored[:8]] == answered
        assert len(stored) == 14
        with Client(second.url, KEY) as client:
            session = client.get_session(session_id)
        assert session.frame_count == 14 and session.resume_count == 1
        assert second.stop()
    finally:
        if second.process.poll() is None:
            second.kill()
    assert "Traceback" not in log.read_text(), log.read_text()


# ----------------------------------------------------------------------------- bad input


def _calibration() -> dict:
    eye = np.eye(4)
    right = eye.copy()
    right[0, 3] = 0.1
    camera = {
        "width": 32,
        "height": 24,
        "fx": 30.0,
        "fy": 30.0,
        "cx": 16.0,
        "cy": 12.0,
        "distortion_model": "none",
        "distortion": [],
    }
    return {"left": {**camera, "T_BS": eye.tolist()}, "right": {**camera, "T_BS": right.tolist()}}


def _png(width: int = 32, height: int = 24) -> bytes:
    import cv2

    image = (np.random.default_rng(width * height).random((height, width)) * 255).astype(np.uint8)
    return cv2.imencode(".png", image)[1].tobytes()


def _malformed_requests(sid: str) -> list[tuple[str, str, dict]]:
    """(method, path, httpx kwargs) that must all be refused with a 4xx."""
    good = _png()
    frames = f"/v1/sessions/{sid}/frames"
    big_header = bytearray(good)
    big_header[16:24] = (60000).to_bytes(4, "big") * 2  # claims 60000 x 60000
    nan_imu = '{"samples": [{"timestamp_ns": 1, "gyro": [NaN, 0, 0], "accel": [0, 0, 1]}]}'

    def frame(timestamp="100", left=good, right=good, **extra):
        return {
            "data": {"timestamp_ns": timestamp, **extra},
            "files": {"left": ("l.png", left), "right": ("r.png", right)},
            "headers": AUTH,
        }

    return [
        ("GET", "/v1/sessions", {}),
        ("GET", "/v1/sessions", {"headers": {"Authorization": "Bearer nope"}}),
        ("GET", "/v1/sessions", {"headers": {"Authorization": "Basic a2V5"}}),
        ("GET", f"/v1/sessions/{sid}", {"headers": {"Authorization": f"Bearer {OTHER_KEY}"}}),
        ("GET", "/v1/sessions/0123456789abcdef0123456789abcdef", {"headers": AUTH}),
        ("GET", "/v1/sessions/..%2F..%2Fetc", {"headers": AUTH}),
        ("DELETE", "/v1/sessions/unknown", {"headers": AUTH}),
        ("POST", "/v1/sessions", {"headers": AUTH, "content": b"{not json"}),
        ("POST", "/v1/sessions", {"headers": AUTH, "json": [1, 2, 3]}),
        ("POST", "/v1/sessions", {"headers": AUTH, "json": {"calibration": "x"}}),
        ("POST", "/v1/sessions", {"headers": AUTH, "data": {"calibration": "x"}}),
        (
            "POST",
            "/v1/sessions",
            {
                "headers": {**AUTH, "content-type": "application/json"},
                "content": '{"calibration": {"left": NaN}}',
            },
        ),
        ("POST", "/v1/sessions/euroc", {"headers": AUTH, "files": {"cam0": b"\x00" * 10}}),
        (
            "POST",
            "/v1/sessions/kitti",
            {
                "headers": AUTH,
                "files": {"calib": b"P0: 1 2"},
                "data": {"width": "-5", "height": "x"},
            },
        ),
        ("POST", frames, {"headers": AUTH, "json": {"timestamp_ns": 1}}),
        (
            "POST",
            frames,
            {"headers": {**AUTH, "content-type": "multipart/form-data"}, "content": b"garbage"},
        ),
        (
            "POST",
            frames,
            {
                "headers": {**AUTH, "content-type": "multipart/form-data; boundary=xx"},
                "content": b'--xx\r\nContent-Disposition: form-data; name="left"\r\n',
            },
        ),
        ("POST", frames, frame(left=os.urandom(5000))),
        ("POST", frames, frame(left=good[: len(good) // 2])),
        ("POST", frames, frame(left=bytes(big_header))),
        ("POST", frames, frame(right=_png(40, 30))),
        ("POST", frames, frame(left=_png(64, 48), right=_png(64, 48))),
        ("POST", frames, frame(timestamp="abc")),
        ("POST", frames, frame(timestamp="-1")),
        ("POST", frames, frame(timestamp=str(2**64))),
        ("POST", frames, frame(timestamp="1e3")),
        ("POST", frames, frame(imu="[not json")),
        ("POST", frames, frame(imu=nan_imu)),
        ("POST", frames, frame(imu='{"samples": [{"timestamp_ns": "x"}]}')),
        ("POST", frames, {"data": {"timestamp_ns": "5"}, "headers": AUTH}),
        ("POST", frames, {**frame(), "headers": {}}),
        ("POST", "/v1/sessions/0123456789abcdef0123456789abcdef/frames", frame()),
        ("POST", f"/v1/sessions/{sid}/imu", {"headers": AUTH, "json": {"samples": "x"}}),
        (
            "POST",
            f"/v1/sessions/{sid}/imu",
            {
                "headers": AUTH,
                "json": {"samples": [{"timestamp_ns": 1, "gyro": [0, 0], "accel": [0, 0, 0]}]},
            },
        ),
        (
            "POST",
            f"/v1/sessions/{sid}/imu",
            {
                "headers": AUTH,
                "json": {
                    "samples": [{"timestamp_ns": 1, "gyro": [0, 0, 0], "accel": [0, 0, 0]}] * 20000
                },
            },
        ),
        ("GET", f"/v1/sessions/{sid}/trajectory?format=xml", {"headers": AUTH}),
    ]


@pytest.mark.slow
def test_malformed_requests_get_4xx_and_the_server_stays_healthy(server: Server) -> None:
    with Client(server.url, KEY) as client:
        sid = client.create_session(_calibration(), config={"backend": {"enabled": False}}).id
    statuses = {}
    with httpx.Client(base_url=server.url, timeout=30) as http:
        for number, (method, path, kwargs) in enumerate(_malformed_requests(sid)):
            response = http.request(method, path, **kwargs)
            statuses[number] = response.status_code
            assert 400 <= response.status_code < 500, (number, path, response.text)
            assert isinstance(response.json()["detail"], str) and response.json()["detail"]
        # After all that, the session still works and nothing was stored from bad input.
        health = http.get("/healthz")
        assert health.status_code == 200
        assert health.json()["executor"] == "process" and health.json()["workers"] == 2
        ok = http.post(
            f"/v1/sessions/{sid}/frames",
            headers=AUTH,
            data={"timestamp_ns": "100"},
            files={"left": _png(), "right": _png()},
        )
        assert ok.status_code == 200, ok.text
        assert ok.json()["index"] == 0
    assert {401, 404, 413, 415, 422} <= set(statuses.values())


def test_oversized_declared_body_is_refused_before_it_is_sent(server: Server) -> None:
    """Only headers go out: the 413 must come back without the server waiting for a body."""
    request = (
        f"POST /v1/sessions HTTP/1.1\r\nHost: 127.0.0.1\r\nAuthorization: Bearer {KEY}\r\n"
        "Content-Type: application/json\r\nContent-Length: 1000000000000\r\n\r\n"
    )
    with socket.create_connection(("127.0.0.1", server.port), timeout=10) as sock:
        sock.sendall(request.encode())
        received = b""
        while chunk := sock.recv(4096):  # the server closes after the answer
            received += chunk
        answer = received.decode(errors="replace")
    assert answer.startswith("HTTP/1.1 413"), answer
    assert "exceeds the limit" in answer


@pytest.mark.slow
def test_random_image_bytes_never_break_the_server(server: Server) -> None:
    with Client(server.url, KEY) as client:
        sid = client.create_session(_calibration(), config={"backend": {"enabled": False}}).id
    http = httpx.Client(base_url=server.url, headers=AUTH, timeout=30)
    prefix = st.sampled_from([b"", b"\x89PNG\r\n\x1a\n", b"\xff\xd8\xff", _png()[:33]])
    counter = iter(range(1, 10**6))

    @settings(
        max_examples=40, deadline=None, derandomize=True, suppress_health_check=list(HealthCheck)
    )
    @given(prefix, st.binary(max_size=2000), prefix, st.binary(max_size=2000))
    def check(p1: bytes, body1: bytes, p2: bytes, body2: bytes) -> None:
        response = http.post(
            f"/v1/sessions/{sid}/frames",
            data={"timestamp_ns": next(counter)},
            files={"left": p1 + body1, "right": p2 + body2},
        )
        assert 400 <= response.status_code < 500, response.text

    try:
        check()
        assert http.get("/healthz").status_code == 200
    finally:
        http.close()


@pytest.mark.slow
def test_websocket_refusals_and_garbage(server: Server) -> None:
    with Client(server.url, KEY) as client:
        sid = client.create_session(_calibration(), config={"backend": {"enabled": False}}).id

    async def scenario() -> list[dict]:
        for key, expected in (
            (None, AuthenticationError),
            ("wrong", AuthenticationError),
            (OTHER_KEY, NotFoundError),
        ):
            with pytest.raises(expected):
                async with stream(server.url, sid, key):
                    pass
        import websockets

        replies = []
        url = server.url.replace("http://", "ws://") + f"/v1/sessions/{sid}/stream?token={KEY}"
        async with websockets.connect(url) as ws:
            assert json.loads(await ws.recv())["type"] == "hello"
            for message in (
                "{",
                "[]",
                '{"type": "nope"}',
                b"\x00" * 10,
                '{"type": "frame", "timestamp_ns": 5, "left_bytes": -1}',
                '{"type": "frame", "timestamp_ns": 5, "left_bytes": 3, "right_bytes": 3}',
                b"abcdef",
                '{"type": "imu", "samples": [{"timestamp_ns": 1}]}',
                '{"type": "close"}',
            ):
                await ws.send(message)
            async for text in ws:
                replies.append(json.loads(text))
        async with AsyncClient(server.url, KEY) as client:
            assert (await client.health())["status"] == "ok"
            assert (await client.get_session(sid)).frame_count == 0
        return replies

    replies = asyncio.run(asyncio.wait_for(scenario(), timeout=60))
    assert [r["type"] for r in replies] == [
        "error",
        "error",
        "error",
        "error",
        "rejected",
        "rejected",
        "error",
        "smoothed",  # the close: the back end's window (no frame was processed: none)
    ]
    assert replies[-1]["poses"] == []
    assert "PNG or JPEG" in replies[5]["detail"]


@pytest.mark.slow
def test_openapi_fuzzing_finds_no_server_error(server: Server, tmp_path: Path) -> None:
    """Schemathesis against the published schema (a few hundred cases); any 5xx fails."""
    command = [
        str(Path(sys.executable).with_name("schemathesis")),
        "run",
        f"{server.url}/openapi.json",
        "-H",
        f"Authorization: Bearer {KEY}",
        "--checks",
        "not_a_server_error",
        "--max-examples",
        "5",
        "--phases",
        "coverage,fuzzing",
        "-w",
        "1",
        "--seed",
        "1",
    ]
    if not Path(command[0]).exists():
        pytest.skip("schemathesis is not installed in this environment")
    finished = subprocess.run(command, capture_output=True, text=True, timeout=120, cwd=tmp_path)
    assert finished.returncode == 0, finished.stdout[-4000:]
    generated = re.search(r"(\d+) generated, (\d+) passed", finished.stdout)
    assert generated is not None, finished.stdout[-2000:]
    assert int(generated.group(1)) >= 100 and generated.group(1) == generated.group(2)


def test_client_reader_matches_the_estimator_reader(euroc_v101_micro: Path) -> None:
    from estimator.formats.datasets import open_sequence

    with pytest.warns(UserWarning):
        local = open_local_sequence(euroc_v101_micro)
    sequence = open_sequence(euroc_v101_micro)
    assert [f.timestamp_ns for f in local.frames] == sequence.timestamps_ns.tolist()
    assert [f.left for f in local.frames] == [f.left_path for f in sequence.frames]
    assert local.imu is not None and sequence.imu is not None
    np.testing.assert_array_equal(local.imu.timestamps_ns, sequence.imu.timestamps_ns)
    np.testing.assert_array_equal(local.imu.gyro, sequence.imu.gyro)
    np.testing.assert_array_equal(local.imu.accel, sequence.imu.accel)
    assert local.image_size == sequence.rig.size


@pytest.mark.slow
@pytest.mark.euroc
def test_client_cli_replay_writes_the_acknowledged_trajectory(
    server: Server, euroc_v101_micro: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from swarmvo_client.cli import main

    out = tmp_path / "out"
    code = main(
        [
            "replay",
            str(euroc_v101_micro),
            "--url",
            server.url,
            "--api-key",
            KEY,
            "--ws",
            "--limit",
            "5",
            "--seed",
            str(SEED),
            "--out",
            str(out),
            "--quiet",
        ]
    )
    assert code == 0
    printed = capsys.readouterr().out
    assert "ate_rmse_m" in printed and "frames_acknowledged: 5" in printed
    summary = json.loads((out / "replay.json").read_text())
    from estimator.formats.trajectory_io import read_tum

    times, poses = read_tum(out / "trajectory.tum")
    stored = _stored(server.url, summary["session_id"])
    assert times.tolist() == [p.timestamp_ns for p in stored]
    np.testing.assert_allclose(poses, np.array([p.pose for p in stored]), rtol=0, atol=1e-9)
    assert (
        main(
            [
                "replay",
                str(euroc_v101_micro),
                "--url",
                server.url,
                "--api-key",
                "wrong",
                "--limit",
                "2",
                "--out",
                str(out),
                "--quiet",
            ]
        )
        == 2
    )
    assert "HTTP 401" in capsys.readouterr().err


@pytest.mark.slow
@pytest.mark.euroc
def test_client_replays_a_bag_as_the_offline_run(
    server: Server, euroc_v101_micro: Path, tmp_path: Path
) -> None:
    """A ROS 1 bag (16-bit images) from the real clip, replayed over the WebSocket."""
    import warnings

    from swarmvo_client.cli import main as client_main

    from estimator.formats.datasets import open_sequence
    from estimator.formats.rosbag_write import write_stereo_bag

    frames = 10
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the clip's unpaired camera rows
        sequence = open_sequence(euroc_v101_micro)
    bag = tmp_path / "clip.bag"
    write_stereo_bag(bag, sequence, frames, "mono16")
    times, offline, _ = _offline(euroc_v101_micro, frames)
    out = tmp_path / "replay"
    code = client_main(
        ["replay", str(bag), "--url", server.url, "--api-key", KEY, "--ws", "--seed", str(SEED),
         "--calibration", str(euroc_v101_micro), "--out", str(out), "--quiet"]
    )
    assert code == 0
    from estimator.formats.trajectory_io import read_tum

    replay_times, poses = read_tum(out / "trajectory.tum")
    assert replay_times.tolist() == times.tolist()
    np.testing.assert_allclose(poses, offline, rtol=0, atol=1e-9)
    assert len((out / "odometry.jsonl").read_text().splitlines()) == frames
