"""What a session's queue carries (frame jobs and their answers) and how a frame is refused."""

from __future__ import annotations

import asyncio
import time
from dataclasses import dataclass, field
from typing import Any

from service.answer import FrameAnswer

# WebSocket close code (application range 4000-4999) sent to streams of a deleted session.
STREAM_CLOSE_DELETED = 4404


class FrameRejected(Exception):
    """A frame the service will not process; carries the HTTP status that explains why."""

    def __init__(
        self, status_code: int, detail: str, kind: str, retry_after_s: float | None = None
    ) -> None:
        super().__init__(detail)
        self.status_code = status_code
        self.detail = detail
        self.kind = kind
        self.retry_after_s = retry_after_s  # a 503 that will pass: when to try again


class SessionGone(FrameRejected):
    """The session was deleted: everything sent for it afterwards is answered 404."""

    def __init__(self) -> None:
        super().__init__(404, "session was deleted", "unknown_session")


class FrameDropped(FrameRejected):
    """A queued frame discarded for a newer one (queue policy ``drop_oldest``)."""

    def __init__(self, detail: str) -> None:
        super().__init__(503, detail, "dropped")


@dataclass
class FrameJob:
    timestamp_ns: int
    left: bytes | memoryview
    right: bytes | memoryview
    future: asyncio.Future[Any]  # Answered; the flushed poses for a flush job
    raw: bool = False
    received: float = field(default_factory=time.perf_counter)
    flush: bool = False  # not a frame: flush the back end once the frames before it are done


@dataclass(frozen=True)
class Answered:
    """A frame's answer as a session hands it out: ``duplicate`` when the frame was sent again
    and this is its stored answer (it was not processed twice)."""

    answer: FrameAnswer
    duplicate: bool = False
