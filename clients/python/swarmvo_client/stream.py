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
    """An open stream of one session."""

    def __init__(self, connection: ClientConnection, hello: dict[str, Any]) -> None:
        self.connection = connection
        self.hello = hello

    async def send_frame(
        self, timestamp_ns: int, left: bytes, right: bytes, imu: ImuData | None = None
    ) -> None:
        """Header as JSON, then both encoded images in one binary message."""
        await self._send_frame({"timestamp_ns": int(timestamp_ns)}, left, right, imu)

    async def send_raw_frame(
        self,
        timestamp_ns: int,
        left: bytes,
        right: bytes,
        width: int,
        height: int,
        imu: ImuData | None = None,
    ) -> None:
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
        await self._send_frame(header, left, right, imu)

    async def _send_frame(
        self, header: dict[str, Any], left: bytes, right: bytes, imu: ImuData | None
    ) -> None:
        """The JSON header (with the payload sizes and IMU), then both images in one message."""
        message = {"type": "frame", **header, "left_bytes": len(left), "right_bytes": len(right)}
        if imu is not None and len(imu):
            message["imu"] = imu.to_samples()
        await self.connection.send(json.dumps(message))
        await self.connection.send(left + right)

    async def send_imu(self, imu: ImuData) -> None:
        await self.connection.send(json.dumps({"type": "imu", "samples": imu.to_samples()}))

    async def recv(self) -> StreamEvent:
        """The next answer to a frame; protocol errors raise :class:`StreamError`."""
        while True:
            message = json.loads(await self.connection.recv())
            kind = message.get("type")
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
) -> AsyncIterator[FrameStream]:
    """Open the session's stream; HTTP-level refusals raise the matching ApiError."""
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
        yield FrameStream(connection, hello)
    finally:
        await connection.close()
