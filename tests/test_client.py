"""The Python client on its own: readers, error mapping, TUM output, ATE, no estimator import."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import cv2
import httpx
import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from swarmvo_client import (
    AuthenticationError,
    Client,
    ConflictError,
    ImuData,
    NotFoundError,
    RateLimitedError,
    ServerError,
    open_local_sequence,
    trajectory_error,
    write_tum,
)
from swarmvo_client.evaluation import rigid_align
from swarmvo_client.replay import format_seconds


def test_client_does_not_import_the_estimator() -> None:
    code = (
        "import sys, swarmvo_client, swarmvo_client.cli\n"
        "bad = [m for m in sys.modules if m == 'estimator' or m.startswith(('estimator.', "
        "'service'))]\n"
        "assert not bad, bad\n"
    )
    subprocess.run([sys.executable, "-c", code], check=True, timeout=60)


@pytest.mark.parametrize(
    ("status", "error"),
    [
        (401, AuthenticationError),
        (404, NotFoundError),
        (409, ConflictError),
        (429, RateLimitedError),
        (503, ServerError),
    ],
)
def test_errors_carry_the_server_message(status: int, error: type) -> None:
    def answer(request: httpx.Request) -> httpx.Response:
        assert request.headers["authorization"] == "Bearer k"
        return httpx.Response(status, json={"detail": f"reason {status}"})

    with Client("http://service", "k", transport=httpx.MockTransport(answer)) as client:
        with pytest.raises(error) as info:
            client.get_session("abc")
    assert info.value.status_code == status and info.value.detail == f"reason {status}"


def test_frame_request_shape() -> None:
    seen = {}

    def answer(request: httpx.Request) -> httpx.Response:
        seen["body"] = request.read()
        seen["type"] = request.headers["content-type"]
        pose = np.eye(4).tolist()
        return httpx.Response(
            200,
            json={
                "session_id": "s",
                "index": 0,
                "timestamp_ns": 7,
                "pose": pose,
                "frontend_pose": pose,
                "relative_pose": pose,
                "status": "ok",
                "matches": 1,
                "inliers": 1,
                "support": 1,
                "timings_s": {"total": 0.1},
                "message": "",
                "resumed": False,
                "imu_samples": 1,
            },
        )

    imu = ImuData(
        np.array([5], dtype=np.int64),
        np.array([[0.1, 0.2, 0.30000000000000004]]),
        np.array([[0.0, 0.0, 9.81]]),
    )
    with Client("http://service", transport=httpx.MockTransport(answer)) as client:
        pose = client.send_frame("s", 7, b"LEFT", b"RIGHT", imu)
    assert pose.pose.shape == (4, 4) and pose.status == "ok"
    assert seen["type"].startswith("multipart/form-data")
    assert b"LEFT" in seen["body"] and b"RIGHT" in seen["body"]
    assert b"0.30000000000000004" in seen["body"]  # floats travel exactly


def test_tum_output_reads_back_exactly_with_the_estimator_reader(tmp_path: Path) -> None:
    from estimator.formats.trajectory_io import read_tum

    rng = np.random.default_rng(4)
    rotations = Rotation.random(50, random_state=5).as_matrix()
    rotations[0] = np.diag([1.0, -1.0, -1.0])  # 180 degrees: the hard case for conversion
    rotations[1] = np.diag([-1.0, -1.0, 1.0])
    poses = np.tile(np.eye(4), (50, 1, 1))
    poses[:, :3, :3] = rotations
    poses[:, :3, 3] = rng.normal(size=(50, 3)) * 10
    times = 1403715273262142976 + np.arange(50, dtype=np.int64) * 50_000_001
    write_tum(tmp_path / "t.tum", times, poses)
    read_times, read_poses = read_tum(tmp_path / "t.tum")
    assert read_times.tolist() == times.tolist()
    np.testing.assert_allclose(read_poses, poses, atol=1e-12)
    assert format_seconds(1403715273262142976) == "1403715273.262142976"
    assert format_seconds(-5) == "-0.000000005"


def test_ate_of_a_rigidly_moved_copy_is_zero_and_noise_shows() -> None:
    rng = np.random.default_rng(1)
    truth = np.cumsum(rng.normal(size=(100, 3)), axis=0)
    times = np.arange(100, dtype=np.int64) * 1000
    rotation = Rotation.from_rotvec([0.3, -0.2, 1.0]).as_matrix()
    moved = truth @ rotation.T + [4.0, -2.0, 1.0]
    R, t = rigid_align(moved, truth)
    np.testing.assert_allclose(moved @ R.T + t, truth, atol=1e-9)
    assert trajectory_error(times, moved, times, truth).ate_rmse_m < 1e-9
    noisy = moved + rng.normal(scale=0.05, size=moved.shape)
    error = trajectory_error(times, noisy, times, truth)
    # 0.05 m per axis -> 0.05 * sqrt(3) = 0.087 m in 3D, a little less after the alignment
    assert error is not None and 0.07 < error.ate_rmse_m < 0.1
    # estimates outside the ground-truth time span are not compared
    assert trajectory_error(times + 10**9, moved, times, truth) is None


def test_kitti_folder_reader_agrees_with_the_estimator(tmp_path: Path) -> None:
    from estimator.formats.datasets import open_sequence

    for folder in ("image_0", "image_1"):
        (tmp_path / folder).mkdir()
        for k in range(4):
            cv2.imwrite(str(tmp_path / folder / f"{k:06d}.png"), np.full((20, 30), k, np.uint8))
    (tmp_path / "calib.txt").write_text(
        "P0: 100 0 15 0 0 100 10 0 0 0 1 0\nP1: 100 0 15 -50 0 100 10 0 0 0 1 0\n"
    )
    (tmp_path / "times.txt").write_text("0.0\n0.1\n0.2\n0.30000001\n")
    poses = np.tile(np.eye(4)[:3].reshape(12), (4, 1))
    poses[:, 3] = [0, 1, 2, 3]
    np.savetxt(tmp_path / "poses.txt", poses)
    local = open_local_sequence(tmp_path)
    sequence = open_sequence(tmp_path)
    assert local.kind == "kitti" and local.image_size == (30, 20) == sequence.rig.size
    assert [f.timestamp_ns for f in local.frames] == sequence.timestamps_ns.tolist()
    assert local.gt_positions is not None and local.gt_positions[:, 0].tolist() == [0, 1, 2, 3]
    assert set(local.calibration_files) == {"calib"}


def test_imu_selection_between_frames() -> None:
    imu = ImuData(np.arange(10, dtype=np.int64) * 10, np.zeros((10, 3)), np.zeros((10, 3)))
    assert imu.between(20, 50).timestamps_ns.tolist() == [30, 40, 50]
    assert imu.between(None, 20).timestamps_ns.tolist() == [0, 10, 20]
    samples = imu.between(80, 90).to_samples()
    assert json.loads(json.dumps(samples)) == [
        {"timestamp_ns": 90, "gyro": [0.0, 0.0, 0.0], "accel": [0.0, 0.0, 0.0]}
    ]


def test_raw_frame_message_shape() -> None:
    """Header first (encoding, size, byte counts), then both images in one binary message."""
    import asyncio

    from swarmvo_client.stream import FrameStream

    class Recorder:
        def __init__(self) -> None:
            self.sent: list = []

        async def send(self, message) -> None:
            self.sent.append(message)

    recorder = Recorder()
    frames = FrameStream(recorder, {})  # type: ignore[arg-type]
    left, right = bytes(range(6)), bytes(6)
    asyncio.run(frames.send_raw_frame(7, left, right, 3, 2))
    header = json.loads(recorder.sent[0])
    assert header == {
        "type": "frame",
        "timestamp_ns": 7,
        "encoding": "raw8",
        "width": 3,
        "height": 2,
        "left_bytes": 6,
        "right_bytes": 6,
    }
    assert recorder.sent[1] == left + right
    with pytest.raises(ValueError, match="width\\*height"):
        asyncio.run(frames.send_raw_frame(8, left, right[:5], 3, 2))
    assert len(recorder.sent) == 2  # nothing sent for the refused frame


def test_hold_back_keeps_frames_the_server_would_refuse() -> None:
    """With ``hold_back`` no more frames are unanswered than the server's window (queue + the
    frame in its worker); a held frame's IMU samples are still sent, and each answer read
    makes room for one more frame."""
    import asyncio

    from swarmvo_client.stream import FrameStream

    class Connection:
        def __init__(self) -> None:
            self.sent: list = []
            self.answers = [json.dumps({"type": "rejected", "timestamp_ns": 1, "status": 429,
                                        "detail": "session queue full"})]

        async def send(self, message) -> None:
            self.sent.append(message)

        async def recv(self) -> str:
            return self.answers.pop(0)

    imu = ImuData(np.array([5], dtype=np.int64), np.zeros((1, 3)), np.zeros((1, 3)))

    async def scenario(hold_back: bool) -> tuple[list[bool], FrameStream, Connection]:
        connection = Connection()
        frames = FrameStream(connection, {"queue_size": 1}, hold_back)  # type: ignore[arg-type]
        sent = [await frames.send_frame(t, b"l", b"r", imu) for t in (1, 2, 3)]
        await frames.recv()
        sent.append(await frames.send_frame(4, b"l", b"r"))
        return sent, frames, connection

    sent, frames, connection = asyncio.run(scenario(True))
    assert sent == [True, True, False, True]
    assert frames.held_back == 1 and frames.unanswered == 2
    kinds = [json.loads(m)["type"] for m in connection.sent if isinstance(m, str)]
    assert kinds == ["frame", "frame", "imu", "frame"]
    sent, frames, connection = asyncio.run(scenario(False))  # the default sends every frame
    assert sent == [True] * 4 and frames.held_back == 0


@pytest.mark.parametrize("websocket", [False, True])
def test_replay_against_no_server_is_one_line_naming_it(euroc_v101_micro, tmp_path, capsys,
                                                        websocket) -> None:
    import socket

    from swarmvo_client.cli import main

    with socket.socket() as closed:  # a port nobody listens on
        closed.bind(("127.0.0.1", 0))
        url = f"http://127.0.0.1:{closed.getsockname()[1]}"
    argv = ["replay", str(euroc_v101_micro), "--url", url, "--api-key", "k",
            "--out", str(tmp_path), "--quiet", *(["--ws"] if websocket else [])]
    assert main(argv) == 2
    lines = capsys.readouterr().err.strip().splitlines()
    # The clip's unpaired images: a warning of one line, without our source line.
    assert all(line.startswith("swarmvo-client: warning: ") for line in lines[:-1]), lines
    assert lines[-1].startswith(f"swarmvo-client replay: error: cannot reach the server at {url}: ")
