"""The messages of a session's WebSocket stream, both directions, as one union on ``type`` each.

Client to server: ``frame`` (a header; the left then the right image follow as binary
messages), ``imu``, ``ping``, ``close``. Server to client: ``hello`` once, then ``pose``,
``dropped`` or ``rejected`` for each frame in order, ``error`` for a message that is not a
frame, and ``pong``; ``smoothed`` is the last message when the session's stream ends (``close``)
or the session is deleted. Unknown fields of client messages are ignored; field types are strict.
"""

from __future__ import annotations

from typing import Annotated, Any, Literal, get_args

from pydantic import BaseModel, Field, Strict, TypeAdapter, model_validator

from service.answer import FrameAnswer
from service.schemas import ImuSample, SmoothedOut, TimestampNs
from service.settings import QueuePolicy

PositiveInt = Annotated[int, Strict(), Field(gt=0)]
# Containers the images may come in: decoded by the server (``png`` covers any of them), or
# ``raw8``: width*height bytes of 8-bit grey, row by row.
Encoding = Literal["png", "jpeg", "image", "raw8"]

# ----------------------------------------------------------------------------- client -> server


class FrameHeader(BaseModel):
    """Announces one stereo pair: the next binary messages carry its left + right images."""

    type: Literal["frame"]
    timestamp_ns: TimestampNs
    left_bytes: PositiveInt
    right_bytes: PositiveInt
    encoding: Encoding = "png"
    width: PositiveInt | None = None
    height: PositiveInt | None = None
    imu: list[ImuSample] | None = Field(None, description="IMU samples since the previous frame")

    @model_validator(mode="after")
    def _raw_sizes(self) -> FrameHeader:
        if self.encoding != "raw8":
            return self
        if self.width is None or self.height is None:
            raise ValueError("raw8 frames need positive integer width and height")
        pixels = self.width * self.height
        if (self.left_bytes, self.right_bytes) != (pixels, pixels):
            raise ValueError(f"raw8 left_bytes and right_bytes must both be width*height = "
                             f"{pixels}")
        return self


class ImuMessage(BaseModel):
    type: Literal["imu"]
    samples: list[ImuSample]


class PingMessage(BaseModel):
    type: Literal["ping"]


class CloseMessage(BaseModel):
    """The client is done: the server answers every frame it holds, then closes (1000)."""

    type: Literal["close"]


ClientMessage = Annotated[
    FrameHeader | ImuMessage | PingMessage | CloseMessage, Field(discriminator="type")
]
CLIENT_MESSAGE: TypeAdapter[ClientMessage] = TypeAdapter(ClientMessage)
# The ``type`` of each client message, read off the models: the valid kinds, in one place.
CLIENT_TYPES: tuple[str, ...] = tuple(
    get_args(model.model_fields["type"].annotation)[0]
    for model in get_args(get_args(ClientMessage)[0])
)

# ----------------------------------------------------------------------------- server -> client


class HelloMessage(BaseModel):
    """Sent once on connecting: where the session stands, so a client can resume."""

    type: Literal["hello"] = "hello"
    session_id: str
    next_index: int
    last_timestamp_ns: int | None
    queue_size: int
    queue_policy: QueuePolicy


class PoseMessage(FrameAnswer):
    """A frame's stored pose: the same body as the REST answer, with its ``type``."""

    type: Literal["pose"] = "pose"
    # True: the frame was sent again and this is its stored answer (it was not processed twice).
    duplicate: bool = False


class DroppedMessage(BaseModel):
    """A queued frame dropped for a newer one (queue policy ``drop_oldest``)."""

    type: Literal["dropped"] = "dropped"
    timestamp_ns: int
    detail: str


class RejectedMessage(BaseModel):
    """A frame refused with an HTTP-like status; ``timestamp_ns`` echoes the header's value."""

    type: Literal["rejected"] = "rejected"
    timestamp_ns: Any
    status: int
    detail: str
    # A passing refusal (503: database away, session leased by another replica): resend the
    # frame after this many seconds, possibly to another replica.
    retry_after_s: float | None = None


class ErrorMessage(BaseModel):
    """A message that could not be used (not a frame, or a frame's images out of place)."""

    type: Literal["error"] = "error"
    detail: str


class PongMessage(BaseModel):
    type: Literal["pong"] = "pong"


class SmoothedMessage(SmoothedOut):
    """The stream's last message: the back end flushed, the final poses of the frames still in
    its window (possibly none); they are stored too (``GET .../smoothed``)."""

    type: Literal["smoothed"] = "smoothed"


ServerMessage = Annotated[
    HelloMessage | PoseMessage | DroppedMessage | RejectedMessage | ErrorMessage | PongMessage
    | SmoothedMessage,
    Field(discriminator="type"),
]
SERVER_MESSAGE: TypeAdapter[ServerMessage] = TypeAdapter(ServerMessage)
