"""The inside of a worker process: its one pipeline factory, its pipelines, its entry points.

A worker holds the pipelines of the sessions pinned to it in a module-level dict; the server
calls the small functions below through the worker's pipe (``worker_serve`` reads the calls;
they must be importable by name, hence module level; the server side is
:mod:`service.worker_pipe`).
"""

from __future__ import annotations

import gc
import logging
import multiprocessing
import multiprocessing.connection
import os
import signal
import threading
from dataclasses import replace
from multiprocessing.connection import Connection
from multiprocessing.context import BaseContext
from typing import TYPE_CHECKING

from service.estimator_adapter import Pipeline, PipelineFactory, PreparedSession
from service.frame_work import (
    FrameFailure,
    FrameProcessed,
    FrameRequest,
    compute_frame,
    finish_pipeline,
    session_problem,
)
from service.memory import trim_free_memory
from service.shared_images import read_pair

if TYPE_CHECKING:  # a type alias only: the storage package would load SQLAlchemy (28 MB)
    from service.storage import SmoothedPose as StoredSmoothedPose

_factory: PipelineFactory | None = None
_pipelines: dict[str, Pipeline] = {}


def worker_context() -> BaseContext:
    """``spawn``: a fork of the server itself is unsafe, since it runs threads."""
    return multiprocessing.get_context("spawn")


def _exit_with_parent() -> None:
    """Leave at once when the server process is gone (even SIGKILLed): no orphan workers."""
    parent = multiprocessing.parent_process()
    if parent is None:
        return
    multiprocessing.connection.wait([parent.sentinel])
    os._exit(0)


def single_threaded_opencv() -> None:
    """One OpenCV thread per worker: the service runs one worker per core, so OpenCV's own
    thread pool only adds hand-overs between threads competing for the same cores (about 5-10 %
    more CPU per frame, docs/performance.md)."""
    import cv2

    cv2.setNumThreads(1)


def worker_init(factory: PipelineFactory) -> None:
    global _factory
    _factory = factory
    # The server decides when workers stop: Ctrl-C on the terminal reaches the whole process
    # group, and queued frames must still be processed while the server drains.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    threading.Thread(target=_exit_with_parent, name="swarmvo-parent-watch", daemon=True).start()
    single_threaded_opencv()
    # glibc's default allocator on purpose: with the server's fixed thresholds
    # (service.memory.reuse_frame_buffers) the workers' heaps kept ~80 MB more each at 8 robots
    # (docs/performance.md), more than the page faults they spare are worth.
    if not logging.getLogger().handlers:  # spawned: the server's logging is not inherited
        logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    # The worker decodes every frame's images itself, whatever estimator it runs.
    from service.images import warm_up_decoder

    warm_up_decoder()
    warm_up = getattr(factory, "warm_up", None)
    if callable(warm_up):
        warm_up()


def worker_serve(connection: Connection, factory: PipelineFactory) -> None:
    """The worker's main loop: warm up, say so, then answer ``(id, function, args)`` calls in
    order until the server closes the pipe. Answers are ``(id, ok, value)``; id 0 is the
    warm-up's (the pid, or the error that stops the worker)."""
    try:
        worker_init(factory)
    except BaseException as error:  # the server logs it and gives up on this worker
        connection.send((0, False, f"the worker's warm-up failed: {error!r}"))
        raise
    try:
        connection.send((0, True, os.getpid()))
    except OSError:  # the server is gone already
        return
    while True:
        try:
            call_id, function, args = connection.recv()
        except (EOFError, OSError):  # the server closed the pipe: stopping
            return
        try:
            answer = (call_id, True, function(*args))
        except Exception as error:
            answer = (call_id, False, error)
        try:
            connection.send(answer)
        except OSError:  # the server is gone or stopped us: nobody reads the answer
            return
        except Exception as error:  # an answer or an error that cannot be pickled
            connection.send((call_id, False, RuntimeError(
                f"the worker could not send its answer back: {error!r}")))


def worker_frame(request: FrameRequest) -> FrameProcessed | FrameFailure:
    assert _factory is not None
    if request.shared is not None:
        # Read in place: the server keeps the slot until this call has returned.
        left, right = read_pair(request.shared)
        request = replace(request, left=left, right=right, shared=None)
    return compute_frame(_pipelines, _factory, request)


def worker_prepare(request: tuple) -> PreparedSession:
    assert _factory is not None
    return _factory.prepare(*request)


def worker_check(prepared: PreparedSession) -> str | None:
    assert _factory is not None
    return session_problem(_factory, prepared)


def worker_finish(session_id: str) -> list[StoredSmoothedPose]:
    flushed = finish_pipeline(_pipelines, session_id)
    release_memory()
    return flushed


def worker_drop(session_id: str) -> None:
    if _pipelines.pop(session_id, None) is not None:
        release_memory()


def release_memory() -> None:
    """After a pipeline is dropped: free its cycles, then give the pages back to the system
    (a worker otherwise keeps the memory of every session it ever held; docs/performance.md)."""
    gc.collect()
    trim_free_memory()
