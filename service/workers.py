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

This module is the service's one import point for all of it; the parts live in
:mod:`service.frame_work` (one frame's work, wherever it runs), :mod:`service.worker_process`
(the inside of a worker process) and :mod:`service.runners` (pinning, supervision, shutdown).
"""

from service.frame_work import (
    CpuBudgetExceeded,
    FrameFailure,
    FrameProcessed,
    FrameRequest,
    PipelineSpec,
    compute_frame,
    cpu_budget,
    finish_pipeline,
    session_problem,
)
from service.runners import ProcessRunner, Runner, ThreadRunner

__all__ = [
    "CpuBudgetExceeded",
    "FrameFailure",
    "FrameProcessed",
    "FrameRequest",
    "PipelineSpec",
    "ProcessRunner",
    "Runner",
    "ThreadRunner",
    "compute_frame",
    "cpu_budget",
    "finish_pipeline",
    "session_problem",
]
