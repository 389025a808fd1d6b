"""Real-time streaming over the WebSocket endpoint.

    async with stream(url, session_id, api_key) as s:
        await s.send_frame(timestamp_ns, left_png, right_png, imu)
        event = await s.recv()   # Pose | DroppedFrame | RejectedFrame, in send order
        last = await s.finish()  # the back end's final poses of the last frames

Sending and receiving are independent: a producer may run ahead of the answers (the server
queues a bounded number of frames per session and says which ones it drops or rejects).
"""

from __future__ import annotations

import json
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from typing import Any

import numpy as np
import websockets
from websockets.asyncio.client import ClientConnection

from swarmvo_client.errors import StreamError, error_for
from swarmvo_client.models import DroppedFrame, ImuData, Pose, RejectedFrame

StreamEvent = Pose | DroppedFrame | RejectedFrame


def ws_url(url: str, session_id: str) -> str:
    base = url.rstrip("/")
    if base.startswith("https://"):
        base = "wss://" + base.removeprefix("https://")
    elif base.startswith("http://"):
        base = "ws://" + base.removeprefix("http://")
    return f"{base}/v1/sessions/{session_id}/stream"


class FrameStream:
    """An open stream of one session.

    With ``hold_back`` a frame is not sent while more frames are unanswered than the server
    holds for the session (its ``queue_size`` from the hello, plus the one being processed):
    the server would refuse it for a full queue, after receiving its images all the same (a
    few ms of its CPU per frame, docs/performance.md). Such a frame is counted in ``held_back``
    and :meth:`send_frame` returns False. The count of unanswered frames includes answers
    still on their way, so a frame is held back at most when the server could have taken it.
    """

    def __init__(self, connection: ClientConnection, hello: dict[str, Any],
                 hold_back: bool = False) -> None:
        self.connection = connection
        self.hello = hello
        self.hold_back = hold_back
        self.unanswered = 0  # frames sent whose answer (pose, dropped, rejected) is not read yet
        self.held_back = 0

    @property
    def server_window(self) -> int:
        """Frames the server holds for the session: its queue and the frame in its worker."""
        return int(self.hello.get("queue_size", 0)) + 1

    async def send_frame(
        self, timestamp_ns: int, left: bytes, right: bytes, imu: ImuData | None = None
    ) -> bool:
        """Header as JSON, then both encoded images in one binary message; False when the
        frame was held back (``hold_back``) instead of sent."""
        return await self._send_frame({"timestamp_ns": int(timestamp_ns)}, left, right, imu)

    async def send_raw_frame(
        self,
        timestamp_ns: int,
        left: bytes,
        right: bytes,
        width: int,
        height: int,
        imu: ImuData | None = None,
    ) -> bool:
        """Raw 8-bit grey pixels (row-major, width*height bytes each): the server skips decoding.

        Noisy camera images barely compress as PNG, so this costs little more bandwidth while
        sparing the robot the encode and the server the decode.
        """
        if len(left) != width * height or len(right) != width * height:
            raise ValueError(f"raw8 images must be width*height = {width * height} bytes each")
        header = {
            "timestamp_ns": int(timestamp_ns),
            "encoding": "raw8",
            "width": int(width),
            "height": int(height),
        }
        return await self._send_frame(header, left, right, imu)

    async def _send_frame(
        self, header: dict[str, Any], left: bytes, right: bytes, imu: ImuData | None
    ) -> bool:
        """The JSON header (with the payload sizes and IMU), then both images in one message."""
        if self.hold_back and self.unanswered >= self.server_window:
            self.held_back += 1
            if imu is not None and len(imu):  # the samples still reach the estimator
                await self.send_imu(imu)
            return False
        message = {"type": "frame", **header, "left_bytes": len(left), "right_bytes": len(right)}
        if imu is not None and len(imu):
            message["imu"] = imu.to_samples()
        await self.connection.send(json.dumps(message))
        await self.connection.send(left + right)
        self.unanswered += 1
        return True

    async def send_imu(self, imu: ImuData) -> None:
        await self.connection.send(json.dumps({"type": "imu", "samples": imu.to_samples()}))

    async def recv(self) -> StreamEvent:
        """The next answer to a frame; protocol errors raise :class:`StreamError`."""
        while True:
            message = json.loads(await self.connection.recv())
            kind = message.get("type")
            if kind in ("pose", "dropped", "rejected"):
                self.unanswered = max(0, self.unanswered - 1)
            if kind == "pose":
                return Pose.from_json(message)
            if kind == "dropped":
                return DroppedFrame(int(message["timestamp_ns"]), message["detail"])
            if kind == "rejected":
                return RejectedFrame(
                    message.get("timestamp_ns"), int(message["status"]), message["detail"]
                )
            if kind == "error":
                raise StreamError(message.get("detail", "unknown stream error"))
            # "pong" and future informational messages are skipped

    async def finish(self) -> list[tuple[int, np.ndarray]]:
        """End the session's stream and wait for it: the server answers the frames already
        sent (read them with :meth:`recv` first), flushes the back end and sends the final
        poses of the frames still in its window, returned here as (timestamp_ns, 4x4)."""
        await self.close()
        final: list[tuple[int, np.ndarray]] = []
        try:
            while True:
                message = json.loads(await self.connection.recv())
                if message.get("type") == "smoothed":
                    final = [(int(item["timestamp_ns"]), np.array(item["pose"], dtype=float))
                             for item in message["poses"]]
        except websockets.ConnectionClosed:
            return final

    async def close(self) -> None:
        """Ask the server to finish: it answers every frame already sent, then closes."""
        try:
            await self.connection.send(json.dumps({"type": "close"}))
        except websockets.ConnectionClosed:
            pass


@asynccontextmanager
async def stream(
    url: str,
    session_id: str,
    api_key: str | None = None,
    max_size: int = 16 * 1024 * 1024,
    hold_back: bool = False,
) -> AsyncIterator[FrameStream]:
    """Open the session's stream; HTTP-level refusals raise the matching ApiError.
    ``hold_back``: see :class:`FrameStream`."""
    headers = {"Authorization": f"Bearer {api_key}"} if api_key else None
    try:
        # No permessage-deflate: encoded images do not compress, deflating them only costs CPU.
        connection = await websockets.connect(
            ws_url(url, session_id), additional_headers=headers, max_size=max_size,
            compression=None,
        )
    except websockets.InvalidStatus as error:
        response = error.response
        try:
            detail = json.loads(response.body or b"{}").get("detail", "")
        except ValueError:
            detail = (response.body or b"").decode(errors="replace")
        raise error_for(response.status_code, detail or str(error)) from error
    try:
        hello = json.loads(await connection.recv())
        yield FrameStream(connection, hello, hold_back)
    finally:
        await connection.close()
