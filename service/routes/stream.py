"""The WebSocket stream of one session: frame headers and images in, poses out, in order."""

from __future__ import annotations

import asyncio
import contextlib
import json
from typing import Any

from fastapi import APIRouter, HTTPException, WebSocket
from fastapi.responses import JSONResponse
from starlette.types import Message
from starlette.websockets import WebSocketDisconnect

from service.auth import AuthError, bearer_token, owner_for
from service.dependencies import live_worker, lookup_live_first, service_state
from service.imu_input import parse_imu
from service.schemas import PoseOut
from service.sessions import FrameDropped, FrameRejected, SessionGone, SessionWorker
from service.storage import SessionRecord

# Answers (poses, refusals, errors) a WebSocket client may leave unread before the server
# stops reading its socket; each is a small JSON message (images are not kept with them).
MAX_UNSENT_REPLIES = 64

router = APIRouter()


@router.websocket("/v1/sessions/{session_id}/stream")
async def stream(websocket: WebSocket, session_id: str) -> None:
    await StreamConnection(websocket, session_id).run()


class StreamConnection:
    """One WebSocket client: JSON headers + binary images in, pose messages out, in order.

    Memory is bounded twice: at most ``queue_size`` frames (with their images) wait per session,
    and at most ``MAX_UNSENT_REPLIES`` answers wait for a client that does not read them; beyond
    that this connection stops reading, so TCP flow control slows the producer.
    """

    def __init__(self, websocket: WebSocket, session_id: str) -> None:
        self.websocket = websocket
        self.session_id = session_id
        self.state = service_state(websocket)
        self.settings = self.state.settings
        self.outbox: asyncio.Queue[Any] = asyncio.Queue()
        self.credit = asyncio.Semaphore(MAX_UNSENT_REPLIES)
        self.header: dict[str, Any] | None = None
        self.parts: list[bytes] = []
        self.received = 0
        self.sender: asyncio.Task[None] | None = None
        self.image_size = (0, 0)  # the session's (width, height), known once accepted
        # Set by terminate() (the session was deleted): close code and reason to send.
        self.ending: tuple[int, str] | None = None
        self.stop = asyncio.Event()

    def terminate(self, code: int, reason: str) -> None:
        """End this stream from outside: its loop stops reading and closes with ``code``."""
        if self.ending is None:
            self.ending = (code, reason)
        self.stop.set()
        if self.sender is not None:
            self.sender.cancel()

    async def _receive(self) -> Message | None:
        """The next client message, or None once the stream was terminated."""
        if self.stop.is_set():
            return None
        receive = asyncio.ensure_future(self.websocket.receive())
        stop = asyncio.ensure_future(self.stop.wait())
        await asyncio.wait({receive, stop}, return_when=asyncio.FIRST_COMPLETED)
        stop.cancel()
        if receive.done():
            return receive.result()
        receive.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await receive
        return None

    async def _deny(self, status: int, detail: str) -> None:
        self.state.metrics.errors.labels("auth" if status == 401 else "unknown_session").inc()
        await self.websocket.send_denial_response(JSONResponse({"detail": detail}, status))

    async def run(self) -> None:
        websocket = self.websocket
        try:
            token = bearer_token(websocket.headers.get("authorization"))
            token = token or websocket.query_params.get("token") or None
            owner = owner_for(token, self.settings)
        except AuthError as error:
            await self._deny(401, str(error))
            return
        try:
            record = await lookup_live_first(self.state, self.session_id, owner)
            worker = live_worker(self.state, record)
            self.state.manager.attach(record.id, self)
        except (HTTPException, SessionGone) as error:
            await self._deny(404 if isinstance(error, SessionGone) else error.status_code,
                             str(error.detail))
            return
        try:
            await self._serve(record, worker)
        finally:
            self.state.manager.detach(record.id, self)

    async def _serve(self, record: SessionRecord, worker: SessionWorker) -> None:
        websocket = self.websocket
        await websocket.accept()
        self.image_size = (record.image_width, record.image_height)
        await websocket.send_json(
            {
                "type": "hello",
                "session_id": record.id,
                "next_index": worker.next_index,
                "last_timestamp_ns": worker.last_submitted_ns,
                "queue_size": self.settings.queue_size,
                "queue_policy": self.settings.queue_policy,
            }
        )
        sender = asyncio.create_task(self._send_loop())
        self.sender = sender
        graceful = False
        try:
            while True:
                message = await self._receive()
                if message is None or message["type"] == "websocket.disconnect":
                    break
                if message.get("text") is not None:
                    if await self._on_text(message["text"], record):
                        graceful = True
                        break
                elif message.get("bytes") is not None:
                    await self._on_bytes(message["bytes"], record)
        except (WebSocketDisconnect, RuntimeError):
            pass
        finally:
            await self.outbox.put(None)
            if self.ending is not None:
                sender.cancel()
                await asyncio.wait({sender})
                with contextlib.suppress(Exception):
                    await websocket.close(*self.ending)
            elif graceful:
                with contextlib.suppress(Exception):
                    await asyncio.wait_for(sender, timeout=120)
                with contextlib.suppress(Exception):
                    await websocket.close(1000)
            else:
                # The client left: frames it sent are still processed and stored (the futures
                # are shielded), only the answers have nobody to go to.
                sender.cancel()
                await asyncio.wait({sender})

    async def _reply(self, payload: dict[str, Any]) -> None:
        await self._acquire_credit()
        self.outbox.put_nowait(payload)

    async def _on_text(self, text: str, record: SessionRecord) -> bool:
        try:
            message = json.loads(text)
        except json.JSONDecodeError as error:
            await self._reply({"type": "error", "detail": f"message is not valid JSON: {error}"})
            return False
        if not isinstance(message, dict):
            await self._reply({"type": "error", "detail": "messages must be JSON objects"})
            return False
        kind = message.get("type")
        if kind == "frame":
            await self._start_frame(message)
        elif kind == "imu":
            try:
                samples = parse_imu({"samples": message.get("samples")}, self.settings)
                live_worker(self.state, record).add_imu(samples)
            except HTTPException as error:
                await self._reply({"type": "error", "detail": str(error.detail)})
            except FrameRejected as error:
                await self._reply({"type": "error", "detail": error.detail})
        elif kind == "ping":
            await self._reply({"type": "pong"})
        elif kind == "close":
            return True
        else:
            await self._reply(
                {"type": "error", "detail": f"unknown message type {kind!r} (frame|imu|ping|close)"}
            )
        return False

    async def _start_frame(self, message: dict[str, Any]) -> None:
        if self.header is not None:
            await self._reply(
                {
                    "type": "error",
                    "detail": "a new frame header arrived before the images of the previous "
                    "one; the previous frame was discarded",
                }
            )
        self.header, self.parts, self.received = None, [], 0
        timestamp = message.get("timestamp_ns")
        sizes = (message.get("left_bytes"), message.get("right_bytes"))
        problem = None
        if not isinstance(timestamp, int) or isinstance(timestamp, bool):
            problem = "timestamp_ns must be an integer"
        elif not 0 <= timestamp < 2**63:
            problem = "timestamp_ns is out of range"
        elif not all(isinstance(n, int) and not isinstance(n, bool) and n > 0 for n in sizes):
            problem = "left_bytes and right_bytes must be positive integers"
        elif sum(sizes) > self.settings.ws_max_message_bytes:  # type: ignore[arg-type]
            problem = f"images exceed {self.settings.ws_max_message_bytes} bytes"
        else:
            problem = self._raw_problem(message, sizes)  # type: ignore[arg-type]
        imu = None
        if problem is None and message.get("imu") is not None:
            try:
                imu = parse_imu({"samples": message["imu"]}, self.settings)
            except HTTPException as error:
                problem = str(error.detail)
        if problem is not None:
            await self._reply(
                {
                    "type": "rejected",
                    "timestamp_ns": timestamp,
                    "status": 422,
                    "detail": f"bad frame header: {problem}",
                }
            )
            return
        self.header = {"timestamp_ns": timestamp, "sizes": sizes, "imu": imu,
                       "raw": message.get("encoding") == "raw8"}

    def _raw_problem(self, message: dict[str, Any], sizes: tuple[int, int]) -> str | None:
        """Check the optional ``encoding`` of a frame header (``png`` default, or ``raw8``)."""
        encoding = message.get("encoding", "png")
        if encoding in ("png", "jpeg", "image"):
            return None
        if encoding != "raw8":
            return f"unknown encoding {encoding!r} (png|raw8)"
        width, height = message.get("width"), message.get("height")
        if not all(isinstance(n, int) and not isinstance(n, bool) and n > 0
                   for n in (width, height)):
            return "raw8 frames need positive integer width and height"
        if (width, height) != self.image_size:
            return (f"raw8 image is {width}x{height} but the session's calibration is for "
                    f"{self.image_size[0]}x{self.image_size[1]}")
        if sizes != (width * height, width * height):
            return (f"raw8 left_bytes and right_bytes must both be width*height = "
                    f"{width * height}")
        return None

    async def _on_bytes(self, data: bytes, record: SessionRecord) -> None:
        if self.header is None:
            await self._reply(
                {"type": "error", "detail": "binary message without a preceding frame header"}
            )
            return
        self.parts.append(data)
        self.received += len(data)
        left_size, right_size = self.header["sizes"]
        expected = left_size + right_size
        if self.received < expected:
            return
        header, blob = self.header, b"".join(self.parts)
        self.header, self.parts, self.received = None, [], 0
        if len(blob) != expected:
            await self._reply(
                {
                    "type": "rejected",
                    "timestamp_ns": header["timestamp_ns"],
                    "status": 422,
                    "detail": f"expected {expected} image bytes, received {len(blob)}",
                }
            )
            return
        await self._acquire_credit()
        try:
            future = live_worker(self.state, record).submit(
                header["timestamp_ns"], blob[:left_size], blob[left_size:], header["imu"],
                raw=header["raw"],
            )
        except (FrameRejected, HTTPException) as error:
            refusal = error if isinstance(error, FrameRejected) else FrameRejected(
                error.status_code, str(error.detail), "unknown_session")
            self.state.metrics.errors.labels(refusal.kind).inc()
            self.outbox.put_nowait({"type": "rejected", "timestamp_ns": header["timestamp_ns"],
                                    "status": refusal.status_code, "detail": refusal.detail})
            return
        self.outbox.put_nowait((future, header["timestamp_ns"]))

    async def _acquire_credit(self) -> None:
        """Wait for room for one more unanswered frame, unless the sender has died."""
        assert self.sender is not None
        acquire = asyncio.ensure_future(self.credit.acquire())
        await asyncio.wait({acquire, self.sender}, return_when=asyncio.FIRST_COMPLETED)
        if not acquire.done():
            acquire.cancel()
            raise WebSocketDisconnect(1011)

    async def _send_loop(self) -> None:
        while True:
            item = await self.outbox.get()
            if item is None:
                return
            if isinstance(item, dict):
                await self.websocket.send_json(item)
                self.credit.release()
                continue
            future, timestamp = item
            try:
                result = await asyncio.shield(future)
                payload = {"type": "pose", **PoseOut.of(
                    result.session_id, result.record, result.imu_samples, result.odometry,
                    result.smoothed,
                ).model_dump(mode="json")}
            except FrameDropped as error:
                payload = {"type": "dropped", "timestamp_ns": timestamp, "detail": error.detail}
            except FrameRejected as error:
                payload = {"type": "rejected", "timestamp_ns": timestamp,
                           "status": error.status_code, "detail": error.detail}
            await self.websocket.send_json(payload)
            self.credit.release()
