"""Smoothed poses in the service: stored as frames are finalised, flushed when a session ends.

A small deterministic pipeline stands in for the odometry: its "back end" holds the newest
``WINDOW`` frames back and finalises a frame (pose + 1 m in z, so that it differs from the
online answer) once ``WINDOW`` newer ones arrived, or when flushed. The same checks run on
SQLite here and on the live PostgreSQL of tests/test_service_postgres.py.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
import pytest
from fastapi.testclient import TestClient
from test_service_units import (
    KEY_A,
    A,
    FakeFactory,
    RecordingPipeline,
    calibration,
    png,
    send,
    settings_for,
)

from estimator.types import FrameReport, ImuBatch, StereoFrame
from service.app import create_app

WINDOW = 3


def smoothed_of(pose: np.ndarray) -> list[float]:
    final = pose.copy()
    final[2, 3] += 1.0
    return final.reshape(16).tolist()


class WindowPipeline(RecordingPipeline):
    """RecordingPipeline with a back end that finalises frames ``WINDOW`` frames late."""

    def __init__(self, *args, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self.window: list[tuple[int, np.ndarray]] = []
        self.finished = False

    def process(self, frame: StereoFrame, imu: ImuBatch | None = None) -> FrameReport:
        assert not self.finished, "a flushed pipeline must not get more frames"
        report = super().process(frame, imu)
        self.window.append((frame.timestamp_ns, report.pose.copy()))
        done, self.window = self.window[:-WINDOW], self.window[-WINDOW:]
        report.final_poses = tuple((t, np.array(smoothed_of(p)).reshape(4, 4)) for t, p in done)
        return report

    def finish(self) -> tuple[tuple[int, np.ndarray], ...]:
        self.finished = True
        done, self.window = self.window, []
        return tuple((t, np.array(smoothed_of(p)).reshape(4, 4)) for t, p in done)


class WindowFactory(FakeFactory):
    def create(self, prepared, initial_pose, first_index):  # type: ignore[override]
        pipeline = WindowPipeline(initial_pose, first_index, self.delay)
        self.created.append(pipeline)
        return pipeline


def _session(client: TestClient, backend: bool = True) -> str:
    body = {"calibration": calibration(), "config": {"backend": {"enabled": backend}}}
    response = client.post("/v1/sessions", headers=A, json=body)
    assert response.status_code == 201, response.text
    return response.json()["id"]


def _ws_frame(ws, t: int) -> None:
    left, right = png(), png(value=3)
    ws.send_text(json.dumps({"type": "frame", "timestamp_ns": t, "left_bytes": len(left),
                             "right_bytes": len(right)}))
    ws.send_bytes(left + right)


def _stream(client: TestClient, sid: str, stamps: list[int]) -> list[dict]:
    """Frames over the WebSocket, then a close message; every message until the server closes."""
    with client.websocket_connect(f"/v1/sessions/{sid}/stream", headers=A) as ws:
        assert ws.receive_json()["type"] == "hello"
        for t in stamps:
            _ws_frame(ws, t)
        ws.send_text(json.dumps({"type": "close"}))
        replies = []
        while True:
            try:
                replies.append(ws.receive_json())
            except Exception:
                return replies


def _flat(rows: list[list[float]]) -> list[float]:
    return [value for row in rows for value in row]


def _stored(client: TestClient, sid: str) -> list[tuple[int, list[float]]]:
    answer = client.get(f"/v1/sessions/{sid}/smoothed", headers=A)
    assert answer.status_code == 200, answer.text
    return [(p["timestamp_ns"], _flat(p["pose"])) for p in answer.json()["poses"]]


def check_smoothed_flow(database_url: str, data_dir: Path) -> None:
    """Stored, flushed at a stream's close and at DELETE, served after a restart."""
    settings = settings_for(data_dir, database_url=database_url)
    with TestClient(create_app(settings, WindowFactory())) as client:
        # REST frames: the finalised poses come with later answers and are stored at once.
        rest = _session(client)
        answers = [send(client, rest, t).json() for t in (10, 20, 30, 40, 50)]
        handed = [(p["timestamp_ns"], _flat(p["pose"])) for a in answers
                  for p in a["smoothed"]]
        assert [t for t, _ in handed] == [10, 20]
        assert _stored(client, rest) == handed

        # A stream's close flushes the window: its last message, stored too, each frame once.
        ws = _session(client)
        replies = _stream(client, ws, [10, 20, 30, 40, 50])
        assert [r["type"] for r in replies] == ["pose"] * 5 + ["smoothed"]
        poses = {r["timestamp_ns"]: np.array(r["pose"]) for r in replies[:5]}
        last = [(p["timestamp_ns"], _flat(p["pose"])) for p in replies[-1]["poses"]]
        assert [t for t, _ in last] == [30, 40, 50]
        assert all(pose == smoothed_of(poses[t]) for t, pose in last)
        online = [(p["timestamp_ns"], _flat(p["pose"])) for r in replies[:5]
                  for p in r["smoothed"]]
        assert _stored(client, ws) == online + last
        # The session goes on: its next frame resumes from the last stored pose.
        again = _stream(client, ws, [60, 70])
        assert again[0]["resumed"] is True and again[0]["index"] == 5
        assert [t for t, _ in _stored(client, ws)] == [10, 20, 30, 40, 50, 60, 70]
        tum = client.get(f"/v1/sessions/{ws}/smoothed?format=tum", headers=A)
        rows = [line for line in tum.text.splitlines() if not line.startswith("#")]
        assert tum.status_code == 200 and len(rows) == 7 and rows[2].endswith(" 1 0 0 0 1")
        kitti = client.get(f"/v1/sessions/{ws}/smoothed?format=kitti", headers=A)
        assert kitti.status_code == 200 and len(kitti.text.splitlines()) == 7

        # DELETE: an open stream gets the flushed window, then the 4404 close.
        doomed = _session(client)
        with client.websocket_connect(f"/v1/sessions/{doomed}/stream", headers=A) as stream:
            stream.receive_json()
            for t in (10, 20):
                _ws_frame(stream, t)
                assert stream.receive_json()["type"] == "pose"
            assert client.delete(f"/v1/sessions/{doomed}", headers=A).status_code == 204
            final = stream.receive_json()
            assert final["type"] == "smoothed"
            assert [p["timestamp_ns"] for p in final["poses"]] == [10, 20]
            with pytest.raises(Exception) as closed:
                stream.receive_json()
            assert getattr(closed.value, "code", None) == 4404

        # Without a back end nothing is held back: a close keeps the pipeline going.
        plain = _session(client, backend=False)
        assert _stream(client, plain, [10])[-1] == {"type": "smoothed", "session_id": plain,
                                                    "poses": []}
        assert _stream(client, plain, [20])[0]["resumed"] is False
        expected = _stored(client, ws)
    # Stored, not held in memory: a new server answers the same, to the last bit.
    with TestClient(create_app(settings, WindowFactory())) as client:
        assert _stored(client, ws) == expected
        stored = _stored(client, rest)  # the shutdown flushed the REST session's window
        assert stored[:2] == handed and [t for t, _ in stored] == [10, 20, 30, 40, 50]
        assert client.get(f"/v1/sessions/{doomed}/smoothed", headers=A).status_code == 404


