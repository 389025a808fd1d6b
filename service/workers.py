"""Where decode + odometry run: worker processes pinned per session, or threads.

The estimator is CPU-bound Python/NumPy/OpenCV/GTSAM code; threads of one interpreter contend on
the GIL, so production runs it in worker *processes*. Each session is pinned to one process when
it goes live (least-loaded first): its ``Odometry`` object lives only there, and the session's
consumer sends that process one frame at a time, so frames stay in timestamp order. Images travel
as the encoded bytes and are decoded in the worker.

A worker that dies, or does not answer a frame within ``frame_timeout_s`` (then it is killed),
fails only the frames it had in flight (clear 503); it is replaced as soon as that is noticed and
every session pinned to it is rebuilt from its last stored pose on its next frame, exactly as after
a server restart. Workers ignore SIGINT/SIGTERM (the server drains them itself) and exit on their
own when the server process disappears, so none is left behind.

The thread runner keeps the same interface for factories that only make sense in-process
(test doubles whose state the caller inspects).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import multiprocessing
import multiprocessing.connection
import os
import signal
import threading
import time
import traceback
from collections.abc import Callable, Iterator
from concurrent.futures import Future, ProcessPoolExecutor, ThreadPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np

from estimator.geometry import nearest_rigid
from estimator.types import ImuBatch, StereoFrame
from service.answer import FrameAnswer, OdometryOut, SmoothedPose
from service.estimator_adapter import Pipeline, PipelineFactory, PreparedSession
from service.images import ImageError, ImageLimits, decode_pair, decode_raw_pair
from service.settings import Executor
from service.storage import SmoothedPose as StoredSmoothedPose

logger = logging.getLogger("swarmvo.service")


@dataclass(frozen=True)
class PipelineSpec:
    """How to (re)build a session's pipeline inside the worker that owns it."""

    prepared: PreparedSession
    initial_pose: np.ndarray | None
    first_index: int
    # The estimator state stored with the last pose (Odometry.state()), when there is one.
    state: dict[str, Any] | None = None


@dataclass(frozen=True)
class FrameRequest:
    """One frame for one session, as sent to a worker (encoded images, not arrays)."""

    session_id: str
    frame_index: int
    timestamp_ns: int
    left: bytes
    right: bytes
    limits: ImageLimits
    image_size: tuple[int, int]
    imu: ImuBatch | None = None
    raw: bool = False  # 8-bit grey pixels, row-major, image_size; no PNG/JPEG container
    create: PipelineSpec | None = None  # build the pipeline first (new, resumed or lost)
    cpu_budget_s: float = 0.0  # CPU seconds for decode + odometry; 0 = unlimited


@dataclass(frozen=True)
class FrameProcessed:
    """A frame's answer as the worker computed it (the session adds queueing and storage)."""

    answer: FrameAnswer
    created: bool  # the worker built the session's pipeline for this frame
    # The pipeline's state after this frame, stored with the pose so that any replica can
    # continue the session (pipelines without state() give None).
    state: dict[str, Any] | None = None


@dataclass(frozen=True)
class FrameFailure:
    """Why a frame produced no pose; ``kind`` decides what the session does next."""

    status_code: int
    detail: str
    # bad_image | bad_frame | internal | pipeline_missing | worker_died
    kind: str
    created: bool = False
    pipeline_lost: bool = False  # the worker no longer holds this session's pipeline
    trace: str = ""


class CpuBudgetExceeded(BaseException):
    """Raised into a frame that used up its CPU budget.

    A BaseException, so that no ``except Exception`` inside the estimator swallows it.
    """


def _out_of_budget(_signum: int, _frame: Any) -> None:
    raise CpuBudgetExceeded()


@contextlib.contextmanager
def cpu_budget(seconds: float) -> Iterator[None]:
    """Interrupt the block once this process has used ``seconds`` of CPU time in it.

    A profiling timer (SIGPROF counts CPU time, not waiting) whose handler raises; signals reach
    only the main thread, which is where a worker process runs its frames. Elsewhere (thread
    mode), or with 0, the block runs unbounded.
    """
    if seconds <= 0 or threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.signal(signal.SIGPROF, _out_of_budget)
    signal.setitimer(signal.ITIMER_PROF, seconds)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_PROF, 0)
        signal.signal(signal.SIGPROF, previous)


