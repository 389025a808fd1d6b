"""The messages of the read-only watcher WebSocket, both directions, as one union on ``type`` each.

Browser to server: ``auth`` first (the key stays out of the URL), then only ``ping``. Server to
browser: ``hello``, ``world`` (how to draw the axes), ``poses`` and ``smoothed`` (columns, see
:mod:`service.web.feed`), ``synced`` once the backlog is sent, ``state`` every second, ``pong``,
and ``error`` before a close. Unknown fields of browser messages are ignored; types are strict.
"""

from __future__ import annotations

from typing import Annotated, Any, Literal

from pydantic import BaseModel, Field, Strict, TypeAdapter

from service.messages import PingMessage, PongMessage

# ----------------------------------------------------------------------------- browser -> server


class AuthMessage(BaseModel):
    """The first message: the API key, and the first frame index the page still needs."""

    type: Literal["auth"]
    token: Annotated[str, Strict()] | None = None
    since: Annotated[int, Strict(), Field(ge=0)] = 0


AUTH_MESSAGE: TypeAdapter[AuthMessage] = TypeAdapter(AuthMessage)
PING_MESSAGE: TypeAdapter[PingMessage] = TypeAdapter(PingMessage)

# ----------------------------------------------------------------------------- server -> browser

Activity = Literal["live", "idle"]


class WatchHello(BaseModel):
    type: Literal["hello"] = "hello"
    session_id: str
    name: str
    created_at: str = Field(description="ISO 8601, UTC")


class WorldMessage(BaseModel):
    """World axes (index, sign) across and up each view, and their labels."""

    type: Literal["world"] = "world"
    up: str
    top: list[list[int]]
    side: list[list[int]]
    side_across: list[list[Any]]  # [index, sign, label]
    top_labels: list[str]
    side_labels: list[str]
    note: str


class PosesMessage(BaseModel):
    """Stored poses as columns; vectors are flattened x, y, z triples."""

    type: Literal["poses"] = "poses"
    index: list[int]
    timestamp_ns: list[int]
    position: list[float]
    frontend_position: list[float]
    forward: list[float] = Field(description="the camera's optical axis in the world")
    status: str = Field(description="one letter per pose (see feed.STATUS_CODES)")
    inliers: list[int]
    latency_ms: list[float]
    message: str = Field(description="the newest pose's message")


class SmoothedMessage(BaseModel):
    """The smoother's final positions, flattened x, y, z triples."""

    type: Literal["smoothed"] = "smoothed"
    timestamp_ns: list[int]
    position: list[float]


class SyncedMessage(BaseModel):
    type: Literal["synced"] = "synced"
    frame_count: int


class StateMessage(BaseModel):
    type: Literal["state"] = "state"
    frame_count: int
    server_time: float
    activity: Activity
    frames_per_s: float | None
    last_update: float | None
    queued: int


class WatchError(BaseModel):
    """Why the channel refuses something; a close with an application code may follow."""

    type: Literal["error"] = "error"
    status: int
    detail: str


WatchServerMessage = Annotated[
    WatchHello | WorldMessage | PosesMessage | SmoothedMessage | SyncedMessage | StateMessage
    | WatchError | PongMessage,
    Field(discriminator="type"),
]
WATCH_SERVER_MESSAGE: TypeAdapter[WatchServerMessage] = TypeAdapter(WatchServerMessage)
