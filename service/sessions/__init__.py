"""Live sessions: what their queues carry (:mod:`.frames`), their IMU buffer
(:mod:`.imu_buffer`), one session's consumer (:mod:`.live`) and a replica's sessions
(:mod:`.manager`)."""

from service.sessions.frames import (
    STREAM_CLOSE_DELETED,
    Answered,
    FrameDropped,
    FrameJob,
    FrameRejected,
    SessionGone,
)
from service.sessions.imu_buffer import ImuSamples
from service.sessions.live import LiveSession
from service.sessions.manager import SessionManager, StreamHandle

__all__ = [
    "STREAM_CLOSE_DELETED",
    "Answered",
    "FrameDropped",
    "FrameJob",
    "FrameRejected",
    "ImuSamples",
    "LiveSession",
    "SessionGone",
    "SessionManager",
    "StreamHandle",
]