def _rows(matrix: np.ndarray) -> list[list[float]]:
    return np.asarray(matrix, dtype=float).reshape(4, 4).tolist()


def _flat(matrix: np.ndarray) -> list[float]:
    return np.asarray(matrix, dtype=float).reshape(16).tolist()


def compute_frame(
    pipelines: dict[str, Pipeline], factory: PipelineFactory, request: FrameRequest
) -> FrameProcessed | FrameFailure:
    """Decode and run the odometry of one frame within its CPU budget; never raises."""
    try:
        with cpu_budget(request.cpu_budget_s):
            return _compute_frame(pipelines, factory, request)
    except CpuBudgetExceeded:
        # Interrupted anywhere: the session's pipeline state is unknown, so only it is dropped
        # (it resumes from its last stored pose); other sessions' pipelines are untouched.
        pipelines.pop(request.session_id, None)
        return FrameFailure(
            422,
            f"the frame used more than its CPU budget of {request.cpu_budget_s:g} s "
            "(frame_cpu_budget_s) and was abandoned; the session resumes from its last stored "
            "pose. Lighter options (fewer features, smaller images) keep frames within it.",
            "cpu_budget",
            pipeline_lost=True,
        )


def _compute_frame(
    pipelines: dict[str, Pipeline], factory: PipelineFactory, request: FrameRequest
) -> FrameProcessed | FrameFailure:
    started = time.perf_counter()
    try:
        if request.raw:
            left, right = decode_raw_pair(request.left, request.right, request.image_size)
        else:
            left, right = decode_pair(request.left, request.right, request.limits,
                                      request.image_size)
    except ImageError as error:
        return FrameFailure(error.status_code, str(error), "bad_image")
    decoded = time.perf_counter()

    created = False
    note = ""
    if request.create is not None:
        spec = request.create
        pipelines.pop(request.session_id, None)
        try:
            try:
                pipeline = factory.create(spec.prepared, spec.initial_pose, spec.first_index)
            except ValueError:
                if spec.initial_pose is None:
                    raise
                # A stored pose the estimator finds not quite rigid would otherwise fail every
                # later frame too: resume from the nearest rigid transform instead.
                pipeline = factory.create(
                    spec.prepared, nearest_rigid(spec.initial_pose), spec.first_index
                )
                note = "the stored pose was not exactly rigid; resumed from its nearest rotation"
            if spec.state is not None and hasattr(pipeline, "restore"):
                try:
                    pipeline.restore(spec.state)
                except (KeyError, TypeError, ValueError) as error:
                    note = f"the stored state was not usable ({error}); resumed from the pose"
                    pipeline = factory.create(spec.prepared, spec.initial_pose, spec.first_index)
        except Exception as error:
            return FrameFailure(500, f"internal error building the pipeline: {error!r}",
                                "internal", pipeline_lost=True, trace=traceback.format_exc())
        pipelines[request.session_id] = pipeline
        created = True
    pipeline = pipelines.get(request.session_id)
    if pipeline is None:
        return FrameFailure(503, "the worker holds no pipeline for this session",
                            "pipeline_missing", pipeline_lost=True)
    try:
        report = pipeline.process(StereoFrame(request.timestamp_ns, left, right), request.imu)
    except ValueError as error:
        return FrameFailure(422, f"frame refused by the estimator: {error}", "bad_frame",
                            created=created)
    except Exception as error:
        # Unknown internal state after a failure: rebuild from the last stored pose.
        pipelines.pop(request.session_id, None)
        return FrameFailure(500, f"internal error processing the frame: {error!r}", "internal",
                            created=created, pipeline_lost=True, trace=traceback.format_exc())
    done = time.perf_counter()
    timings = {"decode": decoded - started, "odometry": done - decoded}
    for stage, seconds in report.timings_s.items():
        timings[f"odometry.{stage}"] = float(seconds)
    odometry = getattr(pipeline, "last_odometry", None)
    answer = FrameAnswer(
        session_id=request.session_id,
        index=request.frame_index,
        timestamp_ns=request.timestamp_ns,
        pose=_rows(report.pose),
        frontend_pose=_rows(report.frontend_pose),
        relative_pose=_rows(report.relative_pose),
        status=str(report.status),
        matches=int(report.matches),
        inliers=int(report.inliers),
        support=int(report.support),
        timings_s=timings,
        message="; ".join(m for m in (note, report.message) if m),
        resumed=False,
        imu_samples=0 if request.imu is None else len(request.imu.timestamps_ns),
        odometry=None if odometry is None else OdometryOut.model_validate(odometry),
        smoothed=[
            SmoothedPose(timestamp_ns=int(stamp), pose=_rows(pose))
            for stamp, pose in report.final_poses
        ],
    )
    return FrameProcessed(answer, created, _pipeline_state(pipeline))


