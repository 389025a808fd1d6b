"""Per-session consumers: a bounded queue, strict timestamp order, CPU work off the event loop.

Each live session has one consumer task that takes frames from its queue one at a time and hands
them to its worker (see :mod:`service.workers`: a pinned process, or a thread), so frames of one
session never overlap while different sessions use all workers. The pose is committed to the
database (in an I/O thread) before its future resolves, i.e. before any client can see it.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import threading
import time
from collections import OrderedDict, deque
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

from estimator.types import ImuBatch, TimestampOrderError, check_timestamp_order
from service.answer import FrameAnswer, flat_of
from service.estimator_adapter import PipelineFactory, PreparedSession
from service.images import ImageLimits
from service.metrics import Metrics
from service.settings import ServiceSettings
from service.storage import SessionRecord, Store
from service.workers import (
    FrameFailure,
    FrameProcessed,
    FrameRequest,
    PipelineSpec,
    ProcessRunner,
    Runner,
    ThreadRunner,
)

logger = logging.getLogger("swarmvo.service")
# Smoothed poses a live session keeps for GET .../smoothed (the newest; they are not stored).
SMOOTHED_KEEP = 20_000

# WebSocket close code (application range 4000-4999) sent to streams of a deleted session.
STREAM_CLOSE_DELETED = 4404
MAX_REMEMBERED_DELETIONS = 10_000


class FrameRejected(Exception):
    """A frame the service will not process; carries the HTTP status that explains why."""

    def __init__(self, status_code: int, detail: str, kind: str) -> None:
        super().__init__(detail)
        self.status_code = status_code
        self.detail = detail
        self.kind = kind


class SessionGone(FrameRejected):
    """The session was deleted: everything sent for it afterwards is answered 404."""

    def __init__(self) -> None:
        super().__init__(404, "session was deleted", "unknown_session")


class StreamHandle(Protocol):
    """An open stream of a session (a WebSocket), ended when the session is deleted."""

    def terminate(self, code: int, reason: str) -> None: ...


class FrameDropped(FrameRejected):
    """A queued frame discarded for a newer one (queue policy ``drop_oldest``)."""

    def __init__(self, detail: str) -> None:
        super().__init__(503, detail, "dropped")


@dataclass
class ImuSamples:
    """IMU samples in arrival order (sorted and de-duplicated when consumed)."""

    timestamps_ns: np.ndarray
    gyro: np.ndarray
    accel: np.ndarray

    def __len__(self) -> int:
        return len(self.timestamps_ns)


@dataclass
class FrameJob:
    timestamp_ns: int
    left: bytes
    right: bytes
    future: asyncio.Future[FrameAnswer]
    raw: bool = False
    received: float = field(default_factory=time.perf_counter)


@dataclass
class _ImuTake:
    """IMU samples chosen for a frame; the buffer only gives them up once the frame is used."""

    batch: ImuBatch | None
    remainder: list[ImuSamples]
    parts: int


class LiveSession:
    """The live state of one session: its queue, its worker slot and its IMU buffer."""

    def __init__(
        self,
        record: SessionRecord,
        settings: ServiceSettings,
        store: Store,
        runner: Runner,
        slot: int,
        io_pool: ThreadPoolExecutor,
        metrics: Metrics,
    ) -> None:
        self.session_id = record.id
        self.record = record
        self.owner = record.owner
        self.prepared = PreparedSession(
            calibration=record.calibration,
            config=record.config,
            imu_noise=record.imu_noise,
            image_size=(record.image_width, record.image_height),
        )
        self.settings = settings
        self.store = store
        self.runner = runner
        self.slot = slot
        self.io_pool = io_pool
        self.metrics = metrics
        self.limits = ImageLimits(
            settings.max_image_width, settings.max_image_height, settings.max_image_pixels
        )
        self.queue: asyncio.Queue[FrameJob] = asyncio.Queue(maxsize=settings.queue_size)
        # False until the worker holds a pipeline for this session (built on the next frame).
        self.pipeline_ready = False
        self.next_index = record.frame_count
        self.last_processed_ns = record.last_timestamp_ns
        self.last_submitted_ns = record.last_timestamp_ns
        self.busy = False
        self.closed = False
        # Wall-clock times of the latest stored poses: the live view's frames/s and last update.
        self.stored_at: deque[float] = deque(maxlen=64)
        self._imu_lock = threading.Lock()
        self._imu: list[ImuSamples] = []
        self._imu_count = 0
        # Final smoothed poses handed out so far: (timestamp_ns, flat 4x4), oldest first.
        self.smoothed: deque[tuple[int, list[float]]] = deque(maxlen=SMOOTHED_KEEP)
        self._task = asyncio.get_running_loop().create_task(self._consume())

    # -- producer side (event loop)

    @property
    def idle(self) -> bool:
        return not self.busy and self.queue.empty() and self._imu_count == 0

    def add_imu(self, samples: ImuSamples) -> int:
        """Buffer IMU samples for the next frames; returns the buffered count."""
        if self.closed:
            raise SessionGone()
        with self._imu_lock:
            if self._imu_count + len(samples) > self.settings.max_imu_buffer:
                raise FrameRejected(
                    429,
                    f"IMU buffer full ({self._imu_count} samples waiting, limit "
                    f"{self.settings.max_imu_buffer}); send frames to consume them",
                    "imu_buffer_full",
                )
            self._imu.append(samples)
            self._imu_count += len(samples)
            return self._imu_count

    def submit(
        self,
        timestamp_ns: int,
        left: bytes,
        right: bytes,
        imu: ImuSamples | None,
        raw: bool = False,
    ) -> asyncio.Future[FrameAnswer]:
        """Queue one frame; the future resolves once its pose is stored (or it is refused)."""
        if self.closed:
            raise SessionGone()
        try:
            check_timestamp_order(timestamp_ns, self.last_submitted_ns)
        except TimestampOrderError as error:
            raise FrameRejected(409, str(error), "timestamp_order") from error
        if imu is not None and len(imu):
            # Samples sent with a frame join the session buffer at once: they stay valid
            # measurements even if this frame is refused or dropped below.
            self.add_imu(imu)
        future: asyncio.Future[FrameAnswer] = asyncio.get_running_loop().create_future()
        # Nobody may be left to read the outcome (client gone): mark it read, not leaked.
        future.add_done_callback(lambda f: f.cancelled() or f.exception())
        job = FrameJob(timestamp_ns, left, right, future, raw)
        if self.queue.full():
            if self.settings.queue_policy == "reject":
                self.metrics.dropped.labels("reject").inc()
                raise FrameRejected(
                    429,
                    f"session queue full ({self.settings.queue_size} frames waiting): frame "
                    f"{timestamp_ns} rejected; send slower or wait for answers",
                    "queue_full",
                )
            oldest = self.queue.get_nowait()
            self.metrics.dropped.labels("drop_oldest").inc()
            if not oldest.future.done():
                oldest.future.set_exception(
                    FrameDropped(
                        f"frame {oldest.timestamp_ns} dropped unprocessed: the session queue "
                        f"was full ({self.settings.queue_size}) and a newer frame arrived"
                    )
                )
        self.queue.put_nowait(job)
        self.last_submitted_ns = timestamp_ns
        return future

    # -- consumer side

    async def _consume(self) -> None:
        while True:
            job = await self.queue.get()
            if job.future.done():
                continue
            self.busy = True
            failed = True
            try:
                result = await self._process(job)
                failed = False
            except FrameRejected as error:
                self.metrics.errors.labels(error.kind).inc()
                if not job.future.done():
                    job.future.set_exception(error)
            except Exception as error:  # a bug must not kill the session's consumer
                logger.exception("frame %s of session %s failed", job.timestamp_ns, self.session_id)
                self.metrics.errors.labels("internal").inc()
                self.pipeline_ready = False
                if not job.future.done():
                    job.future.set_exception(
                        FrameRejected(
                            500, f"internal error processing the frame: {error!r}", "internal"
                        )
                    )
            else:
                if not job.future.done():
                    job.future.set_result(result)
            finally:
                self.busy = False
                # A refused frame must not block a retry with the same timestamp.
                if failed and self.queue.empty():
                    self.last_submitted_ns = self.last_processed_ns

    def _pipeline_spec(self) -> tuple[PipelineSpec, str]:
        """How to build the pipeline: resumed from the last stored pose when there is one."""
        last = self.store.last_pose(self.session_id)
        if last is None:
            return PipelineSpec(self.prepared, None, 0), ""
        initial = np.array(last.pose, dtype=float).reshape(4, 4)
        message = (
            f"resumed from the stored pose of frame {last.index} "
            f"(timestamp {last.timestamp_ns}); motion since then is not known to the estimator"
        )
        return PipelineSpec(self.prepared, initial, last.index + 1), message

    def _peek_imu(self, timestamp_ns: int) -> _ImuTake:
        """IMU samples with previous frame < t <= this frame; later ones stay buffered."""
        with self._imu_lock:
            parts = list(self._imu)
            if not parts:
                return _ImuTake(None, [], 0)
            times = np.concatenate([p.timestamps_ns for p in parts])
            gyro = np.concatenate([p.gyro for p in parts])
            accel = np.concatenate([p.accel for p in parts])
        order = np.argsort(times, kind="stable")
        times, gyro, accel = times[order], gyro[order], accel[order]
        keep = np.ones(len(times), dtype=bool)
        keep[1:] = times[1:] != times[:-1]  # a repeated sample counts once
        times, gyro, accel = times[keep], gyro[keep], accel[keep]
        later = times > timestamp_ns
        remainder = [ImuSamples(times[later], gyro[later], accel[later])] if later.any() else []
        now = ~later
        if self.last_processed_ns is not None:
            now &= times > self.last_processed_ns
        batch = ImuBatch(times[now], gyro[now], accel[now]) if now.any() else None
        return _ImuTake(batch, remainder, len(parts))

    def _consume_imu(self, take: _ImuTake) -> None:
        """Remove what a frame used; samples that arrived meanwhile stay behind it."""
        with self._imu_lock:
            self._imu = [*take.remainder, *self._imu[take.parts :]]
            self._imu_count = sum(len(p) for p in self._imu)

    async def _process(self, job: FrameJob) -> FrameAnswer:
        """Decode + odometry in the session's worker, then persist in an I/O thread."""
        loop = asyncio.get_running_loop()
        started = time.perf_counter()
        timings = {"queue_wait": started - job.received}
        take = self._peek_imu(job.timestamp_ns)
        resume_message = ""
        outcome: FrameProcessed | FrameFailure | None = None
        for _attempt in range(2):
            spec = None
            if not self.pipeline_ready:
                spec, resume_message = await loop.run_in_executor(
                    self.io_pool, self._pipeline_spec
                )
            request = FrameRequest(
                self.session_id, self.next_index, job.timestamp_ns, job.left, job.right,
                self.limits, self.prepared.image_size, take.batch, job.raw, spec,
                self.settings.frame_cpu_budget_s,
            )
            sent = time.perf_counter()
            outcome = await self.runner.run(self.slot, request)
            answered = time.perf_counter()
            if outcome.created:
                self.pipeline_ready = True
                if spec is not None and spec.initial_pose is not None:
                    await loop.run_in_executor(
                        self.io_pool, self.store.note_resumed, self.session_id
                    )
            if isinstance(outcome, FrameFailure) and outcome.pipeline_lost:
                self.pipeline_ready = False
            # The worker lost the pipeline (it was restarted): build it again and retry once.
            if not (isinstance(outcome, FrameFailure) and outcome.kind == "pipeline_missing"):
                break
        assert outcome is not None
        if isinstance(outcome, FrameFailure):
            if outcome.kind not in ("bad_image", "worker_died", "worker_timeout",
                                    "pipeline_missing", "cpu_budget"):
                self._consume_imu(take)  # the estimator saw these samples
            if outcome.trace:
                logger.error("frame %s of session %s failed in its worker:\n%s",
                             job.timestamp_ns, self.session_id, outcome.trace.rstrip())
            kind = "internal" if outcome.kind == "pipeline_missing" else outcome.kind
            raise FrameRejected(outcome.status_code, outcome.detail, kind)
        self._consume_imu(take)
        worked = outcome.answer.timings_s
        timings.update(worked)
        timings["transfer"] = max(0.0, answered - sent - worked["decode"] - worked["odometry"])
        resumed = outcome.created and spec is not None and spec.initial_pose is not None
        message = "; ".join(
            m for m in (resume_message if resumed else "", outcome.answer.message) if m
        )
        answer = outcome.answer.model_copy(
            update={"timings_s": dict(timings), "message": message, "resumed": resumed}
        )
        stored = time.perf_counter()
        try:
            await loop.run_in_executor(self.io_pool, self.store.add_pose, answer)
        except Exception as error:
            # The estimator has moved on but the pose is not stored: rebuild from the last
            # stored pose on the next frame so the stored trajectory stays the source of truth.
            self.pipeline_ready = False
            if self.closed:
                raise SessionGone() from error
            # The database's own message (statement, parameters) stays in the log.
            logger.error("storing a pose of session %s failed: %s", self.session_id,
                         str(error).splitlines()[0] if str(error) else repr(error))
            raise FrameRejected(503, "the pose could not be stored (database error); retry "
                                "the frame", "storage") from error
        done = time.perf_counter()
        timings["persist"] = done - stored
        timings["total"] = done - job.received
        self.next_index += 1
        self.last_processed_ns = job.timestamp_ns
        self.smoothed.extend((p.timestamp_ns, flat_of(p.pose)) for p in answer.smoothed)
        self.stored_at.append(time.time())
        for stage, seconds in timings.items():
            self.metrics.stage_latency.labels(stage).observe(seconds)
        self.metrics.frames.labels(answer.status).inc()
        return answer.model_copy(update={"timings_s": timings})

    async def close(
        self, reason: str, drain_seconds: float = 0.0, deleted: bool = False
    ) -> None:
        """Stop the consumer; queued frames are processed first for up to ``drain_seconds``.

        Frames still queued are refused with 503 (``reason``), or 404 when ``deleted``.
        """
        self.closed = True
        if drain_seconds > 0:
            deadline = time.monotonic() + drain_seconds
            while (self.busy or not self.queue.empty()) and time.monotonic() < deadline:
                await asyncio.sleep(0.02)
        while not self.queue.empty():
            job = self.queue.get_nowait()
            if not job.future.done():
                job.future.set_exception(
                    SessionGone() if deleted else FrameRejected(503, reason, "shutdown")
                )
        # Let a frame already in a worker finish and store its pose.
        while self.busy:
            await asyncio.sleep(0.01)
        self._task.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await self._task


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
                settings.workers, factory, metrics.worker_restarts.inc, settings.frame_timeout_s
            )
            if settings.executor == "process"
            else ThreadRunner(settings.workers, factory)
        )
        # Database reads/writes of the consumers (SQLite serialises writers anyway).
        self.io_pool = ThreadPoolExecutor(
            max(2, min(settings.workers, 8)), thread_name_prefix="swarmvo-io"
        )
        self.live: OrderedDict[str, LiveSession] = OrderedDict()
        # Recently deleted ids (uuid4: never reused), so that a request that looked the session
        # up just before its deletion cannot bring it back to life.
        self.deleted: OrderedDict[str, None] = OrderedDict()
        self.streams: dict[str, set[StreamHandle]] = {}
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

    def live_session(self, record: SessionRecord) -> LiveSession:
        """The session's live state, created on first use; SessionGone once it was deleted."""
        if record.id in self.deleted:
            raise SessionGone()
        worker = self.live.get(record.id)
        if worker is not None:
            self.live.move_to_end(record.id)
            return worker
        self._evict_idle()
        slot = self.runner.assign(record.id)
        worker = LiveSession(
            record, self.settings, self.store, self.runner, slot, self.io_pool, self.metrics
        )
        self.live[record.id] = worker
        self._on_change()
        return worker

    def _evict_idle(self) -> None:
        while len(self.live) >= self.settings.max_active_sessions:
            victim = next((sid for sid, w in self.live.items() if w.idle), None)
            if victim is None:
                return  # all busy: exceed the soft cap rather than refuse work
            worker = self.live.pop(victim)
            # Freed now, not when the close task runs: the session may come back before that,
            # and its new pipeline must not be dropped by this late release.
            self.runner.release(worker.slot, victim)
            asyncio.get_running_loop().create_task(worker.close("session unloaded"))

    def attach(self, session_id: str, stream: StreamHandle) -> None:
        """Register an open stream; SessionGone when the session was deleted meanwhile."""
        if session_id in self.deleted:
            raise SessionGone()
        self.streams.setdefault(session_id, set()).add(stream)

    def detach(self, session_id: str, stream: StreamHandle) -> None:
        streams = self.streams.get(session_id)
        if streams is not None:
            streams.discard(stream)
            if not streams:
                del self.streams[session_id]

    async def remove(self, session_id: str) -> None:
        """Delete the live state: open streams are closed, queued frames refused with 404."""
        self.deleted[session_id] = None
        while len(self.deleted) > MAX_REMEMBERED_DELETIONS:
            self.deleted.popitem(last=False)
        for stream in self.streams.pop(session_id, set()):
            stream.terminate(STREAM_CLOSE_DELETED, "session deleted")
        worker = self.live.pop(session_id, None)
        if worker is not None:
            self._on_change()
            await worker.close("session was deleted", deleted=True)
            self.runner.release(worker.slot, session_id)

    async def shutdown(self, drain_seconds: float = 10.0) -> None:
        workers = list(self.live.values())
        self.live.clear()
        self._on_change()
        await asyncio.gather(
            *(w.close("server shutting down", drain_seconds) for w in workers),
            return_exceptions=True,
        )
        await self.runner.shutdown()
        self.io_pool.shutdown(wait=True, cancel_futures=False)
