"""What a session sends its worker and makes of the answer, apart from the session's state.

The pipeline spec a worker builds a session's pipeline from (resumed from the last stored
pose when there is one), the client's answer made from the worker's (the session's timings
and the resume note added) and the refusal a worker's failure becomes.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from service.answer import FrameAnswer
from service.estimator_adapter import PreparedSession
from service.sessions.frames import FrameJob, FrameRejected
from service.storage import Store
from service.workers import FrameFailure, FrameProcessed, PipelineSpec

logger = logging.getLogger("swarmvo.service")

# Failures before the estimator saw the frame's IMU samples: they stay buffered for a retry.
_SAMPLES_UNSEEN = ("bad_image", "worker_died", "worker_timeout", "pipeline_missing", "cpu_budget")


@dataclass(frozen=True)
class WorkerRun:
    """What the worker answered for one frame, and the pipeline spec it was sent with."""

    outcome: FrameProcessed | FrameFailure
    spec: PipelineSpec | None
    resume_message: str
    sent: float  # perf_counter when the request left
    answered: float  # perf_counter when the answer came back


def pipeline_spec(
    store: Store, session_id: str, prepared: PreparedSession
) -> tuple[PipelineSpec, str]:
    """How to build the pipeline: resumed from the last stored pose when there is one
    (blocking I/O), with the note the next answer carries."""
    last, state = store.resume_point(session_id)
    if last is None:
        return PipelineSpec(prepared, None, 0), ""
    initial = np.array(last.pose, dtype=float).reshape(4, 4)
    if state is not None and state.get("timestamp_ns") != last.timestamp_ns:
        state = None  # not the state of this pose (written by an older server)
    known = ("its motion and back-end biases carried over" if state is not None
             else "motion since then is not known to the estimator")
    message = (
        f"resumed from the stored pose of frame {last.index} "
        f"(timestamp {last.timestamp_ns}); {known}"
    )
    return PipelineSpec(prepared, initial, last.index + 1, state), message


def samples_seen(outcome: FrameFailure) -> bool:
    """Whether the estimator saw the frame's IMU samples before failing (they count as used,
    so they are not fed twice)."""
    return outcome.kind not in _SAMPLES_UNSEEN


def failure_refusal(job: FrameJob, outcome: FrameFailure, session_id: str) -> FrameRejected:
    """The client's refusal for a worker's failure (its trace goes to the log)."""
    if outcome.trace:
        logger.error("frame %s of session %s failed in its worker:\n%s",
                     job.timestamp_ns, session_id, outcome.trace.rstrip())
    kind = "internal" if outcome.kind == "pipeline_missing" else outcome.kind
    return FrameRejected(outcome.status_code, outcome.detail, kind)


def answer_of(run: WorkerRun, outcome: FrameProcessed, timings: dict[str, float]) -> FrameAnswer:
    """The worker's answer with the session's timings and the resume note added;
    ``timings`` gains the worker's stages and the transfer time."""
    worked = outcome.answer.timings_s
    timings.update(worked)
    timings["transfer"] = max(
        0.0, run.answered - run.sent - worked["decode"] - worked["odometry"]
    )
    resumed = outcome.created and run.spec is not None and run.spec.initial_pose is not None
    message = "; ".join(
        m for m in (run.resume_message if resumed else "", outcome.answer.message) if m
    )
    return outcome.answer.model_copy(
        update={"timings_s": dict(timings), "message": message, "resumed": resumed}
    )
