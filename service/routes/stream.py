"""The WebSocket stream of one session: frame headers and images in, poses out, in order."""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
from dataclasses import dataclass
from typing import Any

from fastapi import APIRouter, HTTPException, WebSocket
from fastapi.responses import JSONResponse
from pydantic import BaseModel, ValidationError
from sqlalchemy.exc import DBAPIError
from starlette.types import Message
from starlette.websockets import WebSocketDisconnect

from service.auth import AuthError, bearer_token, owner_for
from service.dependencies import live_session, lookup_live_first, service_state
from service.imu_input import brief, imu_arrays
from service.messages import (
    CLIENT_MESSAGE,
    CLIENT_TYPES,
    ClientMessage,
    DroppedMessage,
    ErrorMessage,
    FrameHeader,
    HelloMessage,
    ImuMessage,
    PingMessage,
    PongMessage,
    PoseMessage,
    RejectedMessage,
    ServerMessage,
    SmoothedMessage,
)
from service.sessions import (
    Answered,
    FrameDropped,
    FrameRejected,
    ImuSamples,
    LiveSession,
    SessionGone,
)
from service.storage import SessionRecord, SmoothedPose

logger = logging.getLogger("swarmvo.service")

# Answers (poses, refusals, errors) a WebSocket client may leave unread before the server
# stops reading its socket; each is a small JSON message (images are not kept with them).
MAX_UNSENT_REPLIES = 64

# Outbox marker: flush the session's back end once the answers before it are sent.
_FLUSH = object()
# How long a stream of a deleted session may take to send its last message.
FINAL_MESSAGE_TIMEOUT_S = 5.0
# How long a robot's close message may take to be answered (every frame, then the flush).
GRACEFUL_CLOSE_TIMEOUT_S = 120.0
# Once the server is stopping: how long answers already due may still take to be sent. Frames
# still queued are processed and stored at shutdown whether or not their answer goes out.
STOPPING_DRAIN_S = 2.0
# How long the close frame may take to be written (a client that stopped reading never takes it).
CLOSE_SEND_TIMEOUT_S = 1.0
# Close code and reason for the streams of a stopping server (1012: service restart).
STREAM_CLOSE_STOPPING = (1012, "server stopping; reconnect to continue")