def _pipeline_state(pipeline: Pipeline) -> dict[str, Any] | None:
    state = getattr(pipeline, "state", None)
    return state() if callable(state) else None


def session_problem(factory: PipelineFactory, prepared: PreparedSession) -> str | None:
    """The factory's dry run of a new session (if it has one): its refusal, or None."""
    check = getattr(factory, "check", None)
    if callable(check):
        try:
            check(prepared)
        except ValueError as error:
            return str(error)
    return None


def finish_pipeline(
    pipelines: dict[str, Pipeline], session_id: str
) -> list[StoredSmoothedPose]:
    """End a session's pipeline: the back end finalises the frames still in its window.

    The pipeline is dropped (its smoother cannot go on after a flush): a later frame of the
    session resumes from its last stored pose. Never raises; a failure only loses the window.
    """
    pipeline = pipelines.pop(session_id, None)
    finish = getattr(pipeline, "finish", None)
    if not callable(finish):
        return []
    try:
        return [(int(stamp), _flat(pose)) for stamp, pose in finish()]
    except Exception:
        logger.exception("flushing the back end of session %s failed", session_id)
        return []


class Runner(Protocol):
    """Runs frames of pinned sessions; ``slot`` is the worker a session was assigned."""

    mode: Executor
    restarts: int

    async def start(self) -> None: ...

    def assign(self, session_id: str) -> int: ...

    def release(self, slot: int, session_id: str) -> None: ...

    async def run(self, slot: int, request: FrameRequest) -> FrameProcessed | FrameFailure: ...

    def check_session(self, prepared: PreparedSession) -> None: ...


    def finish(self, slot: int, session_id: str) -> asyncio.Future[list[StoredSmoothedPose]]:
        """Drop the session's pipeline after flushing its back end; the future holds the
        flushed poses. Submitted at once, so it runs before any later frame of the session."""

    async def shutdown(self) -> None: ...

    def worker_pids(self) -> list[int | None]: ...


class ThreadRunner:
    """All pipelines in this process, frames in a thread pool (GIL-bound, but no pickling)."""

    mode: Executor = "thread"
    restarts = 0

    def __init__(self, workers: int, factory: PipelineFactory) -> None:
        self.factory = factory
        self.pool = ThreadPoolExecutor(workers, thread_name_prefix="swarmvo-worker")
        self.pipelines: dict[str, Pipeline] = {}

    async def start(self) -> None:
        return None

    def assign(self, session_id: str) -> int:
        return 0

    def release(self, slot: int, session_id: str) -> None:
        self.pipelines.pop(session_id, None)

    async def run(self, slot: int, request: FrameRequest) -> FrameProcessed | FrameFailure:
        loop = asyncio.get_running_loop()
        return await loop.run_in_executor(
            self.pool, compute_frame, self.pipelines, self.factory, request
        )

    def check_session(self, prepared: PreparedSession) -> None:
        problem = session_problem(self.factory, prepared)
        if problem is not None:
            raise ValueError(problem)


    def finish(self, slot: int, session_id: str) -> asyncio.Future[list[StoredSmoothedPose]]:
        # Taken out now: a pipeline built for a later frame is a new one, never this.
        pipeline = self.pipelines.pop(session_id, None)
        if pipeline is None:
            return _done([])
        return asyncio.get_running_loop().run_in_executor(
            self.pool, finish_pipeline, {session_id: pipeline}, session_id
        )

    async def shutdown(self) -> None:
        await asyncio.to_thread(self.pool.shutdown, True)

    def worker_pids(self) -> list[int | None]:
        return [os.getpid()]


