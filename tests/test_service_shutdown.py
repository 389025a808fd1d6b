"""A server stopped (SIGTERM) while streams are still open: it tells them it is stopping (close
code 1012 with a reason), exits within seconds without a traceback, and every answered pose is
stored.

The hard case is a robot that sent its close message and then stopped reading: the server's
answers pile up in the socket until its writes block, so the stream can never finish by itself.
"""

from __future__ import annotations

import asyncio
import json
import signal
import time
from pathlib import Path

import pytest
from swarmvo_client import Client
from test_service_server import KEY, Server, _calibration, _png, _stored
from websockets.asyncio.client import ClientConnection, connect

# Each refusal repeats the message type it was given: 256 kB per answer, so a few dozen fill the
# socket buffers of a client that does not read.
BIG_TYPE = "x" * 256 * 1024
FLOOD = 40


async def _answer_then_stop_reading(url: str) -> tuple[list[int], ClientConnection]:
    """Frames answered (timestamps of their poses), then a flood of answers left unread and the
    close message; the connection is returned open, and nobody reads it any more."""
    png = _png()
    ws = await connect(url, max_queue=1, max_size=None)
    assert json.loads(await ws.recv())["type"] == "hello"
    answered = []
    for i in range(5):
        header = {"type": "frame", "timestamp_ns": (i + 1) * 50_000_000,
                  "left_bytes": len(png), "right_bytes": len(png)}
        await ws.send(json.dumps(header))
        await ws.send(png + png)
        reply = json.loads(await ws.recv())
        if reply["type"] == "pose":
            answered.append(reply["timestamp_ns"])
    for _ in range(FLOOD):
        await ws.send(json.dumps({"type": BIG_TYPE}))
    await ws.send(json.dumps({"type": "close"}))
    await asyncio.sleep(2.0)  # the server reads all of it and blocks writing its answers
    return answered, ws


async def _open(url: str) -> ClientConnection:
    """A stream that reads (its connection does, in the background) and sends nothing."""
    ws = await connect(url)
    assert json.loads(await ws.recv())["type"] == "hello"
    return ws


@pytest.mark.slow
@pytest.mark.parametrize("deleted", [False, True], ids=["open", "session-deleted"])
def test_sigterm_with_a_stuck_stream_exits_quickly_and_cleanly(tmp_path: Path,
                                                               deleted: bool) -> None:
    """``deleted``: the session is deleted before the SIGTERM (as the load test does at the end
    of a run), so the stuck stream is already ending when the server stops."""
    log = tmp_path / "server.log"
    server = Server(tmp_path / "data", log)
    try:
        with Client(server.url, KEY) as client:
            sid = client.create_session(_calibration(),
                                        config={"backend": {"enabled": False}}).id
        url = server.url.replace("http://", "ws://") + f"/v1/sessions/{sid}/stream?token={KEY}"
        loop = asyncio.new_event_loop()
        answered, unread = loop.run_until_complete(_answer_then_stop_reading(url))
        assert answered, "the real odometry answered none of the frames with a pose"
        reading = loop.run_until_complete(_open(url))
        if deleted:
            with Client(server.url, KEY) as client:
                client.delete_session(sid)
        start = time.monotonic()
        server.process.send_signal(signal.SIGTERM)
        code = loop.run_until_complete(asyncio.to_thread(server.process.wait, 30))
        took = time.monotonic() - start
        loop.run_until_complete(asyncio.wait_for(reading.wait_closed(), 5))
        if deleted:
            assert (reading.close_code, reading.close_reason) == (4404, "session deleted")
        else:
            assert reading.close_code == 1012
            assert reading.close_reason == "server stopping; reconnect to continue"
        unread.transport.abort()
    finally:
        if server.process.poll() is None:
            server.kill()
        left = asyncio.all_tasks(loop)
        for task in left:
            task.cancel()
        loop.run_until_complete(asyncio.gather(*left, return_exceptions=True))
        loop.close()
    print(f"stopped in {took:.1f} s")
    output = log.read_text()
    assert code in (0, -signal.SIGTERM), output
    assert took < 8.0, f"stopping took {took:.1f} s:\n{output}"
    assert "Traceback" not in output, output
    assert "Exception in ASGI application" not in output, output
    assert "timeout graceful shutdown exceeded" not in output, output
    if deleted:
        return
    again = Server(tmp_path / "data", log)
    try:
        stored = {pose.timestamp_ns for pose in _stored(again.url, sid)}
    finally:
        assert again.stop()
    assert set(answered) <= stored
