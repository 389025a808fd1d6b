"""Exceptions carrying the server's own explanation (its JSON ``detail``)."""

from __future__ import annotations


class SwarmvoError(Exception):
    """Base class of everything this client raises on purpose."""


class ApiError(SwarmvoError):
    """The server answered with an error status."""

    def __init__(self, status_code: int, detail: str) -> None:
        super().__init__(f"HTTP {status_code}: {detail}")
        self.status_code = status_code
        self.detail = detail


class AuthenticationError(ApiError):
    """401: missing or unknown API key."""


class NotFoundError(ApiError):
    """404: unknown session (or one owned by another key)."""


class ConflictError(ApiError):
    """409: e.g. a timestamp that does not increase."""


class PayloadTooLargeError(ApiError):
    """413: request, image or IMU batch over the server's limits."""


class InvalidRequestError(ApiError):
    """400/415/422: the request was malformed or its values were refused."""


class RateLimitedError(ApiError):
    """429: the session queue or the session count is full."""


class ServerError(ApiError):
    """5xx: the server failed; the request may be retried."""


class StreamError(SwarmvoError):
    """The server reported a protocol problem on the WebSocket stream."""


_BY_STATUS: dict[int, type[ApiError]] = {
    400: InvalidRequestError,
    401: AuthenticationError,
    404: NotFoundError,
    409: ConflictError,
    413: PayloadTooLargeError,
    415: InvalidRequestError,
    422: InvalidRequestError,
    429: RateLimitedError,
}


def error_for(status_code: int, detail: str) -> ApiError:
    if status_code >= 500:
        return ServerError(status_code, detail)
    return _BY_STATUS.get(status_code, ApiError)(status_code, detail)