def test_smoothed_poses_are_stored_and_flushed_on_sqlite(tmp_path: Path) -> None:
    check_smoothed_flow(f"sqlite:///{tmp_path / 'smoothed.sqlite3'}", tmp_path)


def test_unloaded_and_shut_down_sessions_store_their_window(tmp_path: Path) -> None:
    factory = WindowFactory()
    settings = settings_for(tmp_path, max_active_sessions=1)
    with TestClient(create_app(settings, factory)) as client:
        first, second = _session(client), _session(client)
        for t in (10, 20):
            send(client, first, t)
        send(client, second, 10)  # unloads the idle first session: its window is flushed
        deadline = time.monotonic() + 10  # stored by the unloading task
        while len(_stored(client, first)) < 2 and time.monotonic() < deadline:
            time.sleep(0.02)
        assert factory.created[0].finished
        assert [t for t, _ in _stored(client, first)] == [10, 20]
        send(client, second, 20)
    # The server's shutdown flushes the live one.
    with TestClient(create_app(settings, factory)) as client:
        assert [t for t, _ in _stored(client, second)] == [10, 20]


def test_rest_finish_makes_the_window_final_like_a_stream_close(tmp_path: Path) -> None:
    """``POST /finish`` (and ``Client.finish``) flushes the back end after the frames sent
    over REST, as a WebSocket's close does; frames after it resume from the stored pose."""
    from swarmvo_client import Client

    factory = WindowFactory()
    with TestClient(create_app(settings_for(tmp_path), factory)) as client:
        sid = _session(client)
        answers = {t: send(client, sid, t).json() for t in (10, 20, 30, 40, 50)}
        poses = {t: np.array(a["pose"], dtype=float) for t, a in answers.items()}
        assert [t for t, _ in _stored(client, sid)] == [10, 20]  # the window holds 3 back
        finished = client.post(f"/v1/sessions/{sid}/finish", headers=A)
        assert finished.status_code == 200, finished.text
        last = [(p["timestamp_ns"], _flat(p["pose"])) for p in finished.json()["poses"]]
        assert [t for t, _ in last] == [30, 40, 50]
        assert all(pose == smoothed_of(poses[t]) for t, pose in last)
        assert factory.created[0].finished
        stored = _stored(client, sid)
        assert [t for t, _ in stored] == [10, 20, 30, 40, 50]
        assert all(pose == smoothed_of(poses[t]) for t, pose in stored)
        # Nothing is held back any more: a second finish has nothing to flush.
        assert client.post(f"/v1/sessions/{sid}/finish", headers=A).json()["poses"] == []
        # The stream may go on: a new pipeline from the last stored pose, flushed by the client.
        assert send(client, sid, 60).status_code == 200
        assert len(factory.created) == 2
        with Client("http://testserver", KEY_A, transport=client._transport) as library:
            flushed = library.finish(sid)
        assert [t for t, _ in flushed] == [60]
        assert [t for t, _ in _stored(client, sid)] == [10, 20, 30, 40, 50, 60]
        # Unknown and deleted sessions are refused.
        assert client.post("/v1/sessions/nope/finish", headers=A).status_code == 404
        assert client.delete(f"/v1/sessions/{sid}", headers=A).status_code == 204
        assert client.post(f"/v1/sessions/{sid}/finish", headers=A).status_code == 404
