"""Runners: where a session's frames are executed, a pinned worker process or a thread.

:class:`ProcessRunner` keeps one single-process executor per worker, pins each session to one
(least-loaded first), replaces a worker that dies or gets stuck, and drains them at shutdown.
:class:`ThreadRunner` has the same interface in-process, for factories that only make sense
there (test doubles whose state the caller inspects). The work of a frame itself is in
:mod:`service.frame_work`; what runs inside a worker process, in :mod:`service.worker_process`.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import signal
from collections.abc import Callable
from concurrent.futures import Future, ProcessPoolExecutor, ThreadPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass, field, replace
from typing import Any, Protocol, TypeVar

from service.estimator_adapter import Pipeline, PipelineFactory, PreparedSession
from service.frame_work import (
    FrameFailure,
    FrameProcessed,
    FrameRequest,
    compute_frame,
    finish_pipeline,
    session_problem,
)
from service.settings import Executor
from service.shared_images import ImageSlots
from service.storage import SmoothedPose as StoredSmoothedPose
from service.worker_process import (
    worker_check,
    worker_context,
    worker_drop,
    worker_finish,
    worker_frame,
    worker_init,
    worker_pid,
    worker_prepare,
)

# What PipelineFactory.prepare takes: calibration, config, IMU noise, frame rate.
PrepareRequest = tuple[dict[str, Any], dict[str, Any], dict[str, Any] | None, float | None]

T = TypeVar("T")

logger = logging.getLogger("swarmvo.service")


class Runner(Protocol):
    """Runs frames of pinned sessions; ``slot`` is the worker a session was assigned."""

    mode: Executor
    restarts: int

    async def start(self) -> None: ...

    def assign(self, session_id: str) -> int: ...

    def release(self, slot: int, session_id: str) -> None: ...

    async def run(self, slot: int, request: FrameRequest) -> FrameProcessed | FrameFailure: ...

    def prepare_session(self, request: PrepareRequest) -> PreparedSession: ...

    def call(self, function: Callable[..., T], *args: Any) -> T: ...

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

    def prepare_session(self, request: PrepareRequest) -> PreparedSession:
        return self.factory.prepare(*request)

    def call(self, function: Callable[..., T], *args: Any) -> T:
        return function(*args)

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
        image_slots: int = 0,
        image_slot_bytes: int = 1 << 20,
    ) -> None:
        self.factory = factory
        self.frame_timeout_s = frame_timeout_s
        self.on_restart = on_restart
        self.context = worker_context()
        self.images = _image_slots(image_slots, image_slot_bytes)
        self.slots = [_Slot(self._executor()) for _ in range(workers)]
        self.restarts = 0
        self._closing = False

    def _executor(self) -> ProcessPoolExecutor:
        return ProcessPoolExecutor(
            1, mp_context=self.context, initializer=worker_init, initargs=(self.factory,)
        )

    async def _warm(self, slot: _Slot) -> None:
        """Start the process and let it import the estimator before frames wait on it."""
        try:
            slot.pid = await asyncio.wrap_future(slot.executor.submit(worker_pid))
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

    def prepare_session(self, request: PrepareRequest) -> PreparedSession:
        """Validate a new session in a worker (blocking; call it from a thread).

        Reading the rig imports the estimator's calibration code and OpenCV: in a worker, which
        has them loaded anyway, the server process stays without them (docs/performance.md). A
        worker that cannot answer is not a reason to refuse: the preparation then runs here.
        """
        slot = min(range(len(self.slots)), key=lambda i: (len(self.slots[i].sessions), i))
        try:
            future = self.slots[slot].executor.submit(worker_prepare, request)
            return future.result(timeout=self.frame_timeout_s)
        except ValueError:
            raise  # the session's own problem, with its message
        except Exception:  # broken, replaced or stuck worker
            return self.factory.prepare(*request)

    def call(self, function: Callable[..., T], *args: Any) -> T:
        """``function(*args)`` in a worker (blocking): the calibration file readers, which
        import OpenCV and SciPy, as ``prepare_session``. Module-level functions only."""
        slot = min(range(len(self.slots)), key=lambda i: (len(self.slots[i].sessions), i))
        try:
            future = self.slots[slot].executor.submit(function, *args)
            return future.result(timeout=self.frame_timeout_s)
        except ValueError:
            raise
        except Exception:  # broken, replaced or stuck worker
            return function(*args)

    def check_session(self, prepared: PreparedSession) -> None:
        """Dry-run a new session in a worker (blocking; call it from a thread).

        The dry run imports and runs the estimator; in a worker, which has it loaded anyway,
        the server process stays free of it (a few hundred MB less, docs/performance.md). A
        worker that cannot answer is not a reason to refuse: the check then runs here.
        """
        slot = min(range(len(self.slots)), key=lambda i: (len(self.slots[i].sessions), i))
        try:
            future = self.slots[slot].executor.submit(worker_check, prepared)
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
            future = self.slots[slot].executor.submit(worker_drop, session_id)
        except (BrokenProcessPool, RuntimeError):
            return  # a dead or replaced worker holds nothing any more
        future.add_done_callback(_ignore_outcome)

    def _submit_frame(self, executor: ProcessPoolExecutor,
                      request: FrameRequest) -> Future[FrameProcessed | FrameFailure]:
        """Submit a frame, its images in a shared slot when one is free (given back once the
        worker's call is over, whatever its outcome), else pickled with the request."""
        images = self.images
        if images is None or (pair := images.put(request.left, request.right)) is None:
            return executor.submit(worker_frame, request)
        try:
            future = executor.submit(
                worker_frame, replace(request, left=b"", right=b"", shared=pair)
            )
        except BaseException:
            images.release(pair)
            raise
        future.add_done_callback(lambda _future: images.release(pair))
        return future

    async def run(self, slot: int, request: FrameRequest) -> FrameProcessed | FrameFailure:
        for _attempt in range(2):
            state = self.slots[slot]
            generation = state.generation
            try:
                future = self._submit_frame(state.executor, request)
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
            future = self.slots[slot].executor.submit(worker_finish, session_id)
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
        if self.images is not None:  # the workers are gone: nobody reads the slots any more
            self.images.close()


def _image_slots(count: int, slot_bytes: int) -> ImageSlots | None:
    """The shared image slots, or None (off, or no shared memory here: images are pickled)."""
    if count <= 0:
        return None
    try:
        return ImageSlots(count, slot_bytes)
    except OSError as error:
        logger.warning("no shared memory for the images (%r); they go through the pipe", error)
        return None


def _done(value: Any) -> asyncio.Future[Any]:
    future = asyncio.get_running_loop().create_future()
    future.set_result(value)
    return future


def _ignore_outcome(future: Future[Any] | asyncio.Future[Any]) -> None:
    """Mark a fire-and-forget result as read (its failure changes nothing)."""
    if not future.cancelled():
        future.exception()
