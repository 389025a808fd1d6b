"""A stream that outlives its server: reconnect with backoff, resend what was not answered.

    async with reliable_stream(url, session_id, api_key) as s:
        await s.send_frame(timestamp_ns, left_png, right_png, imu)
        event = await s.recv()   # Pose | RejectedFrame | DroppedFrame, each frame answered once

Behind a load balancer any replica can continue a session. When the connection breaks (the
replica died), when the server answers a frame with a passing 503 (the session is still leased
by a replica that stopped answering, the database is away) or when no answer came for
``answer_timeout_s``, the stream reconnects with exponential backoff and sends every frame not
yet answered again, oldest first. The service answers a frame it already stored with the stored
pose, so a frame is never processed twice and the robot gets one answer per frame.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import random
import time
from collections import OrderedDict
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from dataclasses import dataclass, field
from typing import Any

import websockets
from websockets.asyncio.client import ClientConnection

from swarmvo_client.models import DroppedFrame, ImuData, Pose, RejectedFrame
from swarmvo_client.stream import StreamEvent, ws_url

# Refusals that pass: reconnect (maybe to another replica) and send the frame again.
RETRY_STATUSES = frozenset({502, 503, 504})


# Seconds a connection attempt may take (the handshake through a balancer included).
OPEN_TIMEOUT_S = 30.0


@dataclass(frozen=True)
class Backoff:
    """Exponential backoff with full jitter (robots of a fleet must not retry in lockstep)."""

    first_s: float = 0.05
    max_s: float = 1.0
    factor: float = 2.0

    def delay(self, attempt: int, rng: random.Random) -> float:
        return rng.uniform(0.5, 1.0) * min(self.max_s, self.first_s * self.factor**attempt)


@dataclass
class _Frame:
    header: dict[str, Any]
    payload: bytes


@dataclass
class Outage:
    """One loss of the stream: when it broke, why, and when a frame was answered again."""

    lost_at: float
    reason: str
    answered_at: float | None = None
    reconnected_at: float | None = None  # the first server greeting after the loss
    connections: int = 0  # connections opened until a frame was answered again


@dataclass
class StreamStats:
    reconnects: int = 0
    resent: int = 0
    duplicates: int = 0  # answers the server gave from a stored pose
    outages: list[Outage] = field(default_factory=list)


class ReliableStream:
    """Frames go out at once while connected and stay buffered until they are answered."""

    def __init__(
        self,
        url: str,
        session_id: str,
        api_key: str | None = None,
        backoff: Backoff | None = None,
        answer_timeout_s: float = 10.0,
        max_size: int = 16 * 1024 * 1024,
        seed: int | None = None,
    ) -> None:
        self.url = ws_url(url, session_id)
        self.headers = {"Authorization": f"Bearer {api_key}"} if api_key else None
        self.backoff = backoff or Backoff()
        self.answer_timeout_s = answer_timeout_s
        self.max_size = max_size
        self.stats = StreamStats()
        self._rng = random.Random(seed)
        self._unanswered: OrderedDict[int, _Frame] = OrderedDict()
        self._events: asyncio.Queue[StreamEvent] = asyncio.Queue()
        self._connection: ClientConnection | None = None
        self._connected = asyncio.Event()
        self._closing = False
        self._last_progress = time.monotonic()
        self._task: asyncio.Task[None] | None = None

    # -- public

    async def start(self) -> None:
        self._task = asyncio.create_task(self._run())

    async def send_frame(
        self, timestamp_ns: int, left: bytes, right: bytes, imu: ImuData | None = None,
        raw_size: tuple[int, int] | None = None,
    ) -> None:
        """Queue a frame (PNG/JPEG, or raw 8-bit grey of ``raw_size`` = (width, height))."""
        header: dict[str, Any] = {"type": "frame", "timestamp_ns": int(timestamp_ns),
                                  "left_bytes": len(left), "right_bytes": len(right)}
        if raw_size is not None:
            header.update(encoding="raw8", width=int(raw_size[0]), height=int(raw_size[1]))
        if imu is not None and len(imu):
            header["imu"] = imu.to_samples()
        frame = _Frame(header, left + right)
        if not self._unanswered:
            self._last_progress = time.monotonic()
        self._unanswered[int(timestamp_ns)] = frame
        if self._connection is not None:
            with contextlib.suppress(websockets.ConnectionClosed, OSError):
                await self._send(self._connection, frame)

    async def recv(self) -> StreamEvent:
        """The next answer (one per frame, in the order the server answered them)."""
        return await self._events.get()

    @property
    def unanswered(self) -> int:
        return len(self._unanswered)

    async def close(self) -> None:
        """Stop reconnecting; answers still owed are not waited for."""
        self._closing = True
        if self._connection is not None:
            with contextlib.suppress(Exception):
                await self._connection.send(json.dumps({"type": "close"}))
                await asyncio.wait_for(self._connection.close(), 2.0)
        if self._task is not None:
            self._task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._task

    # -- connection loop

    async def _send(self, connection: ClientConnection, frame: _Frame) -> None:
        await connection.send(json.dumps(frame.header))
        await connection.send(frame.payload)

    async def _run(self) -> None:
        attempt = 0
        while not self._closing:
            try:
                connection = await websockets.connect(
                    self.url, additional_headers=self.headers, max_size=self.max_size,
                    # Longer than a balancer's read timeout (docker/nginx.conf: 15 s): the
                    # balancer, not this client, gives up on a stalled replica and tries the
                    # next one (a client giving up first would be sent back to it every time).
                    compression=None, open_timeout=OPEN_TIMEOUT_S,
                )
            except (OSError, websockets.InvalidHandshake, TimeoutError) as error:
                await self._pause(attempt, f"connect: {error}")
                attempt += 1
                continue
            reason = await self._serve(connection)
            attempt = 0 if reason == "answered" else attempt + 1
            if not self._closing:
                await self._pause(attempt, reason)

    async def _pause(self, attempt: int, reason: str, at_least_s: float = 0.0) -> None:
        if self._closing:
            return
        if not self.stats.outages or self.stats.outages[-1].answered_at is not None:
            self.stats.outages.append(Outage(time.perf_counter(), reason))
        await asyncio.sleep(max(at_least_s, self.backoff.delay(attempt, self._rng)))

    async def _serve(self, connection: ClientConnection) -> str:
        """Resend what is owed, then read answers until the connection must be replaced."""
        try:
            json.loads(await asyncio.wait_for(connection.recv(), 5.0))  # hello
            if self.stats.outages:
                self.stats.reconnects += 1
                outage = self.stats.outages[-1]
                if outage.answered_at is None:
                    outage.connections += 1
                    outage.reconnected_at = outage.reconnected_at or time.perf_counter()
            # Owed frames first, oldest first; frames queued meanwhile follow them. Only then
            # may send_frame() use the connection, so timestamps reach the server in order.
            sent: set[int] = set()
            while owed := [(t, f) for t, f in self._unanswered.items() if t not in sent]:
                for stamp, frame in owed:
                    self.stats.resent += int(bool(self.stats.outages))
                    await self._send(connection, frame)
                    sent.add(stamp)
            self._connection = connection
            self._last_progress = time.monotonic()
            while True:
                try:
                    text = await asyncio.wait_for(connection.recv(), 0.25)
                except TimeoutError:
                    stalled = time.monotonic() - self._last_progress
                    if self._unanswered and stalled > self.answer_timeout_s:
                        return f"no answer for {stalled:.1f} s"
                    continue
                retry = self._on_message(json.loads(text))
                if retry is not None:
                    await asyncio.sleep(retry)
                    return "server asked to retry"
        except (websockets.ConnectionClosed, OSError, TimeoutError) as error:
            return f"connection lost: {error!r}"
        finally:
            self._connection = None
            with contextlib.suppress(Exception):
                await asyncio.wait_for(connection.close(), 1.0)

    def _on_message(self, message: dict[str, Any]) -> float | None:
        """Deliver an answer; a passing refusal returns how long to wait before reconnecting."""
        kind = message.get("type")
        if kind not in ("pose", "rejected", "dropped"):
            return None
        stamp = message.get("timestamp_ns")
        if kind == "rejected" and int(message.get("status", 0)) in RETRY_STATUSES:
            return float(message.get("retry_after_s") or 0.0)
        if stamp not in self._unanswered:
            return None  # the answer to a resent frame already answered
        del self._unanswered[stamp]
        self._last_progress = time.monotonic()
        if self.stats.outages and self.stats.outages[-1].answered_at is None:
            self.stats.outages[-1].answered_at = time.perf_counter()
        if kind == "pose":
            self.stats.duplicates += int(bool(message.get("duplicate")))
            self._events.put_nowait(Pose.from_json(message))
        elif kind == "dropped":
            self._events.put_nowait(DroppedFrame(int(stamp), message["detail"]))
        else:
            self._events.put_nowait(
                RejectedFrame(stamp, int(message["status"]), message["detail"])
            )
        return None


@asynccontextmanager
async def reliable_stream(
    url: str, session_id: str, api_key: str | None = None, **options: Any
) -> AsyncIterator[ReliableStream]:
    """Open a :class:`ReliableStream`; it connects (and reconnects) in the background."""
    stream = ReliableStream(url, session_id, api_key, **options)
    await stream.start()
    try:
        yield stream
    finally:
        await stream.close()
