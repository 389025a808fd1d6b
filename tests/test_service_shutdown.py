"""A server stopped (SIGTERM) while streams are still open: it tells them it is stopping (close
code 1012 with a reason), exits within seconds without a traceback, and every answered pose is
stored.

The hard case is a robot that sent its close message and then stopped reading: the server's
answers pile up in the socket until its writes block, so the stream can never finish by itself.
A stream's end flush queued behind a full queue of a session deleted meanwhile must return too.
"""

from __future__ import annotations

import asyncio
import datetime as dt
import json
import signal
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest
from swarmvo_client import Client
from test_service_server import KEY, Server, _calibration, _png, _stored
from websockets.asyncio.client import ClientConnection, connect

from service.frame_work import FrameFailure
from service.metrics import Metrics
from service.sessions.frames import FrameRejected
from service.sessions.live import LiveSession
from service.settings import ServiceSettings
from service.storage import SessionRecord

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


class _HeldRunner:
    """A worker holding one frame until ``release`` is set; that frame then fails (a bad image)
    and a flush is answered a moment later, as a worker process answers: a consumer that took
    the stream's flush job is still waiting for it when close() stops the consumer."""

    def __init__(self) -> None:
        self.release = asyncio.Event()
        self.started = asyncio.Event()

    async def run(self, slot: int, request) -> FrameFailure:
        self.started.set()
        await self.release.wait()
        return FrameFailure(400, "bad image", "bad_image")

    def finish(self, slot: int, session_id: str) -> asyncio.Future[list]:
        future: asyncio.Future[list] = asyncio.get_running_loop().create_future()
        asyncio.get_running_loop().call_later(0.05, lambda: future.done() or future.set_result([]))
        return future


async def _flush_behind_a_full_queue_of_a_deleted_session(tmp_path: Path) -> None:
    record = SessionRecord("s1", "owner", "s1", dt.datetime.now(dt.UTC),
                           _calibration(), {}, None, 32, 24, 0, None, 0)
    settings = ServiceSettings(data_dir=tmp_path, api_keys=KEY, queue_size=2,
                               executor="thread")
    runner = _HeldRunner()
    with ThreadPoolExecutor(1) as io_pool:
        live = LiveSession(record, settings, None, runner, 0, io_pool,  # type: ignore[arg-type]
                           Metrics())
        live.pipeline_ready = True  # the worker holds a pipeline: the end flush must reach it
        frames = [live.submit(1, b"", b"", None)]
        await asyncio.wait_for(runner.started.wait(), 5)  # frame 1 in the worker
        frames += [live.submit(t, b"", b"", None) for t in (2, 3)]
        assert live.queue.full()  # frames 2 and 3 wait
        flush = asyncio.create_task(live.flush_after_queued())
        await asyncio.sleep(0.05)
        assert not flush.done()  # it waits for room in the queue
        closing = asyncio.create_task(live.close("session deleted", deleted=True))
        await asyncio.sleep(0.05)  # close() emptied the queue and waits for frame 1
        runner.release.set()
        assert await asyncio.wait_for(closing, 5) == []
        try:
            assert await asyncio.wait_for(flush, 5) == []
        except TimeoutError:
            pytest.fail("the flush queued behind the full queue never returned")
        # Frame 1 finished in the worker (refused by it); frames 2 and 3 were refused by close().
        for frame, status in zip(frames, (400, 404, 404), strict=True):
            with pytest.raises(FrameRejected) as refused:
                await frame
            assert refused.value.status_code == status


def test_a_flush_queued_behind_a_full_queue_returns_when_the_session_is_deleted(
    tmp_path: Path,
) -> None:
    """The stream's end flush waits for room in a full queue; the session is deleted
    meanwhile, and close() empties the queue and stops the consumer: the flush returns (the
    closing session flushes by itself) instead of waiting forever for a job nobody takes."""
    asyncio.run(_flush_behind_a_full_queue_of_a_deleted_session(tmp_path))
