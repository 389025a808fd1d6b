"""Refusals and the app's error handlers: every refused request is one counted JSON answer."""

from __future__ import annotations

import logging
from typing import Any

from fastapi import FastAPI, HTTPException, Request, Response
from fastapi.exception_handlers import http_exception_handler
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from sqlalchemy.exc import OperationalError
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.requests import ClientDisconnect

from service.metrics import Metrics
from service.schemas import ErrorOut

logger = logging.getLogger("swarmvo.service")


class Refusal(HTTPException):
    """A refused request, counted in ``swarmvo_errors_total`` by ``kind`` when it is answered.

    ``kind`` None: already counted where it was detected (e.g. by the session's consumer).
    """

    def __init__(
        self, status_code: int, detail: str, kind: str | None,
        headers: dict[str, str] | None = None,
    ) -> None:
        super().__init__(status_code, detail, headers=headers)
        self.kind = kind


# Kinds of refusals raised without one (FastAPI's own 404/405, form parsing, ...).
_KIND_BY_STATUS = {400: "malformed", 401: "auth", 404: "not_found", 405: "method",
                   408: "timeout", 409: "conflict", 413: "too_large", 415: "media_type",
                   422: "validation", 429: "limit"}

# The refusals a resource route may answer, documented with their body in the OpenAPI schema.
ERROR_RESPONSES: dict[int | str, dict[str, Any]] = {
    code: {"model": ErrorOut} for code in (400, 401, 404, 409, 413, 415, 422, 429)
}


def refusal_kind(error: StarletteHTTPException) -> str | None:
    if isinstance(error, Refusal):
        return error.kind
    return _KIND_BY_STATUS.get(error.status_code, f"http_{error.status_code}")


def unknown_session(session_id: str) -> Refusal:
    return Refusal(404, f"unknown session {session_id!r}", "unknown_session")


def install_error_handlers(app: FastAPI, metrics: Metrics) -> None:
    """Validation, refusals, client hang-ups, database outages and bugs: each one JSON answer."""

    @app.exception_handler(RequestValidationError)
    async def _validation(_request: Request, error: RequestValidationError) -> JSONResponse:
        metrics.errors.labels("validation").inc()
        parts = []
        for item in error.errors()[:5]:
            location = ".".join(str(p) for p in item.get("loc", ()))
            parts.append(f"{location}: {item.get('msg')}")
        return JSONResponse({"detail": "; ".join(parts) or "invalid request"}, status_code=422)

    @app.exception_handler(StarletteHTTPException)
    async def _refused(request: Request, error: StarletteHTTPException) -> Response:
        kind = refusal_kind(error)
        if kind is not None:
            metrics.errors.labels(kind).inc()
        return await http_exception_handler(request, error)

    @app.exception_handler(ClientDisconnect)
    async def _client_left(request: Request, _error: ClientDisconnect) -> Response:
        """An expected client-side event: one line, no traceback, not an internal error."""
        client = request.client.host if request.client else "?"
        logger.info("client %s disconnected during %s %s", client, request.method,
                    request.url.path)
        metrics.errors.labels("client_disconnect").inc()
        return Response(status_code=400)

    @app.exception_handler(OperationalError)
    async def _database_down(_request: Request, error: OperationalError) -> JSONResponse:
        """A lost database connection is a temporary outage (retry later), not a server bug."""
        logger.error("database unavailable: %s", str(error).splitlines()[0])
        metrics.errors.labels("storage").inc()
        return JSONResponse(
            {"detail": "database unavailable; retry later"},
            status_code=503,
            headers={"Retry-After": "1"},
        )

    @app.exception_handler(Exception)
    async def _internal(_request: Request, error: Exception) -> JSONResponse:
        logger.exception("unhandled error", exc_info=error)
        metrics.errors.labels("internal").inc()
        return JSONResponse({"detail": "internal server error"}, status_code=500)
