"""A server stopped (SIGTERM) while a stream is still open: it tells the stream it is stopping,
exits within seconds without a traceback, and every answered pose is stored.

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


@pytest.mark.slow
def test_sigterm_with_a_stuck_stream_exits_quickly_and_cleanly(tmp_path: Path) -> None:
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
        start = time.monotonic()
        server.process.send_signal(signal.SIGTERM)
        code = server.process.wait(timeout=30)
        took = time.monotonic() - start
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

    again = Server(tmp_path / "data", log)
    try:
        stored = {pose.timestamp_ns for pose in _stored(again.url, sid)}
    finally:
        assert again.stop()
    assert set(answered) <= stored
