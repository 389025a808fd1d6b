"""Live sessions of one replica by id: created on first use, evicted when idle, their streams
ended when a session is deleted, their leases given back when the robot is done."""

from __future__ import annotations

import asyncio
import contextlib
import time
from collections import OrderedDict
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from typing import Protocol

from service.estimator_adapter import PipelineFactory
from service.lease import LeaseBook, replica_id
from service.memory import trim_free_memory
from service.metrics import Metrics
from service.pose_writer import PoseWriter
from service.sessions.frames import STREAM_CLOSE_DELETED, SessionGone
from service.sessions.live import LiveSession
from service.settings import ServiceSettings
from service.storage import SessionRecord, SmoothedPose, Store
from service.workers import ProcessRunner, Runner, ThreadRunner

MAX_REMEMBERED_DELETIONS = 10_000


class StreamHandle(Protocol):
    """An open stream of a session (a WebSocket), ended when the session is deleted or the
    server stops."""

    def terminate(self, code: int, reason: str, last: list[SmoothedPose] | None = None) -> None:
        """Close with ``code`` after sending ``last`` (the flushed smoothed poses), if any."""

    def server_stopping(self) -> None:
        """Stop reading, send what is answered within a bounded time, close with 1012."""


class SessionManager:
    """Live sessions by id, with a soft cap on pipelines held in memory."""

    def __init__(
        self,
        settings: ServiceSettings,
        store: Store,
        factory: PipelineFactory,
        metrics: Metrics,
    ) -> None:
        self.settings = settings
        self.store = store
        self.factory = factory
        self.metrics = metrics
        self.runner: Runner = (
            ProcessRunner(
                settings.workers, factory, metrics.worker_restarts.inc, settings.frame_timeout_s,
                settings.image_slots, settings.image_slot_bytes,
            )
            if settings.executor == "process"
            else ThreadRunner(settings.workers, factory)
        )
        # Database reads/writes of the consumers (SQLite serialises writers anyway).
        self.io_pool = ThreadPoolExecutor(
            max(2, min(settings.workers, 8)), thread_name_prefix="swarmvo-io"
        )
        self.pose_writer = PoseWriter(store, self.io_pool)  # one group commit for all sessions
        self.live: OrderedDict[str, LiveSession] = OrderedDict()
        self.leases = LeaseBook(store, settings.replica_id or replica_id(), settings.lease_ttl_s,
                                settings.leases)
        # Recently deleted ids (uuid4: never reused), so that a request that looked the session
        # up just before its deletion cannot bring it back to life.
        self.deleted: OrderedDict[str, None] = OrderedDict()
        self.streams: dict[str, set[StreamHandle]] = {}
        # Streams of deleted sessions, still sending their last message until they detach.
        self.ending: set[StreamHandle] = set()
        self._background: set[asyncio.Task[None]] = set()
        self._trimmer: asyncio.Task[None] | None = None
        self._on_change: Callable[[], None] = lambda: metrics.sessions_active.set(
            len(self.live)
        )

    async def start(self) -> None:
        """Start the worker processes (they import the estimator) before serving."""
        try:
            await self.runner.start()
        except BaseException:
            self.io_pool.shutdown(wait=False)
            raise
        if self.settings.memory_trim_interval_s > 0:
            self._trimmer = asyncio.get_running_loop().create_task(
                self._trim_periodically(self.settings.memory_trim_interval_s))

    async def _trim_periodically(self, interval_s: float) -> None:
        """Give the server's freed heap pages back now and then: the frames it received (724
        KB each, refused ones too) leave freed buffers in every thread's heap."""
        loop = asyncio.get_running_loop()
        while True:
            await asyncio.sleep(interval_s)
            await loop.run_in_executor(self.io_pool, trim_free_memory)

    def live_session(self, record: SessionRecord) -> LiveSession:
        """The session's live state, created on first use; SessionGone once it was deleted."""
        if record.id in self.deleted:
            raise SessionGone()
        live = self.live.get(record.id)
        if live is not None:
            self.live.move_to_end(record.id)
            return live
        self._evict_idle()
        slot = self.runner.assign(record.id)
        live = LiveSession(
            record, self.settings, self.store, self.runner, slot, self.io_pool, self.metrics,
            self.leases, self.pose_writer,
        )
        self.live[record.id] = live
        self._on_change()
        return live

    def _evict_idle(self) -> None:
        while len(self.live) >= self.settings.max_active_sessions:
            victim = next((sid for sid, w in self.live.items() if w.idle), None)
            if victim is None:
                return  # all busy: exceed the soft cap rather than refuse work
            live = self.live.pop(victim)
            # Flushed and freed now, not when the close task runs: the session may come back
            # before that, and its new pipeline must not be dropped by this late release.
            flushed = live.start_flush()
            self.runner.release(live.slot, victim)
            asyncio.get_running_loop().create_task(self._unload(live, flushed))

    @staticmethod
    async def _unload(
        live: LiveSession, flushed: asyncio.Future[list[SmoothedPose]]
    ) -> None:
        """An evicted session: its back end's last poses are stored, its consumer stopped."""
        await live.close("session unloaded")
        await live.finish_flush(flushed)

    def attach(self, session_id: str, stream: StreamHandle) -> None:
        """Register an open stream; SessionGone when the session was deleted meanwhile."""
        if session_id in self.deleted:
            raise SessionGone()
        self.streams.setdefault(session_id, set()).add(stream)

    def detach(self, session_id: str, stream: StreamHandle, finished: bool = False) -> None:
        """Forget a stream; ``finished`` (the robot said close): give the lease up once idle."""
        self.ending.discard(stream)
        streams = self.streams.get(session_id)
        if streams is not None:
            streams.discard(stream)
            if not streams:
                del self.streams[session_id]
        live = self.live.get(session_id)
        if finished and live is not None and session_id not in self.streams:
            self._release_later(live)

    async def stop_streams(self, grace_s: float) -> None:
        """Tell every open stream the server is stopping; wait up to ``grace_s`` for them to close.

        Called before the server waits for its connections: a stream whose robot stopped
        reading would otherwise hold the shutdown until the server gives up and cancels it.
        Frames already queued are not touched here; :meth:`shutdown` processes and stores them.
        """
        for stream in [*self.ending, *(s for group in self.streams.values() for s in group)]:
            stream.server_stopping()
        deadline = time.monotonic() + grace_s
        while (self.streams or self.ending) and time.monotonic() < deadline:
            await asyncio.sleep(0.05)

    async def finish(self, session_id: str) -> list[SmoothedPose]:
        """The robot's end of stream over REST, as a WebSocket's close message: once the frames
        sent so far are done the back end's window is flushed (stored and returned) and, with no
        stream open, the lease is given up. A later frame resumes from the last stored pose."""
        if session_id in self.deleted:
            raise SessionGone()
        live = self.live.get(session_id)
        if live is None:  # nothing live here: nothing held back
            return []
        flushed = await live.flush_after_queued()
        if session_id not in self.streams:
            self._release_later(live)
        return flushed

    def _release_later(self, live: LiveSession) -> None:
        task = asyncio.get_running_loop().create_task(self._release_when_idle(live))
        self._background.add(task)  # referenced until done (the loop keeps weak ones)
        task.add_done_callback(self._background.discard)

    async def _release_when_idle(self, live: LiveSession, wait_s: float = 30.0) -> None:
        deadline = time.monotonic() + wait_s

        def drained() -> bool:
            return not live.busy and live.queue.empty()

        while not drained() and time.monotonic() < deadline:
            await asyncio.sleep(0.05)
        if drained() and live.session_id not in self.streams:
            with contextlib.suppress(Exception):  # best effort: the lease expires anyway
                await asyncio.get_running_loop().run_in_executor(
                    self.io_pool, live.release_lease)

    async def remove(self, session_id: str) -> None:
        """Delete the live state: queued frames are refused with 404, the back end's window is
        flushed to the open streams, which are then closed."""
        self.deleted[session_id] = None
        while len(self.deleted) > MAX_REMEMBERED_DELETIONS:
            self.deleted.popitem(last=False)
        live = self.live.pop(session_id, None)
        last: list[SmoothedPose] = []
        if live is not None:
            self._on_change()
            last = await live.close("session was deleted", deleted=True)
            self.runner.release(live.slot, session_id)
        for stream in self.streams.pop(session_id, set()):
            self.ending.add(stream)
            stream.terminate(STREAM_CLOSE_DELETED, "session deleted", last)

    async def shutdown(self, drain_seconds: float = 10.0) -> None:
        if self._trimmer is not None:
            self._trimmer.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._trimmer
        sessions = list(self.live.values())
        self.live.clear()
        self._on_change()
        await asyncio.gather(
            *(w.close("server shutting down", drain_seconds) for w in sessions),
            return_exceptions=True,
        )
        # Leases given back: other replicas take these sessions over at once, not on expiry.
        for live in sessions:
            with contextlib.suppress(Exception):
                await asyncio.get_running_loop().run_in_executor(self.io_pool,
                                                                 live.release_lease)
        await self.runner.shutdown()
        await self.pose_writer.drained()  # a batch still waiting for its commit is stored
        self.io_pool.shutdown(wait=True, cancel_futures=False)