# ----------------------------------------------------------------------------- worker process

_factory: PipelineFactory | None = None
_pipelines: dict[str, Pipeline] = {}


def _exit_with_parent() -> None:
    """Leave at once when the server process is gone (even SIGKILLed): no orphan workers."""
    parent = multiprocessing.parent_process()
    if parent is None:
        return
    multiprocessing.connection.wait([parent.sentinel])
    os._exit(0)


def _worker_init(factory: PipelineFactory) -> None:
    global _factory
    _factory = factory
    # The server decides when workers stop: Ctrl-C on the terminal reaches the whole process
    # group, and queued frames must still be processed while the server drains.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    threading.Thread(target=_exit_with_parent, name="swarmvo-parent-watch", daemon=True).start()
    warm_up = getattr(factory, "warm_up", None)
    if callable(warm_up):
        warm_up()


def _worker_frame(request: FrameRequest) -> FrameProcessed | FrameFailure:
    assert _factory is not None
    return compute_frame(_pipelines, _factory, request)


def _worker_check(prepared: PreparedSession) -> str | None:
    assert _factory is not None
    return session_problem(_factory, prepared)


def _worker_finish(session_id: str) -> list[StoredSmoothedPose]:
    return finish_pipeline(_pipelines, session_id)


def _worker_drop(session_id: str) -> None:
    _pipelines.pop(session_id, None)


def _worker_pid() -> int:
    return os.getpid()


@dataclass
class _Slot:
    executor: ProcessPoolExecutor
    generation: int = 0
    sessions: set[str] = field(default_factory=set)
    pid: int | None = None