# Answers in order: a ready message, (future, timestamp_ns) of a frame being processed, or
# the flush marker.
_Outgoing = BaseModel | tuple[asyncio.Future[Answered], int] | object
# Flushes after a normal close, kept referenced until they are done.
_PENDING_FLUSHES: set[asyncio.Task[Any]] = set()

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
        self.outbox: asyncio.Queue[_Outgoing | None] = asyncio.Queue()
        self.credit = asyncio.Semaphore(MAX_UNSENT_REPLIES)
        self.header: _Pending | None = None
        self.parts: list[bytes] = []
        self.received = 0
        self.sender: asyncio.Task[None] | None = None
        self.image_size = (0, 0)  # the session's (width, height), known once accepted
        # Set by terminate() (the session was deleted) or server_stopping(): close code and
        # reason to send.
        self.ending: tuple[int, str] | None = None
        self.stop = asyncio.Event()
        self.stopped: asyncio.Future[object] | None = None  # waits on ``stop``, made on first use
        self.server_stop = asyncio.Event()  # set once the server is stopping

    def terminate(self, code: int, reason: str, last: list[SmoothedPose] | None = None) -> None:
        """End this stream from outside: its loop stops reading and closes with ``code``,
        after a last ``smoothed`` message when the session's back end was flushed."""
        if self.ending is None:
            self.ending = (code, reason)
        self.stop.set()
        if last is not None and self.sender is not None and not self.sender.done():
            self.outbox.put_nowait(SmoothedMessage.of(self.session_id, last))
            self.outbox.put_nowait(None)
        elif self.sender is not None:
            self.sender.cancel()

    def server_stopping(self) -> None:
        """The server is stopping: stop reading, send what is due for a short while (even after
        the robot's close message), then close with 1012 so the robot reconnects elsewhere."""
        if self.ending is None:
            self.ending = STREAM_CLOSE_STOPPING
        self.server_stop.set()
        self.stop.set()

    def _stop_waiter(self) -> asyncio.Future[object]:
        """One waiter on the stop event for the whole connection (not one per message)."""
        if self.stopped is None:
            self.stopped = asyncio.ensure_future(self.stop.wait())
        return self.stopped

    async def _receive(self) -> Message | None:
        """The next client message, or None once the stream was terminated.

        One waiter on the stop event serves the whole connection: a task per message would be
        created and cancelled twice per frame (header and images).
        """
        if self.stop.is_set():
            return None
        receive = asyncio.ensure_future(self.websocket.receive())
        await asyncio.wait({receive, self._stop_waiter()}, return_when=asyncio.FIRST_COMPLETED)
        if receive.done():
            return receive.result()
        receive.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await receive
        return None

    async def _deny(self, status: int, detail: str) -> None:
        kind = {401: "auth", 503: "storage"}.get(status, "unknown_session")
        self.state.metrics.errors.labels(kind).inc()
        headers = {"Retry-After": "1"} if status == 503 else None
        await self.websocket.send_denial_response(
            JSONResponse({"detail": detail}, status, headers=headers))

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
            live = live_session(self.state, record)
            self.state.manager.attach(record.id, self)
        except (HTTPException, SessionGone) as error:
            await self._deny(404 if isinstance(error, SessionGone) else error.status_code,
                             str(error.detail))
            return
        except DBAPIError as error:  # the database is away: the robot retries later
            logger.error("stream refused, database unavailable: %s", str(error).splitlines()[0])
            await self._deny(503, "database unavailable; retry later")
            return
        finished = False
        try:
            finished = await self._serve(record, live)
        finally:
            self.state.manager.detach(record.id, self, finished)

    async def _serve(self, record: SessionRecord, live: LiveSession) -> bool:
        """Serve the stream; True when the robot ended it with a close message."""
        websocket = self.websocket
        await websocket.accept()
        self.image_size = (record.image_width, record.image_height)
        hello = HelloMessage(
            session_id=record.id, next_index=live.next_index,
            last_timestamp_ns=live.last_submitted_ns, queue_size=self.settings.queue_size,
            queue_policy=self.settings.queue_policy,
        )
        await websocket.send_json(hello.model_dump(mode="json"))
        sender = asyncio.create_task(self._send_loop())
        self.sender = sender
        graceful = False
        try:
            while True:
                message = await self._receive()
                if message is None:
                    break
                if message["type"] == "websocket.disconnect":
                    # A normal close ends the session's stream as a close message does (the
                    # answers have nobody to go to); a lost connection keeps the window.
                    live = self.state.manager.live.get(record.id)
                    if message.get("code") in (1000, 1001) and live is not None:
                        _flush_later(live)
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
            if self.stopped is not None:
                self.stopped.cancel()
            if graceful and self.ending is None:
                # The back end's window follows the answers, then the stream closes.
                await self.outbox.put(_FLUSH)
            await self.outbox.put(None)
            await self._finish(sender, graceful)
        return graceful

    async def _finish(self, sender: asyncio.Task[None], graceful: bool) -> None:
        """Let the sender send what is due (bounded), then close the socket.

        A cancelled sender loses answers only: frames already submitted are still processed
        and stored (their futures are shielded), and a stopping server flushes every back end.
        """
        if self.ending is None and not graceful:
            # The client left: only the answers have nobody to go to.
            sender.cancel()
            await asyncio.wait({sender})
            return
        limit = GRACEFUL_CLOSE_TIMEOUT_S if self.ending is None else FINAL_MESSAGE_TIMEOUT_S
        await self._wait_sender(sender, limit)
        sender.cancel()
        await asyncio.wait({sender})
        code, reason = self.ending or (1000, "")
        with contextlib.suppress(Exception):
            # Bounded: a client that stopped reading leaves the socket unwritable for good.
            await asyncio.wait_for(self.websocket.close(code, reason), CLOSE_SEND_TIMEOUT_S)

    async def _wait_sender(self, sender: asyncio.Task[None], limit_s: float) -> None:
        """Wait up to ``limit_s`` for the sender, cut short when the stream is ended from
        outside meanwhile: ``FINAL_MESSAGE_TIMEOUT_S`` once its session is deleted,
        ``STOPPING_DRAIN_S`` once the server stops."""
        ended = asyncio.ensure_future(self.stop.wait())
        stopping = asyncio.ensure_future(self.server_stop.wait())
        try:
            await asyncio.wait({sender, ended}, timeout=limit_s,
                               return_when=asyncio.FIRST_COMPLETED)
            if sender.done() or not ended.done():
                return
            await asyncio.wait({sender, stopping}, timeout=FINAL_MESSAGE_TIMEOUT_S,
                               return_when=asyncio.FIRST_COMPLETED)
            if stopping.done() and not sender.done():
                await asyncio.wait({sender}, timeout=STOPPING_DRAIN_S)
        finally:
            ended.cancel()
            stopping.cancel()

    async def _reply(self, message: ServerMessage) -> None:
        await self._acquire_credit()
        self.outbox.put_nowait(message)

    async def _on_text(self, text: str, record: SessionRecord) -> bool:
        """Handle one client message; True when the client closes the stream."""
        try:
            # Parsed and validated in one step (13 us for a header with 10 IMU samples, against
            # 40 us for json.loads and then the models); what fails is looked at again below
            # for the precise answer.
            message = CLIENT_MESSAGE.validate_json(text)
        except ValidationError:
            message = await self._invalid(text)
            if message is None:
                return False
        if isinstance(message, FrameHeader):
            await self._start_frame(message, record)
        elif isinstance(message, ImuMessage):
            try:
                samples = imu_arrays(message.samples, self.settings)
                live_session(self.state, record).add_imu(samples)
            except HTTPException as error:
                await self._reply(ErrorMessage(detail=str(error.detail)))
            except FrameRejected as error:
                await self._reply(ErrorMessage(detail=error.detail))
        elif isinstance(message, PingMessage):
            await self._reply(PongMessage())
        else:
            return True
        return False

    async def _invalid(self, text: str) -> ClientMessage | None:
        """A message that did not validate as it came: the reason answered (None), or the
        message when it validates once parsed (never expected; the two ways agree)."""
        try:
            raw = json.loads(text)
        except json.JSONDecodeError as error:
            await self._reply(ErrorMessage(detail=f"message is not valid JSON: {error}"))
            return None
        if not isinstance(raw, dict):
            await self._reply(ErrorMessage(detail="messages must be JSON objects"))
            return None
        kind = raw.get("type")
        if kind not in CLIENT_TYPES:
            await self._reply(ErrorMessage(
                detail=f"unknown message type {kind!r} ({'|'.join(CLIENT_TYPES)})"))
            return None
        try:
            return CLIENT_MESSAGE.validate_python(raw)
        except ValidationError as error:
            await self._refuse(kind, raw, brief(error, skip=1))
            return None

    async def _refuse(self, kind: str, raw: dict[str, Any], problem: str) -> None:
        """A message of a known type that does not validate: a frame header is rejected (with
        the timestamp it gave, whatever it was), anything else is an error."""
        if kind == "frame":
            await self._discard_pending()
            await self._reply(RejectedMessage(timestamp_ns=raw.get("timestamp_ns"), status=422,
                                              detail=f"bad frame header: {problem}"))
        elif kind == "imu":
            await self._reply(ErrorMessage(detail=f"invalid IMU samples: {problem}"))
        else:
            await self._reply(ErrorMessage(detail=f"invalid {kind} message: {problem}"))

    async def _discard_pending(self) -> None:
        """A new frame header ends a frame whose images did not all arrive (one refused from
        its header has its answer already)."""
        if self.header is not None and not self.header.answered:
            await self._reply(ErrorMessage(
                detail="a new frame header arrived before the images of the previous one; the "
                "previous frame was discarded"))
        self.header, self.parts, self.received = None, [], 0

    async def _start_frame(self, header: FrameHeader, record: SessionRecord) -> None:
        await self._discard_pending()
        problem = self._size_problem(header)
        imu = None
        if problem is None and header.imu is not None:
            try:
                imu = imu_arrays(header.imu, self.settings)
            except HTTPException as error:
                problem = str(error.detail)
        if problem is not None:
            await self._reply(RejectedMessage(timestamp_ns=header.timestamp_ns, status=422,
                                              detail=f"bad frame header: {problem}"))
            return
        try:
            refusal = live_session(self.state, record).refusal_before_images(
                header.timestamp_ns, imu)
        except (FrameRejected, HTTPException):
            refusal = None  # submit() meets the same problem and answers it, after the images
        if refusal is not None:
            # Answered now; its images are counted as they arrive, never kept.
            self.state.metrics.errors.labels(refusal.kind).inc()
            await self._reply(RejectedMessage(timestamp_ns=header.timestamp_ns,
                                              status=refusal.status_code, detail=refusal.detail))
        self.header = _Pending(header, imu, answered=refusal is not None)

    def _size_problem(self, header: FrameHeader) -> str | None:
        """What the header's own validation cannot know: this server's limit, the session's size."""
        if header.left_bytes + header.right_bytes > self.settings.ws_max_message_bytes:
            return f"images exceed {self.settings.ws_max_message_bytes} bytes"
        if header.encoding == "raw8" and (header.width, header.height) != self.image_size:
            return (f"raw8 image is {header.width}x{header.height} but the session's calibration "
                    f"is for {self.image_size[0]}x{self.image_size[1]}")
        return None

    async def _on_bytes(self, data: bytes, record: SessionRecord) -> None:
        if self.header is None:
            await self._reply(
                ErrorMessage(detail="binary message without a preceding frame header"))
            return
        pending = self.header
        if not pending.answered:
            self.parts.append(data)
        self.received += len(data)
        header, imu = pending.header, pending.imu
        expected = header.left_bytes + header.right_bytes
        if self.received < expected:
            return
        parts, received = self.parts, self.received
        self.header, self.parts, self.received = None, [], 0
        if pending.answered:
            return  # refused from its header
        if received != expected:
            await self._reply(RejectedMessage(
                timestamp_ns=header.timestamp_ns, status=422,
                detail=f"expected {expected} image bytes, received {received}"))
            return
        left, right = _split_images(parts, header.left_bytes)
        await self._acquire_credit()
        try:
            future = live_session(self.state, record).submit(
                header.timestamp_ns, left, right, imu, raw=header.encoding == "raw8",
            )
        except (FrameRejected, HTTPException) as error:
            refusal = error if isinstance(error, FrameRejected) else FrameRejected(
                error.status_code, str(error.detail), "unknown_session")
            self.state.metrics.errors.labels(refusal.kind).inc()
            self.outbox.put_nowait(RejectedMessage(
                timestamp_ns=header.timestamp_ns, status=refusal.status_code,
                detail=refusal.detail))
            return
        self.outbox.put_nowait((future, header.timestamp_ns))

    async def _acquire_credit(self) -> None:
        """Wait for room for one more unanswered frame, unless the sender has died or the stream
        is ending (the session deleted, the server stopping)."""
        assert self.sender is not None
        acquire = asyncio.ensure_future(self.credit.acquire())
        await asyncio.wait({acquire, self.sender, self._stop_waiter()},
                           return_when=asyncio.FIRST_COMPLETED)
        if not acquire.done():
            acquire.cancel()
            raise WebSocketDisconnect(1011)

    async def _send_loop(self) -> None:
        while True:
            item = await self.outbox.get()
            if item is None:
                return
            if item is _FLUSH:
                live = self.state.manager.live.get(self.session_id)
                last = [] if live is None else await live.flush_after_queued()
                await self.websocket.send_json(
                    SmoothedMessage.of(self.session_id, last).model_dump(mode="json")
                )
                continue
            message = item if isinstance(item, BaseModel) else await self._outcome(*item)
            # Serialised by pydantic in one step (a fifth of a dict dump plus json.dumps).
            await self.websocket.send_text(message.model_dump_json())
            self.credit.release()

    @staticmethod
    async def _outcome(future: asyncio.Future[Answered], timestamp_ns: int) -> ServerMessage:
        """The answer to a submitted frame, once its pose is stored (or it was refused)."""
        try:
            result = await asyncio.shield(future)
        except FrameDropped as error:
            return DroppedMessage(timestamp_ns=timestamp_ns, detail=error.detail)
        except FrameRejected as error:
            return RejectedMessage(timestamp_ns=timestamp_ns, status=error.status_code,
                                   detail=error.detail, retry_after_s=error.retry_after_s)
        # The answer was validated where it was built: not again for every frame.
        return PoseMessage.model_construct(**dict(result.answer), duplicate=result.duplicate)


def _flush_later(live: LiveSession) -> None:
    """Flush once the frames already sent are done, without waiting for it here."""
    task = asyncio.get_running_loop().create_task(live.flush_after_queued())
    _PENDING_FLUSHES.add(task)
    task.add_done_callback(_PENDING_FLUSHES.discard)


def _split_images(parts: list[bytes], left_bytes: int) -> tuple[bytes | memoryview,
                                                               bytes | memoryview]:
    """The left and right images of a frame's binary messages: views of the one message that
    holds both (the usual case; two fresh copies cost 0.4 ms of page faults per frame), the
    messages themselves when there is one per image, copied only when split across messages."""
    if len(parts) == 2 and len(parts[0]) == left_bytes:
        return parts[0], parts[1]
    blob = memoryview(parts[0] if len(parts) == 1 else b"".join(parts))
    return blob[:left_bytes], blob[left_bytes:]


@dataclass
class _Pending:
    """A frame header whose images are still arriving."""

    header: FrameHeader
    imu: ImuSamples | None
    answered: bool = False  # refused from its header: the images are counted, not kept
