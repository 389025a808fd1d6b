"""One frame's work where it runs: decode, (re)build the session's pipeline, odometry, answer.

Everything here runs inside the process (or thread) that holds the session's pipeline, and never
raises: a frame gives either :class:`FrameProcessed` or a :class:`FrameFailure` whose ``kind``
tells the session what to do next. The requests and answers are plain picklable data, since
they cross a process boundary.
"""

from __future__ import annotations

import contextlib
import logging
import signal
import threading
import time
import traceback
from collections.abc import Iterator
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from estimator.geometry import nearest_rigid
from estimator.types import ImuBatch, StereoFrame
from service.answer import FrameAnswer, OdometryOut, SmoothedPose
from service.estimator_adapter import Pipeline, PipelineFactory, PreparedSession
from service.images import ImageError, ImageLimits, decode_pair, decode_raw_pair
from service.shared_images import SharedPair

if TYPE_CHECKING:  # a type alias only: the storage package would load SQLAlchemy in workers
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
    """One frame for one session, as sent to a worker (encoded images, not arrays).

    The images are either in ``left``/``right`` or, with ``shared``, in a shared-memory slot
    (``left``/``right`` then empty until the worker reads them; :mod:`service.shared_images`).
    """

    session_id: str
    frame_index: int
    timestamp_ns: int
    left: bytes | memoryview
    right: bytes | memoryview
    limits: ImageLimits
    image_size: tuple[int, int]
    imu: ImuBatch | None = None
    raw: bool = False  # 8-bit grey pixels, row-major, image_size; no PNG/JPEG container
    create: PipelineSpec | None = None  # build the pipeline first (new, resumed or lost)
    cpu_budget_s: float = 0.0  # CPU seconds for decode + odometry; 0 = unlimited
    shared: SharedPair | None = None


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
        pipelines.pop(request.session_id, None)
        try:
            pipeline, note = _build_pipeline(factory, request.create)
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
    timings = {"decode": decoded - started, "odometry": time.perf_counter() - decoded}
    answer = _answer(request, pipeline, report, timings, note)
    return FrameProcessed(answer, created, _pipeline_state(pipeline))


def _build_pipeline(factory: PipelineFactory, spec: PipelineSpec) -> tuple[Pipeline, str]:
    """A new, resumed or rebuilt pipeline, and a note for the answer when resuming needed help."""
    note = ""
    try:
        pipeline = factory.create(spec.prepared, spec.initial_pose, spec.first_index)
    except ValueError:
        if spec.initial_pose is None:
            raise
        # A stored pose the estimator finds not quite rigid would otherwise fail every
        # later frame too: resume from the nearest rigid transform instead.
        pipeline = factory.create(spec.prepared, nearest_rigid(spec.initial_pose),
                                  spec.first_index)
        note = "the stored pose was not exactly rigid; resumed from its nearest rotation"
    if spec.state is not None and hasattr(pipeline, "restore"):
        try:
            pipeline.restore(spec.state)
        except (KeyError, TypeError, ValueError) as error:
            note = f"the stored state was not usable ({error}); resumed from the pose"
            pipeline = factory.create(spec.prepared, spec.initial_pose, spec.first_index)
    return pipeline, note


def _answer(request: FrameRequest, pipeline: Pipeline, report: Any,
            timings: dict[str, float], note: str) -> FrameAnswer:
    for stage, seconds in report.timings_s.items():
        timings[f"odometry.{stage}"] = float(seconds)
    odometry = getattr(pipeline, "last_odometry", None)
    return FrameAnswer(
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
