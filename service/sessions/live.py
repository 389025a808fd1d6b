"""One live session: a bounded queue, strict timestamp order, CPU work off the event loop.

Each live session has one consumer task that takes frames from its queue one at a time and hands
them to its worker (see :mod:`service.workers`: a pinned process, or a thread), so frames of one
session never overlap while different sessions use all workers. The pose is committed to the
database (in an I/O thread) before its future resolves, i.e. before any client can see it.
The session's lease lives in :mod:`.session_lease`; the pipeline spec sent to the worker and
what its answer or failure becomes, in :mod:`.worker_answer`.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from collections import deque
from concurrent.futures import ThreadPoolExecutor
from typing import Any

from sqlalchemy.exc import DBAPIError

from estimator.types import TimestampOrderError, check_timestamp_order
from service.answer import FrameAnswer, flat_of
from service.estimator_adapter import PreparedSession
from service.images import ImageLimits
from service.lease import LeaseBook
from service.metrics import Metrics
from service.pose_writer import PoseWriter
from service.sessions.frames import (
    Answered,
    FrameDropped,
    FrameJob,
    FrameRejected,
    SessionGone,
)
from service.sessions.imu_buffer import ImuBuffer, ImuSamples, ImuTake
from service.sessions.session_lease import SessionLease
from service.sessions.worker_answer import (
    WorkerRun,
    answer_of,
    failure_refusal,
    pipeline_spec,
    samples_seen,
)
from service.settings import ServiceSettings
from service.storage import LeaseLost, PendingPose, SessionRecord, SmoothedPose, Store
from service.workers import (
    FrameFailure,
    FrameRequest,
    Runner,
)

logger = logging.getLogger("swarmvo.service")


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
        leases: LeaseBook | None = None,
        pose_writer: PoseWriter | None = None,
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
        self.pose_writer = pose_writer or PoseWriter(store, io_pool)
        self.metrics = metrics
        self.lease = SessionLease(leases, record.id, store, io_pool)
        # Frames queued or in flight by timestamp: a resent one shares the first one's answer.
        self.pending: dict[int, asyncio.Future[Answered]] = {}
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
        self.imu = ImuBuffer(settings.max_imu_buffer)
        # A back end holds the newest frames back for smoothing: a stream's end flushes them.
        self.smoothing = bool(record.config.get("backend", {}).get("enabled", True))
        # Held while the worker runs this session's pipeline: a flush never overlaps a frame.
        self._pipeline_lock = asyncio.Lock()
        self._task = asyncio.get_running_loop().create_task(self._consume())

    # -- producer side (event loop)

    @property
    def idle(self) -> bool:
        return not self.busy and self.queue.empty() and self.imu.count == 0

    def add_imu(self, samples: ImuSamples) -> int:
        """Buffer IMU samples for the next frames; returns the buffered count."""
        if self.closed:
            raise SessionGone()
        buffered = self.imu.add(samples)
        if buffered is None:
            raise FrameRejected(
                429,
                f"IMU buffer full ({self.imu.count} samples waiting, limit "
                f"{self.settings.max_imu_buffer}); send frames to consume them",
                "imu_buffer_full",
            )
        return buffered

    def submit(
        self,
        timestamp_ns: int,
        left: bytes | memoryview,
        right: bytes | memoryview,
        imu: ImuSamples | None,
        raw: bool = False,
    ) -> asyncio.Future[Answered]:
        """Queue one frame; the future resolves once its pose is stored (or it is refused)."""
        if self.closed:
            raise SessionGone()
        if timestamp_ns in self.pending:
            return self.pending[timestamp_ns]  # resent while still queued or in flight
        last = self.last_submitted_ns
        if last is not None and timestamp_ns <= last:
            # Resent after its answer was lost (a reconnect): the stored answer, or a 409.
            return asyncio.get_running_loop().create_task(self._stored_answer(timestamp_ns))
        if imu is not None and len(imu):
            # Samples sent with a frame join the session buffer at once: they stay valid
            # measurements even if this frame is refused or dropped below.
            self.add_imu(imu)
        future: asyncio.Future[Answered] = asyncio.get_running_loop().create_future()
        # Nobody may be left to read the outcome (client gone): mark it read, not leaked.
        future.add_done_callback(lambda f: f.cancelled() or f.exception())
        job = FrameJob(timestamp_ns, left, right, future, raw)
        if self.queue.full():
            if self.settings.queue_policy == "reject":
                raise self._queue_full(timestamp_ns)
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
        self.pending[timestamp_ns] = future
        future.add_done_callback(lambda _f: self.pending.pop(timestamp_ns, None))
        return future

    def refusal_before_images(
        self, timestamp_ns: int, imu: ImuSamples | None
    ) -> FrameRejected | None:
        """The refusal a frame announced now gets when the queue is full (policy ``reject``),
        decided from its header: the server then neither keeps nor copies its images. Its IMU
        samples join the buffer as they would in :meth:`submit`; a resent frame (answered from
        its first copy or the store) and a closed session are left to :meth:`submit`."""
        if self.closed or self.settings.queue_policy != "reject" or not self.queue.full():
            return None
        last = self.last_submitted_ns
        if timestamp_ns in self.pending or (last is not None and timestamp_ns <= last):
            return None
        if imu is not None and len(imu):
            self.add_imu(imu)
        return self._queue_full(timestamp_ns)

    def _queue_full(self, timestamp_ns: int) -> FrameRejected:
        self.metrics.dropped.labels("reject").inc()
        return FrameRejected(
            429,
            f"session queue full ({self.settings.queue_size} frames waiting): frame "
            f"{timestamp_ns} rejected; send slower or wait for answers",
            "queue_full",
        )

    async def _stored_answer(self, timestamp_ns: int) -> Answered:
        """A frame already processed gets its stored pose; any other old timestamp a 409."""
        loop = asyncio.get_running_loop()
        stored = await loop.run_in_executor(
            self.io_pool, self.store.pose_at, self.session_id, timestamp_ns
        )
        if stored is None:
            try:
                check_timestamp_order(timestamp_ns, self.last_submitted_ns)
            except TimestampOrderError as error:
                raise FrameRejected(409, str(error), "timestamp_order") from error
        if stored is None:  # not older after all (the session moved back): still refused
            raise FrameRejected(409, f"timestamp_ns {timestamp_ns} was not stored",
                                "timestamp_order")
        self.metrics.frames.labels("duplicate").inc()
        return Answered(stored, duplicate=True)

    async def _hold_lease(self) -> None:
        """Own the session before processing; when another replica may have written
        meanwhile, the counters are read again and the pipeline is rebuilt from the stored
        state only if they moved."""
        record = await self.lease.hold()
        if record is not None:
            stored = (record.frame_count, record.last_timestamp_ns)
            if stored != (self.next_index, self.last_processed_ns):  # written by another
                self.next_index, self.last_processed_ns = stored
                self.pipeline_ready = False

    def release_lease(self) -> None:
        """Give the lease up (blocking I/O): the session's streams have all ended."""
        self.lease.release()

    # -- consumer side

    async def _consume(self) -> None:
        while True:
            job = await self.queue.get()
            if job.future.done():
                continue
            if job.flush:
                job.future.set_result(await self.flush())
                continue
            self.busy = True
            failed = True
            try:
                async with self._pipeline_lock:
                    result = await self._process(job)
                failed = False
            except FrameRejected as error:
                self.metrics.errors.labels(error.kind).inc()
                if not job.future.done():
                    job.future.set_exception(error)
                if error.retry_after_s is not None:
                    self._refuse_queued(error)
            except DBAPIError as error:  # the database is away: a pause, not a bug
                logger.error("database unavailable for session %s: %s", self.session_id,
                             str(error).splitlines()[0] if str(error) else repr(error))
                self.metrics.errors.labels("storage").inc()
                self.lease.drop()
                refusal = FrameRejected(
                    503, "database unavailable; retry the frame", "storage", 1.0
                )
                if not job.future.done():
                    job.future.set_exception(refusal)
                self._refuse_queued(refusal)
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

    def _refuse_queued(self, error: FrameRejected) -> None:
        """After a passing failure the frames queued behind it are refused too: the client
        resends them after the failed one, in order (answering them now would leave the failed
        frame behind the session's timestamp)."""
        while not self.queue.empty():
            job = self.queue.get_nowait()
            if not job.future.done():
                job.future.set_exception(FrameRejected(
                    error.status_code, f"an earlier frame was refused: {error.detail}",
                    error.kind, error.retry_after_s))

    async def _process(self, job: FrameJob) -> Answered:
        """Decode + odometry in the session's worker, then persist in an I/O thread."""
        started = time.perf_counter()
        timings = {"queue_wait": started - job.received}
        await self._hold_lease()
        if self.last_processed_ns is not None and job.timestamp_ns <= self.last_processed_ns:
            return await self._stored_answer(job.timestamp_ns)  # stored by another replica
        take = self.imu.peek(job.timestamp_ns, self.last_processed_ns)
        run = await self._run_in_worker(job, take)
        outcome = run.outcome
        if isinstance(outcome, FrameFailure):
            if samples_seen(outcome):
                self.imu.consume(take)  # the estimator saw these samples
            raise failure_refusal(job, outcome, self.session_id)
        self.imu.consume(take)
        answer = answer_of(run, outcome, timings)
        stored = time.perf_counter()
        await self._persist(answer, outcome.state)
        done = time.perf_counter()
        timings["persist"] = done - stored
        timings["total"] = done - job.received
        self._note_stored(job.timestamp_ns, timings, answer.status)
        return Answered(answer.model_copy(update={"timings_s": timings}))

    async def _run_in_worker(self, job: FrameJob, take: ImuTake) -> WorkerRun:
        """Send the frame to the worker, building the pipeline first when it is not there.

        A worker that lost the pipeline (it was restarted) answers ``pipeline_missing``: the
        pipeline is built again from the store and the frame retried once.
        """
        loop = asyncio.get_running_loop()
        resume_message = ""
        for _attempt in range(2):
            spec = None
            if not self.pipeline_ready:
                spec, resume_message = await loop.run_in_executor(
                    self.io_pool, pipeline_spec, self.store, self.session_id, self.prepared
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
            if not (isinstance(outcome, FrameFailure) and outcome.kind == "pipeline_missing"):
                break
        return WorkerRun(outcome, spec, resume_message, sent, answered)

    async def _persist(self, answer: FrameAnswer, state: dict[str, Any] | None) -> None:
        """Store the pose (and the estimator state) before anyone sees it; a failed write
        marks the pipeline stale so the stored trajectory stays the source of truth."""
        fence = self.lease.fence
        try:
            await self.pose_writer.add(PendingPose(
                answer, fence, state,
                [(p.timestamp_ns, flat_of(p.pose)) for p in answer.smoothed],
            ))
        except LeaseLost as error:
            # Another replica took the session over: this one must not write, and its
            # pipeline is out of date; the client resends the frame to the new owner.
            self.pipeline_ready = False
            self.lease.drop()
            logger.warning("%s", error)
            raise FrameRejected(503, f"{error}; resend the frame", "lease_lost", 0.2) from error
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
                                "the frame", "storage", 1.0) from error

    def _note_stored(self, timestamp_ns: int, timings: dict[str, float], status: str) -> None:
        """Advance the session past a stored frame and record its latency metrics."""
        self.next_index += 1
        self.last_processed_ns = timestamp_ns
        self.lease.renewed()  # the write renewed it
        self.stored_at.append(time.time())
        for stage, seconds in timings.items():
            self.metrics.stage_latency.labels(stage).observe(seconds)
        self.metrics.frames.labels(status).inc()

    def start_flush(self) -> asyncio.Future[list[SmoothedPose]]:
        """Ask the worker to finalise the back end's window; call only between frames.

        The pipeline is dropped (a smoother cannot go on after a flush), so a later frame
        resumes from the last stored pose, as after a restart.
        """
        if not (self.pipeline_ready and self.smoothing):  # nothing held back: it goes on
            done: asyncio.Future[list[SmoothedPose]] = asyncio.get_running_loop().create_future()
            done.set_result([])
            return done
        self.pipeline_ready = False
        return self.runner.finish(self.slot, self.session_id)

    async def flush_after_queued(self) -> list[SmoothedPose]:
        """Flush once the frames queued so far are done: the stream that sent them ended."""
        if self.closed:
            return []
        future: asyncio.Future[list[SmoothedPose]] = asyncio.get_running_loop().create_future()
        future.add_done_callback(lambda f: f.cancelled() or f.exception())
        await self.queue.put(FrameJob(-1, b"", b"", future, flush=True))
        if self.closed and not future.done():
            # Put after close() began (it waited for room in a full queue): close() may have
            # emptied the queue already and nobody would take it; the closing session flushes
            # (and stores) by itself.
            return []
        try:
            return await asyncio.shield(future)
        except FrameRejected:  # refused by a closing session, which flushes by itself
            return []

    async def flush(self, store: bool = True) -> list[SmoothedPose]:
        """The session's stream ended: its last frames get their final poses, stored (unless
        the session is being deleted) and returned for the stream's last message."""
        async with self._pipeline_lock:  # never in the middle of a frame
            flushed = self.start_flush()
        return await self.finish_flush(flushed, store)

    async def finish_flush(
        self, flushed: asyncio.Future[list[SmoothedPose]], store: bool = True
    ) -> list[SmoothedPose]:
        try:
            smoothed = await asyncio.wait_for(flushed, self.settings.frame_timeout_s)
        except Exception as error:
            logger.error("flushing the back end of session %s failed: %r", self.session_id, error)
            return []
        if smoothed and store:
            try:
                await asyncio.get_running_loop().run_in_executor(
                    self.io_pool, self.store.add_smoothed, self.session_id, smoothed
                )
            except Exception as error:
                logger.error("storing the flushed poses of session %s failed: %s",
                             self.session_id, str(error).splitlines()[0] if str(error) else "")
        return smoothed

    async def close(
        self, reason: str, drain_seconds: float = 0.0, deleted: bool = False
    ) -> list[SmoothedPose]:
        """Stop the consumer; queued frames are processed first for up to ``drain_seconds``.

        Frames still queued are refused with 503 (``reason``), or 404 when ``deleted``. The
        back end's window is then flushed (stored unless ``deleted``); its poses are returned.
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
        return await self.flush(store=not deleted)
