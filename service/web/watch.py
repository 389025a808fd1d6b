"""The read-only watcher channel of one session, and the live sessions list.

``/v1/sessions/{id}/watch`` is a WebSocket next to the robot's stream. The key does not travel
in the URL (access logs print URLs): the first message is ``{"type": "auth", "token": KEY}``.
The server answers ``hello``, then every stored pose in ``poses`` messages (columns, see
:mod:`service.web.feed`), ``synced`` once the backlog is sent, then new poses as they are
stored and a ``state`` message every second. Poses are read from the store, so a watcher sees
the same trajectory whichever server process the robot streams to.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import time
from typing import Any

from fastapi import APIRouter, WebSocket
from pydantic import BaseModel, ValidationError
from sqlalchemy.exc import OperationalError
from starlette.concurrency import run_in_threadpool
from starlette.websockets import WebSocketDisconnect, WebSocketState

from service.auth import AuthError, owner_for
from service.dependencies import SESSION_ID, Owner, ServiceState, State
from service.imu_input import brief
from service.messages import PongMessage
from service.storage import SessionRecord
from service.web.feed import (
    SessionActivity,
    WorldFrame,
    pose_columns,
    read_poses,
    session_summary,
    smoothed_columns,
)
from service.web.watch_messages import (
    AUTH_MESSAGE,
    PING_MESSAGE,
    AuthMessage,
    StateMessage,
    SyncedMessage,
    WatchError,
    WatchHello,
    WorldMessage,
)

AUTH_TIMEOUT_S = 10.0
# Poses per message while catching up (a 10,000-pose backlog goes in a few messages).
CHUNK = 2000
# Store polling: quick while poses keep coming, slow when the session is quiet.
FAST_POLL_S = 0.025
SLOW_POLL_S = 0.5
STATE_EVERY_S = 1.0
# Close codes (4000-4999 are the application's): the page shows the ``detail`` sent before.
CLOSE_UNAUTHORIZED = 4401
CLOSE_NOT_FOUND = 4404
CLOSE_BAD_REQUEST = 4400

logger = logging.getLogger("swarmvo.service")
router = APIRouter()


@router.get("/v1/live/sessions", tags=["live view"])
async def live_sessions(owner: Owner, state: State) -> dict[str, Any]:
    """The key's sessions with frames, frames/s, last update and the newest pose's status."""

    def read() -> list[tuple[SessionRecord, Any]]:
        records = state.store.list_sessions(owner)
        return [(r, state.store.last_pose(r.id)) for r in records]

    rows = await run_in_threadpool(read)
    live = state.manager.live
    return {
        "server_time": time.time(),
        "sessions": [session_summary(r, live.get(r.id), last) for r, last in rows],
    }


@router.websocket("/v1/sessions/{session_id}/watch")
async def watch(websocket: WebSocket, session_id: str) -> None:
    await WatchConnection(websocket, session_id).run()


class WatchConnection:
    """One browser watching one session: authenticate, send the backlog, then follow."""

    def __init__(self, websocket: WebSocket, session_id: str) -> None:
        self.websocket = websocket
        self.session_id = session_id
        self.state: ServiceState = websocket.app.state.swarmvo
        self.sent = 0  # next frame index to send
        self.world: WorldFrame | None = None  # known once the session has a pose
        self.smoothed_ns = -1  # timestamp of the newest smoothed pose sent
        self.closed = asyncio.Event()

    async def _send(self, message: BaseModel) -> None:
        await self.websocket.send_json(message.model_dump(mode="json"))

    async def _fail(self, status: int, detail: str, code: int) -> None:
        label = {401: "auth", 404: "unknown_session"}.get(status, "validation")
        self.state.metrics.errors.labels(label).inc()
        with contextlib.suppress(Exception):
            await self._send(WatchError(status=status, detail=detail))
            await self.websocket.close(code)

    async def run(self) -> None:
        await self.websocket.accept()
        try:
            record = await self._authenticate()
        except (WebSocketDisconnect, RuntimeError):
            return
        if record is None:
            return
        reader = asyncio.create_task(self._read_until_closed())
        try:
            await self._follow(record)
        except (WebSocketDisconnect, RuntimeError):
            pass
        except OperationalError as error:  # the database went away: the page will reconnect
            logger.error("watcher of session %s: database unavailable: %s", self.session_id,
                         str(error).splitlines()[0])
            with contextlib.suppress(Exception):
                await self._send(WatchError(status=503, detail="database unavailable; retry later"))
                await self.websocket.close(1011)
        finally:
            reader.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await reader

    async def _authenticate(self) -> SessionRecord | None:
        try:
            text = await asyncio.wait_for(self.websocket.receive_text(), AUTH_TIMEOUT_S)
        except TimeoutError:
            await self._fail(
                401, f"no auth message within {AUTH_TIMEOUT_S:.0f} s", CLOSE_UNAUTHORIZED
            )
            return None
        except KeyError:  # a binary message
            await self._fail(400, "the first message must be text (JSON)", CLOSE_BAD_REQUEST)
            return None
        message = _auth_message(text)
        if isinstance(message, str):
            await self._fail(400, message, CLOSE_BAD_REQUEST)
            return None
        token = message.token or None
        try:
            owner = owner_for(token, self.state.settings)
        except AuthError as error:
            await self._fail(401, str(error), CLOSE_UNAUTHORIZED)
            return None
        record = None
        if SESSION_ID.match(self.session_id):
            record = await run_in_threadpool(self.state.store.get_session, self.session_id, owner)
        if record is None:
            await self._fail(404, f"unknown session {self.session_id!r}", CLOSE_NOT_FOUND)
            return None
        self.sent = message.since
        return record

    async def _read_until_closed(self) -> None:
        """The channel is read-only; reading still notices the browser leaving."""
        try:
            while True:
                text = await self.websocket.receive_text()
                with contextlib.suppress(ValidationError):
                    PING_MESSAGE.validate_json(text)
                    await self._send(PongMessage())
                    continue
                await self._send(WatchError(
                    status=400, detail="the watch channel is read-only "
                    '(it answers {"type": "ping"}; frames go to /v1/sessions/{id}/stream)'
                ))
        except (WebSocketDisconnect, RuntimeError, KeyError):
            pass
        finally:
            self.closed.set()

    async def _frame_count(self) -> int | None:
        """Stored poses of the session: from its live session here, else from the store."""
        live = self.state.manager.live.get(self.session_id)
        if live is not None:
            return live.next_index
        record = await run_in_threadpool(self.state.store.get_session, self.session_id)
        return None if record is None else record.frame_count

    async def _send_new(self, count: int) -> bool:
        """Send the poses from ``self.sent`` up to ``count``; True when there were some.

        Read and sent in chunks, the next read while this one is sent: a long run's backlog
        is never all in memory at once, and the browser parses one chunk while the next is read.
        """
        store = self.state.store
        start = self.sent
        sent_any = False
        reading: asyncio.Future[Any] | None = None

        def read_from(index: int) -> asyncio.Future[Any]:
            return asyncio.ensure_future(
                run_in_threadpool(read_poses, store, self.session_id, index, CHUNK))

        try:
            while start < count or reading is not None:
                records = await (reading or read_from(start))
                reading = None
                if not records:
                    break
                start = records[-1].frame_index + 1
                if start < count:
                    reading = read_from(start)
                if self.world is None:  # frame 0 fixes the world (its whole pose is needed)
                    first = await run_in_threadpool(store.poses, self.session_id, 0, 1)
                    self.world = WorldFrame.of(first[0])
                    await self._send(WorldMessage(**self.world.axes()))
                await self._send(pose_columns(records, self.world))
                self.sent = start
                sent_any = True
        finally:
            if reading is not None:  # the browser left while a chunk was being read
                reading.cancel()
        return sent_any

    async def _send_smoothed(self) -> None:
        """The smoother's final poses stored since the last sent."""
        if self.world is None:
            return
        new = await run_in_threadpool(
            self.state.store.smoothed, self.session_id, self.smoothed_ns
        )
        if not new:
            return
        self.smoothed_ns = new[-1][0]
        await self._send(smoothed_columns(new))

    async def _send_state(self, count: int) -> None:
        live = self.state.manager.live.get(self.session_id)
        activity = SessionActivity.of(live)
        await self._send(
            StateMessage(frame_count=count, server_time=time.time(), **activity.as_json())
        )

    async def _follow(self, record: SessionRecord) -> None:
        websocket = self.websocket
        await self._send(WatchHello(session_id=record.id, name=record.name,
                                    created_at=record.created_at.isoformat()))
        count = await self._frame_count()
        await self._send_new(count or 0)
        await self._send_smoothed()
        await self._send(SyncedMessage(frame_count=self.sent))
        await self._send_state(self.sent)
        state_due = time.monotonic() + STATE_EVERY_S
        quiet_since = time.monotonic()
        while not self.closed.is_set() and websocket.client_state == WebSocketState.CONNECTED:
            busy = time.monotonic() - quiet_since < 1.0
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(self.closed.wait(), FAST_POLL_S if busy else SLOW_POLL_S)
            count = await self._frame_count()
            if count is None:
                await self._fail(404, "the session was deleted", CLOSE_NOT_FOUND)
                return
            if await self._send_new(count):
                quiet_since = time.monotonic()
                await self._send_smoothed()
            if time.monotonic() >= state_due:
                await self._send_smoothed()  # also those flushed when a stream ended
                await self._send_state(count)
                state_due = time.monotonic() + STATE_EVERY_S


def _auth_message(text: str) -> AuthMessage | str:
    """The parsed first message, or what is wrong with it."""
    try:
        data = json.loads(text)
    except json.JSONDecodeError:
        return "the first message must be JSON"
    if not isinstance(data, dict) or data.get("type") != "auth":
        return 'the first message must be {"type": "auth", "token": "<API key>"}'
    try:
        return AUTH_MESSAGE.validate_python(data)
    except ValidationError as error:
        return brief(error)
