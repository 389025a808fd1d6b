"""Python client for the swarmvo odometry service: REST (sync/async), WebSocket, replay."""

from swarmvo_client.client import AsyncClient, Client
from swarmvo_client.datasets import LocalSequence, open_local_sequence
from swarmvo_client.errors import (
    ApiError,
    AuthenticationError,
    ConflictError,
    InvalidRequestError,
    NotFoundError,
    PayloadTooLargeError,
    RateLimitedError,
    ServerError,
    StreamError,
    SwarmvoError,
)
from swarmvo_client.evaluation import TrajectoryError, trajectory_error
from swarmvo_client.models import DroppedFrame, ImuData, Pose, RejectedFrame, Session
from swarmvo_client.reliable import Backoff, ReliableStream, reliable_stream
from swarmvo_client.replay import ReplayResult, replay, replay_http, replay_ws, write_tum
from swarmvo_client.stream import FrameStream, stream

__all__ = [
    "ApiError",
    "AsyncClient",
    "AuthenticationError",
    "Backoff",
    "Client",
    "ConflictError",
    "DroppedFrame",
    "FrameStream",
    "ImuData",
    "InvalidRequestError",
    "LocalSequence",
    "NotFoundError",
    "PayloadTooLargeError",
    "Pose",
    "RateLimitedError",
    "RejectedFrame",
    "ReliableStream",
    "ReplayResult",
    "ServerError",
    "Session",
    "StreamError",
    "SwarmvoError",
    "TrajectoryError",
    "open_local_sequence",
    "reliable_stream",
    "replay",
    "replay_http",
    "replay_ws",
    "stream",
    "trajectory_error",
    "write_tum",
]
