"""Runners: where a session's frames are executed, a pinned worker process or a thread.

:class:`ProcessRunner` keeps one worker process per slot, each behind a pipe the event loop
reads and writes itself, pins each session to one (least-loaded first), replaces a worker that
dies or gets stuck, and drains them at shutdown.
:class:`ThreadRunner` has the same interface in-process, for factories that only make sense
there (test doubles whose state the caller inspects). The work of a frame itself is in
:mod:`service.frame_work`; what runs inside a worker process, in :mod:`service.worker_process`.
"""

from __future__ import annotations

import asyncio
import atexit
import contextlib
import logging
import os
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
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
from service.worker_pipe import WorkerDied, WorkerPipe
from service.worker_process import (
    worker_check,
    worker_context,
    worker_drop,
    worker_finish,
    worker_frame,
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
    worker: WorkerPipe | None = None  # None: not started, or could not be started
    generation: int = 0
    sessions: set[str] = field(default_factory=set)
    pid: int | None = None  # known once the worker is warmed up


class ProcessRunner:
    """``workers`` worker processes, each behind its own pipe that the event loop reads and
    writes (:mod:`service.worker_pipe`); a session's frames always go to its own worker."""

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
        self.slots = [_Slot() for _ in range(workers)]
        self.restarts = 0
        self._closing = False
        self._loop: asyncio.AbstractEventLoop | None = None
        self._warming: set[asyncio.Task[None]] = set()

    def _spawn(self, index: int) -> None:
        """Start a worker process for slot ``index`` and warm it up in the background."""
        state = self.slots[index]
        generation = state.generation
        try:
            state.worker = WorkerPipe(
                self.context, self.factory,
                lambda pipe: self._exited(index, generation, pipe),
            )
        except Exception as error:
            state.worker = None
            logger.error(
                "a worker process failed to start: %r (in process mode the pipeline factory "
                "must be picklable and its warm_up must succeed)", error
            )
            return
        warm = asyncio.get_running_loop().create_task(self._warm(state, state.worker))
        warm.add_done_callback(_ignore_outcome)
        self._warming.add(warm)
        warm.add_done_callback(self._warming.discard)

    async def _warm(self, state: _Slot, worker: WorkerPipe) -> None:
        try:
            pid = await worker.ready
        except Exception as error:
            logger.error(
                "a worker process failed to start: %r (in process mode the pipeline factory "
                "must be picklable and its warm_up must succeed)", error
            )
            return
        if state.worker is worker:
            state.pid = pid

    async def start(self) -> None:
        """Start the workers and let them import the estimator before frames wait on them."""
        self._loop = asyncio.get_running_loop()
        atexit.register(self._close_pipes)  # else multiprocessing's exit would wait for them
        for index in range(len(self.slots)):
            self._spawn(index)
        if self._warming:
            await asyncio.gather(*self._warming)
        if any(slot.pid is None for slot in self.slots):
            await self.shutdown()
            raise RuntimeError("worker processes could not be started (see the log)")

    def assign(self, session_id: str) -> int:
        """Pin the session to the least-loaded worker (fewest live sessions, lowest index)."""
        slot = self._least_loaded()
        self.slots[slot].sessions.add(session_id)
        return slot

    def _least_loaded(self) -> int:
        return min(range(len(self.slots)), key=lambda i: (len(self.slots[i].sessions), i))

    def _blocking_call(self, function: Callable[..., T], *args: Any) -> T:
        """``function(*args)`` in the least-loaded worker, from a thread other than the loop's
        (blocking). Raises what the function raised, or another error if no worker could."""
        loop = self._loop
        if loop is None or loop.is_closed() or _on_loop(loop):
            raise RuntimeError("no worker reachable from here")

        async def on_loop() -> T:
            worker = self.slots[self._least_loaded()].worker
            if worker is None or not worker.alive:
                raise WorkerDied("the worker process is gone")
            return await worker.call(function, *args)

        future = asyncio.run_coroutine_threadsafe(on_loop(), loop)
        try:
            return future.result(timeout=self.frame_timeout_s)
        except TimeoutError:
            future.cancel()
            raise

    def prepare_session(self, request: PrepareRequest) -> PreparedSession:
        """Validate a new session in a worker (blocking; call it from a thread).

        Reading the rig imports the estimator's calibration code and OpenCV: in a worker, which
        has them loaded anyway, the server process stays without them (docs/performance.md). A
        worker that cannot answer is not a reason to refuse: the preparation then runs here.
        """
        try:
            return self._blocking_call(worker_prepare, request)
        except ValueError:
            raise  # the session's own problem, with its message
        except Exception:  # dead, replaced or stuck worker
            return self.factory.prepare(*request)

    def call(self, function: Callable[..., T], *args: Any) -> T:
        """``function(*args)`` in a worker (blocking): the calibration file readers, which
        import OpenCV and SciPy, as ``prepare_session``. Module-level functions only."""
        try:
            return self._blocking_call(function, *args)
        except ValueError:
            raise
        except Exception:  # dead, replaced or stuck worker
            return function(*args)

    def check_session(self, prepared: PreparedSession) -> None:
        """Dry-run a new session in a worker (blocking; call it from a thread).

        The dry run imports and runs the estimator; in a worker, which has it loaded anyway,
        the server process stays free of it (a few hundred MB less, docs/performance.md). A
        worker that cannot answer is not a reason to refuse: the check then runs here.
        """
        try:
            problem = self._blocking_call(worker_check, prepared)
        except Exception:  # dead, replaced or stuck worker
            problem = session_problem(self.factory, prepared)
        if problem is not None:
            raise ValueError(problem)

    def release(self, slot: int, session_id: str) -> None:
        """Forget the session and free its pipeline's memory in the worker."""
        state = self.slots[slot]
        state.sessions.discard(session_id)
        if self._closing or state.worker is None or not state.worker.alive:
            return  # a dead or replaced worker holds nothing any more
        state.worker.call(worker_drop, session_id).add_done_callback(_ignore_outcome)

    def _send_frame(self, worker: WorkerPipe,
                    request: FrameRequest) -> asyncio.Future[FrameProcessed | FrameFailure]:
        """Send a frame, its images in a shared slot when one is free (given back once the
        worker is done with the call, whatever its outcome), else pickled with the request."""
        images = self.images
        if images is None or (pair := images.put(request.left, request.right)) is None:
            # Views of the received message (the stream's images) cannot be pickled; bytes can
            # (``bytes`` of a bytes object is that object, not a copy).
            return worker.call(worker_frame, replace(
                request, left=bytes(request.left), right=bytes(request.right)))
        try:
            return worker.call(worker_frame, replace(request, left=b"", right=b"", shared=pair),
                               over=lambda: images.release(pair))
        except BaseException:
            images.release(pair)
            raise

    async def run(self, slot: int, request: FrameRequest) -> FrameProcessed | FrameFailure:
        for _attempt in range(2):
            state = self.slots[slot]
            generation = state.generation
            worker = state.worker
            if worker is None or not worker.alive:
                # It died before this frame (or never started): this frame never reached it,
                # so a fresh worker may take it (the session's pipeline is rebuilt there).
                self._replace(slot, generation)
                continue
            try:
                answer = self._send_frame(worker, request)
            except WorkerDied:  # its pipe closed just now: the frame did not reach it either
                self._replace(slot, generation)
                continue
            try:
                while True:
                    try:
                        return await asyncio.wait_for(asyncio.shield(answer),
                                                      self.frame_timeout_s)
                    except TimeoutError:
                        if self._kill(slot, generation):
                            break
                        # Its process id is not known yet (still starting): wait once more.
            except WorkerDied:
                break
            with contextlib.suppress(Exception):
                await answer  # fails once the process is gone, or completed just now
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
        worker = self.slots[slot].worker
        if worker is None or not worker.alive or self._closing:
            return _done([])  # a dead or replaced worker holds nothing any more
        return worker.call(worker_finish, session_id)

    def _kill(self, slot: int, generation: int) -> bool:
        """SIGKILL a stuck worker (a thread cannot be stopped; a process can)."""
        state = self.slots[slot]
        if state.generation != generation or state.pid is None or state.worker is None:
            return False
        logger.error("worker process %s (pid %s) is stuck; killing it", slot, state.pid)
        state.worker.kill()
        return True

    def _exited(self, slot: int, generation: int, worker: WorkerPipe) -> None:
        """A worker process ended: replace it at once if it had been working (one that died
        while warming up is replaced by the next frame that needs it, so no start-up loop)."""
        state = self.slots[slot]
        if state.generation == generation and state.worker is worker and state.pid is not None:
            self._replace(slot, generation)

    def _replace(self, slot: int, generation: int) -> None:
        """Swap a dead worker for a fresh process (once, however many frames noticed)."""
        state = self.slots[slot]
        if state.generation != generation or self._closing:
            return
        logger.error("worker process %s (pid %s) died; starting a new one", slot, state.pid)
        state.generation += 1
        state.pid = None
        self.restarts += 1
        if self.on_restart is not None:
            self.on_restart()
        self._spawn(slot)

    def worker_pids(self) -> list[int | None]:
        return [slot.pid for slot in self.slots]

    async def shutdown(self) -> None:
        """Let every worker finish the calls it has, then stop it (pipe closed, SIGKILL after
        ``frame_timeout_s``)."""
        self._closing = True
        for task in list(self._warming):
            task.cancel()
        await asyncio.gather(
            *(slot.worker.stop(self.frame_timeout_s) for slot in self.slots
              if slot.worker is not None)
        )
        atexit.unregister(self._close_pipes)
        if self.images is not None:  # the workers are gone: nobody reads the slots any more
            self.images.close()

    def _close_pipes(self) -> None:
        """At interpreter exit without a shutdown: close the pipes so the workers leave."""
        for slot in self.slots:
            if slot.worker is not None:
                slot.worker.close_pipe_now()


def _image_slots(count: int, slot_bytes: int) -> ImageSlots | None:
    """The shared image slots, or None (off, or no shared memory here: images are pickled)."""
    if count <= 0:
        return None
    try:
        return ImageSlots(count, slot_bytes)
    except OSError as error:
        logger.warning("no shared memory for the images (%r); they go through the pipe", error)
        return None


def _on_loop(loop: asyncio.AbstractEventLoop) -> bool:
    try:
        return asyncio.get_running_loop() is loop
    except RuntimeError:
        return False


def _done(value: Any) -> asyncio.Future[Any]:
    future = asyncio.get_running_loop().create_future()
    future.set_result(value)
    return future


def _ignore_outcome(future: Future[Any] | asyncio.Future[Any]) -> None:
    """Mark a fire-and-forget result as read (its failure changes nothing)."""
    if not future.cancelled():
        future.exception()