class ProcessRunner:
    """``workers`` single-process executors; a session's frames always go to its own one."""

    mode: Executor = "process"

    def __init__(
        self,
        workers: int,
        factory: PipelineFactory,
        on_restart: Callable[[], None] | None = None,
        frame_timeout_s: float = 60.0,
    ) -> None:
        self.factory = factory
        self.frame_timeout_s = frame_timeout_s
        self.on_restart = on_restart
        self.context = multiprocessing.get_context("spawn")  # no fork of a threaded server
        self.slots = [_Slot(self._executor()) for _ in range(workers)]
        self.restarts = 0
        self._closing = False

    def _executor(self) -> ProcessPoolExecutor:
        return ProcessPoolExecutor(
            1, mp_context=self.context, initializer=_worker_init, initargs=(self.factory,)
        )

    async def _warm(self, slot: _Slot) -> None:
        """Start the process and let it import the estimator before frames wait on it."""
        try:
            slot.pid = await asyncio.wrap_future(slot.executor.submit(_worker_pid))
        except Exception as error:
            logger.error(
                "a worker process failed to start: %r (in process mode the pipeline factory "
                "must be picklable and its warm_up must succeed)", error
            )

    async def start(self) -> None:
        await asyncio.gather(*(self._warm(slot) for slot in self.slots))
        if any(slot.pid is None for slot in self.slots):
            await self.shutdown()
            raise RuntimeError("worker processes could not be started (see the log)")

    def assign(self, session_id: str) -> int:
        """Pin the session to the least-loaded worker (fewest live sessions, lowest index)."""
        slot = min(range(len(self.slots)), key=lambda i: (len(self.slots[i].sessions), i))
        self.slots[slot].sessions.add(session_id)
        return slot

    def check_session(self, prepared: PreparedSession) -> None:
        """Dry-run a new session in a worker (blocking; call it from a thread).

        The dry run imports and runs the estimator; in a worker, which has it loaded anyway,
        the server process stays free of it (a few hundred MB less, docs/performance.md). A
        worker that cannot answer is not a reason to refuse: the check then runs here.
        """
        slot = min(range(len(self.slots)), key=lambda i: (len(self.slots[i].sessions), i))
        try:
            future = self.slots[slot].executor.submit(_worker_check, prepared)
            problem = future.result(timeout=self.frame_timeout_s)
        except Exception:  # broken, replaced or stuck worker
            problem = session_problem(self.factory, prepared)
        if problem is not None:
            raise ValueError(problem)

    def release(self, slot: int, session_id: str) -> None:
        """Forget the session and free its pipeline's memory in the worker."""
        self.slots[slot].sessions.discard(session_id)
        if self._closing:
            return
        try:
            future = self.slots[slot].executor.submit(_worker_drop, session_id)
        except (BrokenProcessPool, RuntimeError):
            return  # a dead or replaced worker holds nothing any more
        future.add_done_callback(_ignore_outcome)

    async def run(self, slot: int, request: FrameRequest) -> FrameProcessed | FrameFailure:
        for _attempt in range(2):
            state = self.slots[slot]
            generation = state.generation
            try:
                future = state.executor.submit(_worker_frame, request)
            except BrokenProcessPool:
                # It died while idle: this frame never reached it, so a fresh worker may take it
                # (the session's pipeline is gone there and gets rebuilt).
                self._replace(slot, generation)
                continue
            answer = asyncio.wrap_future(future)
            try:
                while True:
                    try:
                        return await asyncio.wait_for(asyncio.shield(answer),
                                                      self.frame_timeout_s)
                    except TimeoutError:
                        if self._kill(slot, generation):
                            break
                        # Its process id is not known yet (still starting): wait once more.
            except BrokenProcessPool:
                self._replace(slot, generation)
                break
            with contextlib.suppress(Exception):
                await answer  # fails (the process is gone) or completed just now
            self._replace(slot, generation)
            return FrameFailure(
                503,
                f"the frame was not done after {self.frame_timeout_s:g} s; the worker process "
                "running this session was restarted and the session resumes from its last "
                "stored pose",
                "worker_timeout",
                pipeline_lost=True,
            )
        return FrameFailure(
            503,
            "the worker process running this session stopped unexpectedly; the frame was not "
            "processed and the session resumes from its last stored pose",
            "worker_died",
            pipeline_lost=True,
        )

    def finish(self, slot: int, session_id: str) -> asyncio.Future[list[StoredSmoothedPose]]:
        """Flush the session's back end in its worker, queued before any later frame of it."""
        try:
            future = self.slots[slot].executor.submit(_worker_finish, session_id)
        except (BrokenProcessPool, RuntimeError):
            return _done([])  # a dead or replaced worker holds nothing any more
        return asyncio.wrap_future(future)

    def _kill(self, slot: int, generation: int) -> bool:
        """SIGKILL a stuck worker (a thread cannot be stopped; a process can)."""
        state = self.slots[slot]
        if state.generation != generation or state.pid is None:
            return False
        logger.error("worker process %s (pid %s) is stuck; killing it", slot, state.pid)
        with contextlib.suppress(ProcessLookupError):
            os.kill(state.pid, signal.SIGKILL)
        return True

    def _replace(self, slot: int, generation: int) -> None:
        """Swap a broken executor for a fresh process (once, however many frames noticed)."""
        state = self.slots[slot]
        if state.generation != generation or self._closing:
            return
        logger.error("worker process %s (pid %s) died; starting a new one", slot, state.pid)
        old = state.executor
        state.executor = self._executor()
        state.generation += 1
        state.pid = None
        self.restarts += 1
        if self.on_restart is not None:
            self.on_restart()
        old.shutdown(wait=False, cancel_futures=True)
        warm = asyncio.get_running_loop().create_task(self._warm(state))
        warm.add_done_callback(_ignore_outcome)

    def worker_pids(self) -> list[int | None]:
        return [slot.pid for slot in self.slots]

    async def shutdown(self) -> None:
        self._closing = True
        await asyncio.gather(
            *(asyncio.to_thread(slot.executor.shutdown, True, cancel_futures=True)
              for slot in self.slots)
        )


def _done(value: Any) -> asyncio.Future[Any]:
    future = asyncio.get_running_loop().create_future()
    future.set_result(value)
    return future


def _ignore_outcome(future: Future[Any] | asyncio.Future[Any]) -> None:
    """Mark a fire-and-forget result as read (its failure changes nothing)."""
    if not future.cancelled():
        future.exception()
