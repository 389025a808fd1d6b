"""Per-session workers: a bounded queue, strict timestamp order, odometry off the event loop.

Each live session has one consumer task that takes frames from its queue one at a time and runs
decode + odometry + persistence in the shared thread pool, so frames of one session never
overlap while different sessions use all workers. A pose is committed to the database before
its future resolves, i.e. before any client can see it.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import threading
import time
from collections import OrderedDict
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, replace

import numpy as np

from estimator.types import ImuBatch, StereoFrame
from service.images import ImageError, ImageLimits, decode_pair
from service.metrics import Metrics
from service.pipeline import Pipeline, PipelineFactory, PreparedSession
from service.settings import ServiceSettings
from service.storage import PoseRecord, SessionRecord, Store

logger = logging.getLogger("swarmvo.service")


class FrameRejected(Exception):
    """A frame the service will not process; carries the HTTP status that explains why."""

    def __init__(self, status_code: int, detail: str, kind: str) -> None:
        super().__init__(detail)
        self.status_code = status_code
        self.detail = detail
        self.kind = kind


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
    imu: ImuSamples | None
    future: asyncio.Future[FrameResult]
    received: float = field(default_factory=time.perf_counter)


@dataclass(frozen=True)
class FrameResult:
    session_id: str
    record: PoseRecord
    imu_samples: int


def _flat(matrix: np.ndarray) -> list[float]:
    return [float(v) for v in np.asarray(matrix, dtype=float).reshape(16)]


class SessionWorker:
    """The live state of one session: its queue, its pipeline and its IMU buffer."""

    def __init__(
        self,
        record: SessionRecord,
        settings: ServiceSettings,
        store: Store,
        factory: PipelineFactory,
        pool: ThreadPoolExecutor,
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
        self.factory = factory
        self.pool = pool
        self.metrics = metrics
        self.limits = ImageLimits(
            settings.max_image_width, settings.max_image_height, settings.max_image_pixels
        )
        self.queue: asyncio.Queue[FrameJob] = asyncio.Queue(maxsize=settings.queue_size)
        self.pipeline: Pipeline | None = None
        self.next_index = record.frame_count
        self.last_processed_ns = record.last_timestamp_ns
        self.last_submitted_ns = record.last_timestamp_ns
        self.busy = False
        self.closed = False
        self._imu_lock = threading.Lock()
        self._imu: list[ImuSamples] = []
        self._imu_count = 0
        self._task = asyncio.get_running_loop().create_task(self._consume())

    # -- producer side (event loop)

    @property
    def idle(self) -> bool:
        return not self.busy and self.queue.empty() and self._imu_count == 0

    def add_imu(self, samples: ImuSamples) -> int:
        """Buffer IMU samples for the next frames; returns the buffered count."""
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
        self, timestamp_ns: int, left: bytes, right: bytes, imu: ImuSamples | None
    ) -> asyncio.Future[FrameResult]:
        """Queue one frame; the future resolves once its pose is stored (or it is refused)."""
        if self.closed:
            raise FrameRejected(404, "session was deleted", "unknown_session")
        last = self.last_submitted_ns
        if last is not None and timestamp_ns <= last:
            raise FrameRejected(
                409,
                f"timestamp_ns {timestamp_ns} does not increase: the session is already at "
                f"{last}",
                "timestamp_order",
            )
        if imu is not None and len(imu):
            # Samples sent with a frame join the session buffer at once: they stay valid
            # measurements even if this frame is refused or dropped below.
            self.add_imu(imu)
        future: asyncio.Future[FrameResult] = asyncio.get_running_loop().create_future()
        # Nobody may be left to read the outcome (client gone): mark it read, not leaked.
        future.add_done_callback(lambda f: f.cancelled() or f.exception())
        job = FrameJob(timestamp_ns, left, right, None, future)
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
        loop = asyncio.get_running_loop()
        while True:
            job = await self.queue.get()
            if job.future.done():
                continue
            self.busy = True
            failed = True
            try:
                result = await loop.run_in_executor(self.pool, self._process, job)
                failed = False
            except FrameRejected as error:
                self.metrics.errors.labels(error.kind).inc()
                if not job.future.done():
                    job.future.set_exception(error)
            except Exception as error:  # a bug must not kill the session's consumer
                logger.exception("frame %s of session %s failed", job.timestamp_ns, self.session_id)
                self.metrics.errors.labels("internal").inc()
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

    def _load_pipeline(self) -> tuple[Pipeline, bool, str]:
        """Build the pipeline, resuming from the last stored pose when the session has one."""
        last = self.store.last_pose(self.session_id)
        if last is None:
            return self.factory.create(self.prepared, None, 0), False, ""
        initial = np.array(last.pose, dtype=float).reshape(4, 4)
        pipeline = self.factory.create(self.prepared, initial, last.frame_index + 1)
        self.store.note_resumed(self.session_id)
        message = (
            f"resumed from the stored pose of frame {last.frame_index} "
            f"(timestamp {last.timestamp_ns}); motion since then is not known to the estimator"
        )
        return pipeline, True, message

    def _take_imu(self, timestamp_ns: int, inline: ImuSamples | None) -> ImuBatch | None:
        """IMU samples with previous frame < t <= this frame; later ones stay buffered."""
        with self._imu_lock:
            parts = [*self._imu, *([inline] if inline is not None and len(inline) else [])]
            if not parts:
                return None
            times = np.concatenate([p.timestamps_ns for p in parts])
            gyro = np.concatenate([p.gyro for p in parts])
            accel = np.concatenate([p.accel for p in parts])
            order = np.argsort(times, kind="stable")
            times, gyro, accel = times[order], gyro[order], accel[order]
            keep = np.ones(len(times), dtype=bool)
            keep[1:] = times[1:] != times[:-1]  # a repeated sample counts once
            times, gyro, accel = times[keep], gyro[keep], accel[keep]
            later = times > timestamp_ns
            self._imu = (
                [ImuSamples(times[later], gyro[later], accel[later])] if later.any() else []
            )
            self._imu_count = int(later.sum())
            now = ~later
            if self.last_processed_ns is not None:
                now &= times > self.last_processed_ns
            if not now.any():
                return None
            return ImuBatch(times[now], gyro[now], accel[now])

    def _process(self, job: FrameJob) -> FrameResult:
        """Decode, run the odometry and persist; runs in a worker thread."""
        started = time.perf_counter()
        timings = {"queue_wait": started - job.received}
        try:
            left, right = decode_pair(job.left, job.right, self.limits, self.prepared.image_size)
        except ImageError as error:
            raise FrameRejected(error.status_code, str(error), "bad_image") from error
        timings["decode"] = time.perf_counter() - started

        resumed, resume_message = False, ""
        if self.pipeline is None:
            self.pipeline, resumed, resume_message = self._load_pipeline()
        imu = self._take_imu(job.timestamp_ns, job.imu)
        frame = StereoFrame(job.timestamp_ns, left, right)
        try:
            report = self.pipeline.process(frame, imu)
        except ValueError as error:
            raise FrameRejected(
                422, f"frame refused by the estimator: {error}", "bad_frame"
            ) from error
        except Exception:
            # Unknown internal state after a failure: rebuild from the last stored pose.
            self.pipeline = None
            raise
        for stage, seconds in report.timings_s.items():
            timings[f"odometry.{stage}"] = float(seconds)
        odometry_done = time.perf_counter()
        timings["odometry"] = odometry_done - started - timings["decode"]

        message = "; ".join(m for m in (resume_message, report.message) if m)
        record = PoseRecord(
            frame_index=self.next_index,
            timestamp_ns=job.timestamp_ns,
            pose=_flat(report.pose),
            frontend_pose=_flat(report.frontend_pose),
            relative_pose=_flat(report.relative_pose),
            status=str(report.status),
            matches=int(report.matches),
            inliers=int(report.inliers),
            support=int(report.support),
            timings=timings,
            message=message,
            resumed=resumed,
        )
        try:
            self.store.add_pose(self.session_id, record)
        except Exception as error:
            # The estimator has moved on but the pose is not stored: rebuild from the last
            # stored pose on the next frame so the stored trajectory stays the source of truth.
            self.pipeline = None
            logger.exception("storing a pose of session %s failed", self.session_id)
            raise FrameRejected(503, f"the pose could not be stored: {error}", "storage") from error
        done = time.perf_counter()
        timings["persist"] = done - odometry_done
        timings["total"] = done - job.received
        self.next_index += 1
        self.last_processed_ns = job.timestamp_ns
        for stage, seconds in timings.items():
            self.metrics.stage_latency.labels(stage).observe(seconds)
        self.metrics.frames.labels(record.status).inc()
        return FrameResult(self.session_id, replace(record, timings=timings), len(imu or ()))

    async def close(self, reason: str, drain_seconds: float = 0.0) -> None:
        """Stop the consumer; queued frames are processed first for up to ``drain_seconds``."""
        self.closed = True
        if drain_seconds > 0:
            deadline = time.monotonic() + drain_seconds
            while (self.busy or not self.queue.empty()) and time.monotonic() < deadline:
                await asyncio.sleep(0.02)
        while not self.queue.empty():
            job = self.queue.get_nowait()
            if not job.future.done():
                job.future.set_exception(FrameRejected(503, reason, "shutdown"))
        # Let a frame already in a worker thread finish and store its pose.
        while self.busy:
            await asyncio.sleep(0.01)
        self._task.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await self._task


class SessionManager:
    """Live workers by session id, with a soft cap on pipelines held in memory."""

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
        self.pool = ThreadPoolExecutor(settings.workers, thread_name_prefix="swarmvo-worker")
        self.workers: OrderedDict[str, SessionWorker] = OrderedDict()
        self._on_change: Callable[[], None] = lambda: metrics.sessions_active.set(
            len(self.workers)
        )

    def worker(self, record: SessionRecord) -> SessionWorker:
        worker = self.workers.get(record.id)
        if worker is not None:
            self.workers.move_to_end(record.id)
            return worker
        self._evict_idle()
        worker = SessionWorker(
            record, self.settings, self.store, self.factory, self.pool, self.metrics
        )
        self.workers[record.id] = worker
        self._on_change()
        return worker

    def _evict_idle(self) -> None:
        while len(self.workers) >= self.settings.max_active_sessions:
            victim = next((sid for sid, w in self.workers.items() if w.idle), None)
            if victim is None:
                return  # all busy: exceed the soft cap rather than refuse work
            worker = self.workers.pop(victim)
            asyncio.get_running_loop().create_task(worker.close("session unloaded"))

    async def remove(self, session_id: str) -> None:
        worker = self.workers.pop(session_id, None)
        if worker is not None:
            self._on_change()
            await worker.close("session was deleted")

    async def shutdown(self, drain_seconds: float = 10.0) -> None:
        workers = list(self.workers.values())
        self.workers.clear()
        self._on_change()
        await asyncio.gather(
            *(w.close("server shutting down", drain_seconds) for w in workers),
            return_exceptions=True,
        )
        self.pool.shutdown(wait=True, cancel_futures=False)
