"""FastAPI application: routes validate, authenticate, queue and persist; the odometry itself
runs in :mod:`service.sessions` workers behind a :class:`~service.pipeline.PipelineFactory`."""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import re
import tempfile
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any, Literal

import numpy as np
from fastapi import Depends, FastAPI, HTTPException, Query, Request, Response, WebSocket
from fastapi.exception_handlers import http_exception_handler
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse, PlainTextResponse
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer
from pydantic import ValidationError
from sqlalchemy.exc import OperationalError
from starlette.concurrency import run_in_threadpool
from starlette.datastructures import FormData, UploadFile
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.formparsers import MultiPartException
from starlette.requests import ClientDisconnect
from starlette.types import ASGIApp, Message, Receive, Scope, Send
from starlette.websockets import WebSocketDisconnect

from service.auth import AuthError, bearer_token, owner_for
from service.limits import image_size_problems, work_limit_problems
from service.metrics import Metrics
from service.pipeline import (
    EstimatorFactory,
    PipelineFactory,
    euroc_calibration,
    euroc_imu_noise,
    kitti_calibration,
)
from service.schemas import (
    ErrorOut,
    Health,
    ImuBatchIn,
    ImuBatchOut,
    PoseOut,
    SessionCreate,
    SessionList,
    SessionOut,
    SmoothedOut,
    SmoothedPose,
    TrajectoryOut,
)
from service.sessions import (
    FrameDropped,
    FrameRejected,
    ImuSamples,
    SessionGone,
    SessionManager,
    SessionWorker,
)
from service.settings import ServiceSettings
from service.storage import SessionRecord, Store

logger = logging.getLogger("swarmvo.service")

SESSION_ID = re.compile(r"^[0-9a-f]{32}$")
# Plain ASCII digits only: int() would also take "1_000", " 5 " and non-ASCII digits.
DIGITS = re.compile(r"[0-9]{1,19}")
MAX_CALIBRATION_FILE = 1024 * 1024
MAX_TEXT_FIELD = 4 * 1024 * 1024
# Answers (poses, refusals, errors) a WebSocket client may leave unread before the server
# stops reading its socket; each is a small JSON message (images are not kept with them).
MAX_UNSENT_REPLIES = 64


@dataclass
class ServiceState:
    settings: ServiceSettings
    store: Store
    manager: SessionManager
    metrics: Metrics
    factory: PipelineFactory


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


def refusal_kind(error: StarletteHTTPException) -> str | None:
    if isinstance(error, Refusal):
        return error.kind
    return _KIND_BY_STATUS.get(error.status_code, f"http_{error.status_code}")


# ----------------------------------------------------------------------------- request body


class BodyLimit:
    """Refuse oversized or stalled request bodies: by Content-Length, and while streaming in.

    A body larger than ``max_bytes`` gets a 413; a client that stops sending its body for
    ``timeout_s`` gets a 408, so half-sent requests do not hold connections forever.
    """

    def __init__(self, app: ASGIApp, max_bytes: int, timeout_s: float, metrics: Metrics) -> None:
        self.app = app
        self.max_bytes = max_bytes
        self.timeout_s = timeout_s
        self.metrics = metrics

    async def _refuse(self, send: Send, refusal: Refusal) -> None:
        self.metrics.errors.labels(refusal.kind or "too_large").inc()
        body = json.dumps({"detail": refusal.detail}).encode()
        await send(
            {
                "type": "http.response.start",
                "status": refusal.status_code,
                "headers": [
                    (b"content-type", b"application/json"),
                    (b"content-length", str(len(body)).encode()),
                    (b"connection", b"close"),
                ],
            }
        )
        await send({"type": "http.response.body", "body": body})

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        for name, value in scope.get("headers", []):
            if name == b"content-length":
                try:
                    declared = int(value)
                except ValueError:
                    declared = -1
                if declared < 0 or declared > self.max_bytes:
                    await self._refuse(send, _TooLarge(self.max_bytes))
                    return
        received = 0
        body_done = False
        started = False

        async def limited_receive() -> Message:
            nonlocal received, body_done
            if body_done:  # afterwards only a disconnect can come: no time limit
                return await receive()
            try:
                message = await asyncio.wait_for(receive(), self.timeout_s)
            except TimeoutError:
                raise _BodyTimeout(self.timeout_s) from None
            if message["type"] == "http.request":
                received += len(message.get("body", b""))
                body_done = not message.get("more_body", False)
                if received > self.max_bytes:
                    raise _TooLarge(self.max_bytes)
            return message

        async def tracking_send(message: Message) -> None:
            nonlocal started
            if message["type"] == "http.response.start":
                started = True
            await send(message)

        try:
            await self.app(scope, limited_receive, tracking_send)
        except _BodyRefusal as refusal:
            if not started:
                await self._refuse(send, refusal)


class _BodyRefusal(Refusal):
    """Raised from ``receive``; an HTTPException, so body parsers pass it through."""


class _TooLarge(_BodyRefusal):
    def __init__(self, max_bytes: int) -> None:
        super().__init__(413, f"request body exceeds the limit of {max_bytes} bytes", "too_large")


class _BodyTimeout(_BodyRefusal):
    def __init__(self, seconds: float) -> None:
        super().__init__(
            408, f"request body not received: nothing arrived for {seconds:g} s", "timeout"
        )


# ----------------------------------------------------------------------------- helpers


bearer_scheme = HTTPBearer(auto_error=False, description="API key: 'Authorization: Bearer KEY'")


def _state(request: Request) -> ServiceState:
    return request.app.state.swarmvo


def current_owner(
    request: Request,
    _credentials: Annotated[HTTPAuthorizationCredentials | None, Depends(bearer_scheme)],
) -> str:
    state = _state(request)
    try:
        return owner_for(bearer_token(request.headers.get("authorization")), state.settings)
    except AuthError as error:
        raise Refusal(401, str(error), "auth", headers={"WWW-Authenticate": "Bearer"}) from error


Owner = Annotated[str, Depends(current_owner)]
State = Annotated[ServiceState, Depends(_state)]


def _unknown(session_id: str) -> HTTPException:
    return Refusal(404, f"unknown session {session_id!r}", "unknown_session")


def _lookup(state: ServiceState, session_id: str, owner: str) -> SessionRecord:
    """The owner's session or 404 (another key's session is indistinguishable from none)."""
    if session_id in state.manager.deleted:
        raise _unknown(session_id)
    record = state.store.get_session(session_id, owner) if SESSION_ID.match(session_id) else None
    if record is None:
        raise _unknown(session_id)
    return record


async def _lookup_async(state: ServiceState, session_id: str, owner: str) -> SessionRecord:
    worker = state.manager.workers.get(session_id)
    if worker is not None and worker.owner == owner:
        return worker.record
    return await run_in_threadpool(_lookup, state, session_id, owner)


def _live(state: ServiceState, record: SessionRecord) -> SessionWorker:
    """The session's worker, or 404 when it was deleted after it was looked up."""
    try:
        return state.manager.worker(record)
    except SessionGone as error:
        raise _unknown(record.id) from error


def parse_imu(text: str | bytes | dict[str, Any], settings: ServiceSettings) -> ImuSamples:
    """Validated IMU samples (finite numbers, bounded count) as arrays."""
    try:
        if isinstance(text, dict):
            batch = ImuBatchIn.model_validate(text)
        else:
            batch = ImuBatchIn.model_validate_json(text)
    except ValidationError as error:
        raise Refusal(422, f"invalid IMU samples: {_brief(error)}", "validation") from error
    if len(batch.samples) > settings.max_imu_batch:
        raise Refusal(
            413,
            f"{len(batch.samples)} IMU samples in one batch; the limit is "
            f"{settings.max_imu_batch}",
            "too_large",
        )
    return ImuSamples(
        np.array([s.timestamp_ns for s in batch.samples], dtype=np.int64),
        np.array([s.gyro for s in batch.samples], dtype=float).reshape(-1, 3),
        np.array([s.accel for s in batch.samples], dtype=float).reshape(-1, 3),
    )


def _brief(error: ValidationError) -> str:
    parts = []
    for item in error.errors()[:5]:
        location = ".".join(str(p) for p in item.get("loc", ()))
        parts.append(f"{location}: {item.get('msg')}" if location else str(item.get("msg")))
    more = len(error.errors()) - 5
    return "; ".join(parts) + (f" (and {more} more)" if more > 0 else "")


async def _form(request: Request, max_files: int, max_fields: int) -> FormData:
    content_type = request.headers.get("content-type", "")
    if not content_type.startswith("multipart/form-data"):
        raise HTTPException(415, "expected a multipart/form-data body")
    try:
        return await request.form(
            max_files=max_files, max_fields=max_fields, max_part_size=MAX_TEXT_FIELD
        )
    except MultiPartException as error:
        raise Refusal(400, f"malformed multipart body: {error.message}", "malformed") from error
    except (ValueError, KeyError) as error:
        raise Refusal(400, f"malformed multipart body: {error}", "malformed") from error


async def _file(form: FormData, name: str, limit: int | None = None) -> bytes:
    item = form.get(name)
    if item is None:
        raise HTTPException(422, f"missing file field {name!r}")
    if not isinstance(item, UploadFile):
        raise HTTPException(422, f"field {name!r} must be a file upload")
    data = await item.read()
    if limit is not None and len(data) > limit:
        raise HTTPException(413, f"file {name!r} is larger than {limit} bytes")
    return data


def _text(form: FormData, name: str, required: bool = True) -> str | None:
    item = form.get(name)
    if item is None:
        if required:
            raise HTTPException(422, f"missing form field {name!r}")
        return None
    if not isinstance(item, str):
        raise HTTPException(422, f"form field {name!r} must be text, not a file")
    if "\x00" in item:  # no database text type stores NUL (PostgreSQL refuses it)
        raise HTTPException(422, f"form field {name!r} contains a NUL character")
    return item


def _int_field(form: FormData, name: str, low: int, high: int) -> int:
    text = _text(form, name)
    assert text is not None
    if not DIGITS.fullmatch(text):
        raise HTTPException(
            422, f"form field {name!r} must be a non-negative integer in plain ASCII digits"
        )
    value = int(text)
    if not low <= value <= high:
        raise HTTPException(422, f"form field {name!r} must be in [{low}, {high}]")
    return value


def _json_object(text: str | None, name: str) -> dict[str, Any]:
    if text is None or not text.strip():
        return {}
    try:
        value = json.loads(text)
    except json.JSONDecodeError as error:
        raise HTTPException(422, f"form field {name!r} is not valid JSON: {error}") from error
    if not isinstance(value, dict):
        raise HTTPException(422, f"form field {name!r} must be a JSON object")
    return value


def _create_session(
    state: ServiceState,
    owner: str,
    name: str,
    calibration: dict[str, Any],
    config: dict[str, Any],
    imu_noise: dict[str, Any] | None,
) -> SessionOut:
    if state.store.count_sessions(owner) >= state.settings.max_sessions_per_key:
        raise Refusal(
            429,
            f"session limit reached ({state.settings.max_sessions_per_key} per API key); "
            "delete sessions you no longer need",
            "too_many_sessions",
        )
    try:
        prepared = state.factory.prepare(calibration, config, imu_noise)
        problems = work_limit_problems(prepared.config) + image_size_problems(
            prepared.image_size, state.settings
        )
        if problems:
            raise ValueError("; ".join(problems))
        check = getattr(state.factory, "check", None)
        if callable(check):
            check(prepared)
    except ValueError as error:
        raise Refusal(422, str(error), "bad_session") from error
    record = state.store.create_session(
        owner, name, prepared.calibration, prepared.config, prepared.imu_noise, prepared.image_size
    )
    return SessionOut.of(record)


def _multipart_body(required: list[str], properties: dict[str, Any]) -> dict[str, Any]:
    """OpenAPI request body of a multipart route (FastAPI cannot infer it from raw parsing)."""
    schema = {"type": "object", "required": required, "properties": properties}
    return {
        "requestBody": {
            "required": True,
            "content": {"multipart/form-data": {"schema": schema}},
        }
    }


_BINARY = {"type": "string", "format": "binary"}
_CONFIG_FIELD = {"type": "string", "description": "JSON SwarmvoConfig"}

_MULTIPART_FRAME = _multipart_body(
    ["left", "right", "timestamp_ns"],
    {
        "left": _BINARY,
        "right": _BINARY,
        "timestamp_ns": {"type": "integer", "minimum": 0},
        "imu": {
            "type": "string",
            "description": 'JSON {"samples": [{"timestamp_ns", "gyro", '
            '"accel"}]}: IMU samples since the previous frame',
        },
    },
)
_MULTIPART_EUROC = _multipart_body(
    ["cam0", "cam1"],
    {
        "cam0": _BINARY,
        "cam1": _BINARY,
        "imu0": _BINARY,
        "name": {"type": "string"},
        "config": _CONFIG_FIELD,
    },
)
_MULTIPART_KITTI = _multipart_body(
    ["calib", "width", "height"],
    {
        "calib": _BINARY,
        "width": {"type": "integer", "minimum": 1},
        "height": {"type": "integer", "minimum": 1},
        "name": {"type": "string"},
        "config": _CONFIG_FIELD,
    },
)

# format=json answers TrajectoryOut (added by FastAPI); tum and kitti answer plain text.
_TRAJECTORY_CONTENT: dict[str, Any] = {
    "description": "JSON for format=json; text for format=tum (t x y z qx qy qz qw per line) "
    "and format=kitti (12 numbers of the 3x4 pose per line)",
    "content": {"text/plain": {"schema": {"type": "string"}}},
}

_SMOOTHED_CONTENT: dict[str, Any] = {
    "description": "JSON for format=json; text for format=tum (t x y z qx qy qz qw per line)",
    "content": {"text/plain": {"schema": {"type": "string"}}},
}

_ERRORS: dict[int | str, dict[str, Any]] = {
    code: {"model": ErrorOut} for code in (400, 401, 404, 409, 413, 415, 422, 429)
}


# ----------------------------------------------------------------------------- app


def create_app(
    settings: ServiceSettings,
    factory: PipelineFactory | None = None,
    store: Store | None = None,
) -> FastAPI:
    """The service app; ``factory`` defaults to the real odometry, ``store`` to settings' DB."""
    settings.check_startable()
    metrics = Metrics()
    pipeline_factory = factory or EstimatorFactory()

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        own_store = store is None
        database = store or await run_in_threadpool(
            Store.open, settings.resolved_database_url(), settings.sqlite_synchronous
        )
        mode = settings.executor
        if mode == "auto":
            mode = "thread" if factory is not None else "process"
        manager = SessionManager(settings, database, pipeline_factory, metrics, mode)
        try:
            await manager.start()
        except BaseException:
            if own_store:
                database.close()
            raise
        app.state.swarmvo = ServiceState(settings, database, manager, metrics, pipeline_factory)
        try:
            yield
        finally:
            await manager.shutdown()
            if own_store:
                database.close()

    app = FastAPI(
        title="swarmvo odometry service",
        version="1",
        description="Stereo visual odometry over HTTP and WebSocket. Every answered pose is "
        "stored before the answer is sent.",
        lifespan=lifespan,
        # Served offline by service.web (the defaults load Swagger UI / ReDoc from a CDN).
        docs_url=None,
        redoc_url=None,
    )
    app.add_middleware(BodyLimit, max_bytes=settings.max_request_bytes,
                       timeout_s=settings.request_body_timeout_s, metrics=metrics)

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

    # -- operations

    @app.get("/healthz", response_model=Health, tags=["operations"])
    async def healthz(request: Request) -> Health:
        state = _state(request)
        try:
            await run_in_threadpool(state.store.ping)
        except Exception as error:
            logger.error("health check: database unavailable: %s", str(error).splitlines()[:1])
            raise Refusal(503, "database unavailable", "storage") from error
        runner = state.manager.runner
        return Health(status="ok", sessions_active=len(state.manager.workers), database="ok",
                      executor=runner.mode, workers=settings.workers)

    @app.get("/metrics", response_class=PlainTextResponse, tags=["operations"])
    async def prometheus_metrics() -> Response:
        return Response(metrics.render(), media_type="text/plain; version=0.0.4; charset=utf-8")

    # -- sessions

    @app.post(
        "/v1/sessions", status_code=201, response_model=SessionOut, tags=["sessions"],
        responses=_ERRORS,
    )
    def create_session(body: SessionCreate, owner: Owner, state: State) -> SessionOut:
        noise = None if body.imu_noise is None else body.imu_noise.model_dump()
        return _create_session(state, owner, body.name, body.calibration, body.config, noise)

    @app.post(
        "/v1/sessions/euroc", status_code=201, response_model=SessionOut, tags=["sessions"],
        openapi_extra=_MULTIPART_EUROC, responses=_ERRORS,
    )
    async def create_session_euroc(request: Request, owner: Owner, state: State) -> SessionOut:
        """Session from EuRoC ``cam0/sensor.yaml``, ``cam1/sensor.yaml`` (and ``imu0``)."""
        form = await _form(request, max_files=3, max_fields=2)
        cam0 = await _file(form, "cam0", MAX_CALIBRATION_FILE)
        cam1 = await _file(form, "cam1", MAX_CALIBRATION_FILE)
        imu0 = await _file(form, "imu0", MAX_CALIBRATION_FILE) if "imu0" in form else None
        name = _text(form, "name", required=False) or ""
        config = _json_object(_text(form, "config", required=False), "config")
        try:
            calibration = await run_in_threadpool(euroc_calibration, cam0, cam1)
            noise = None if imu0 is None else await run_in_threadpool(euroc_imu_noise, imu0)
        except ValueError as error:
            raise Refusal(422, str(error), "bad_session") from error
        return await run_in_threadpool(
            _create_session, state, owner, name[:200], calibration, config, noise
        )

    @app.post(
        "/v1/sessions/kitti", status_code=201, response_model=SessionOut, tags=["sessions"],
        openapi_extra=_MULTIPART_KITTI, responses=_ERRORS,
    )
    async def create_session_kitti(request: Request, owner: Owner, state: State) -> SessionOut:
        """Session from a KITTI ``calib.txt`` plus the image size."""
        form = await _form(request, max_files=1, max_fields=4)
        calib = await _file(form, "calib", MAX_CALIBRATION_FILE)
        width = _int_field(form, "width", 1, settings.max_image_width)
        height = _int_field(form, "height", 1, settings.max_image_height)
        name = _text(form, "name", required=False) or ""
        config = _json_object(_text(form, "config", required=False), "config")
        try:
            calibration = await run_in_threadpool(kitti_calibration, calib, (width, height))
        except ValueError as error:
            raise Refusal(422, str(error), "bad_session") from error
        return await run_in_threadpool(
            _create_session, state, owner, name[:200], calibration, config, None
        )

    @app.get("/v1/sessions", response_model=SessionList, tags=["sessions"], responses=_ERRORS)
    def list_sessions(owner: Owner, state: State) -> SessionList:
        return SessionList(sessions=[SessionOut.of(r) for r in state.store.list_sessions(owner)])

    @app.get(
        "/v1/sessions/{session_id}", response_model=SessionOut, tags=["sessions"],
        responses=_ERRORS,
    )
    def get_session(session_id: str, owner: Owner, state: State) -> SessionOut:
        return SessionOut.of(_lookup(state, session_id, owner))

    @app.delete(
        "/v1/sessions/{session_id}", status_code=204, tags=["sessions"], responses=_ERRORS
    )
    async def delete_session(session_id: str, owner: Owner, state: State) -> Response:
        await run_in_threadpool(_lookup, state, session_id, owner)
        await state.manager.remove(session_id)
        try:
            await run_in_threadpool(state.store.delete_session, session_id, owner)
        except Exception:
            state.manager.deleted.pop(session_id, None)  # still stored: a retry may delete it
            raise
        return Response(status_code=204)

    # -- frames and IMU

    @app.post(
        "/v1/sessions/{session_id}/frames", response_model=PoseOut, tags=["frames"],
        openapi_extra=_MULTIPART_FRAME, responses={**_ERRORS, 503: {"model": ErrorOut}},
    )
    async def post_frame(session_id: str, request: Request, owner: Owner, state: State) -> PoseOut:
        """Process one stereo pair; answers once its pose is stored."""
        record = await _lookup_async(state, session_id, owner)
        form = await _form(request, max_files=2, max_fields=2)
        left = await _file(form, "left")
        right = await _file(form, "right")
        timestamp_ns = _int_field(form, "timestamp_ns", 0, 2**63 - 1)
        imu_text = _text(form, "imu", required=False)
        imu = parse_imu(imu_text, settings) if imu_text and imu_text.strip() else None
        worker = _live(state, record)
        try:
            future = worker.submit(timestamp_ns, left, right, imu)
        except FrameRejected as error:
            raise Refusal(error.status_code, error.detail, error.kind) from error
        try:
            # Shielded: a client that hangs up does not cancel a frame already accepted.
            result = await asyncio.shield(future)
        except FrameRejected as error:  # counted by the session's consumer
            raise Refusal(error.status_code, error.detail, None) from error
        return PoseOut.of(
            result.session_id, result.record, result.imu_samples, result.odometry, result.smoothed
        )

    @app.post(
        "/v1/sessions/{session_id}/imu", response_model=ImuBatchOut, tags=["frames"],
        responses=_ERRORS,
    )
    async def post_imu(
        session_id: str, body: ImuBatchIn, owner: Owner, state: State
    ) -> ImuBatchOut:
        """Buffer IMU samples; each frame consumes those up to its timestamp."""
        record = await _lookup_async(state, session_id, owner)
        samples = parse_imu(body.model_dump(), settings)
        worker = _live(state, record)
        try:
            buffered = worker.add_imu(samples)
        except FrameRejected as error:
            raise Refusal(error.status_code, error.detail, error.kind) from error
        return ImuBatchOut(accepted=len(samples), buffered=buffered)

    # -- trajectory

    @app.get(
        "/v1/sessions/{session_id}/trajectory", tags=["sessions"],
        responses={**_ERRORS, 200: _TRAJECTORY_CONTENT}, response_model=TrajectoryOut,
    )
    def get_trajectory(
        session_id: str,
        owner: Owner,
        state: State,
        format: Annotated[Literal["tum", "kitti", "json"], Query()] = "json",
    ) -> Response:
        """All stored poses: TUM (``t x y z qx qy qz qw``), KITTI (3x4 rows) or JSON."""
        _lookup(state, session_id, owner)
        records = state.store.poses(session_id)
        if format == "json":
            body = TrajectoryOut(
                session_id=session_id, poses=[PoseOut.of(session_id, r) for r in records]
            )
            return JSONResponse(body.model_dump(mode="json"))
        return _trajectory_file(
            format,
            np.array([r.timestamp_ns for r in records], dtype=np.int64),
            np.array([r.pose for r in records], dtype=float).reshape(-1, 4, 4),
            f"{session_id}.{format}.txt",
        )

    @app.get(
        "/v1/sessions/{session_id}/smoothed", tags=["sessions"],
        responses={**_ERRORS, 200: _SMOOTHED_CONTENT}, response_model=SmoothedOut,
    )
    def get_smoothed(
        session_id: str,
        owner: Owner,
        state: State,
        format: Annotated[Literal["tum", "json"], Query()] = "json",
    ) -> Response:
        """The smoother's final poses handed out so far by the live session (left camera in
        world; each frame once, the newest 20000): the smoothed twin of ``/trajectory``. Not
        stored: empty for a session that is not live in this server."""
        _lookup(state, session_id, owner)
        worker = state.manager.workers.get(session_id)
        smoothed = list(worker.smoothed) if worker is not None else []
        if format == "json":
            body = SmoothedOut(
                session_id=session_id,
                poses=[SmoothedPose(timestamp_ns=t, pose=[p[0:4], p[4:8], p[8:12], p[12:16]])
                       for t, p in smoothed],
            )
            return JSONResponse(body.model_dump(mode="json"))
        return _trajectory_file(
            "tum",
            np.array([t for t, _ in smoothed], dtype=np.int64),
            np.array([p for _, p in smoothed], dtype=float).reshape(-1, 4, 4),
            f"{session_id}.smoothed.tum.txt",
        )

    # -- streaming

    @app.websocket("/v1/sessions/{session_id}/stream")
    async def stream(websocket: WebSocket, session_id: str) -> None:
        await StreamConnection(websocket, session_id).run()

    from service.web import install_web_view  # imports this module: not at the top

    install_web_view(app)
    return app


def _trajectory_file(
    format: Literal["tum", "kitti"], times: np.ndarray, poses: np.ndarray, filename: str
) -> PlainTextResponse:
    """Poses as a TUM or KITTI text download, written by the same writers as ``swarmvo run``."""
    from estimator.formats.trajectory_io import write_kitti, write_tum

    with tempfile.TemporaryDirectory(prefix="swarmvo-export-") as folder:
        path = Path(folder) / f"trajectory.{format}"
        if format == "tum":
            write_tum(path, times, poses)
        else:
            write_kitti(path, poses)
        text = path.read_text()
    return PlainTextResponse(
        text, headers={"content-disposition": f'attachment; filename="{filename}"'}
    )


# ----------------------------------------------------------------------------- WebSocket


class StreamConnection:
    """One WebSocket client: JSON headers + binary images in, pose messages out, in order.

    Memory is bounded twice: at most ``queue_size`` frames (with their images) wait per session,
    and at most ``MAX_UNSENT_REPLIES`` answers wait for a client that does not read them; beyond
    that this connection stops reading, so TCP flow control slows the producer.
    """

    def __init__(self, websocket: WebSocket, session_id: str) -> None:
        self.websocket = websocket
        self.session_id = session_id
        self.state: ServiceState = websocket.app.state.swarmvo
        self.settings = self.state.settings
        self.outbox: asyncio.Queue[Any] = asyncio.Queue()
        self.credit = asyncio.Semaphore(MAX_UNSENT_REPLIES)
        self.header: dict[str, Any] | None = None
        self.parts: list[bytes] = []
        self.received = 0
        self.sender: asyncio.Task[None] | None = None
        self.image_size = (0, 0)  # the session's (width, height), known once accepted
        # Set by terminate() (the session was deleted): close code and reason to send.
        self.ending: tuple[int, str] | None = None
        self.stop = asyncio.Event()

    def terminate(self, code: int, reason: str) -> None:
        """End this stream from outside: its loop stops reading and closes with ``code``."""
        if self.ending is None:
            self.ending = (code, reason)
        self.stop.set()
        if self.sender is not None:
            self.sender.cancel()

    async def _receive(self) -> Message | None:
        """The next client message, or None once the stream was terminated."""
        if self.stop.is_set():
            return None
        receive = asyncio.ensure_future(self.websocket.receive())
        stop = asyncio.ensure_future(self.stop.wait())
        await asyncio.wait({receive, stop}, return_when=asyncio.FIRST_COMPLETED)
        stop.cancel()
        if receive.done():
            return receive.result()
        receive.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await receive
        return None

    async def _deny(self, status: int, detail: str) -> None:
        self.state.metrics.errors.labels("auth" if status == 401 else "unknown_session").inc()
        await self.websocket.send_denial_response(JSONResponse({"detail": detail}, status))

    async def run(self) -> None:
        websocket = self.websocket
        try:
            token = bearer_token(websocket.headers.get("authorization"))
            token = token or websocket.query_params.get("token") or None
            owner = owner_for(token, self.settings)
        except AuthError as error:
            await self._deny(401, str(error))
            return
        try:
            record = await _lookup_async(self.state, self.session_id, owner)
            worker = _live(self.state, record)
            self.state.manager.attach(record.id, self)
        except (HTTPException, SessionGone) as error:
            await self._deny(404 if isinstance(error, SessionGone) else error.status_code,
                             str(error.detail))
            return
        try:
            await self._serve(record, worker)
        finally:
            self.state.manager.detach(record.id, self)

    async def _serve(self, record: SessionRecord, worker: SessionWorker) -> None:
        websocket = self.websocket
        await websocket.accept()
        self.image_size = (record.image_width, record.image_height)
        await websocket.send_json(
            {
                "type": "hello",
                "session_id": record.id,
                "next_index": worker.next_index,
                "last_timestamp_ns": worker.last_submitted_ns,
                "queue_size": self.settings.queue_size,
                "queue_policy": self.settings.queue_policy,
            }
        )
        sender = asyncio.create_task(self._send_loop())
        self.sender = sender
        graceful = False
        try:
            while True:
                message = await self._receive()
                if message is None or message["type"] == "websocket.disconnect":
                    break
                if message.get("text") is not None:
                    if await self._on_text(message["text"], record):
                        graceful = True
                        break
                elif message.get("bytes") is not None:
                    await self._on_bytes(message["bytes"], record)
        except (WebSocketDisconnect, RuntimeError):
            pass
        finally:
            await self.outbox.put(None)
            if self.ending is not None:
                sender.cancel()
                await asyncio.wait({sender})
                with contextlib.suppress(Exception):
                    await websocket.close(*self.ending)
            elif graceful:
                with contextlib.suppress(Exception):
                    await asyncio.wait_for(sender, timeout=120)
                with contextlib.suppress(Exception):
                    await websocket.close(1000)
            else:
                # The client left: frames it sent are still processed and stored (the futures
                # are shielded), only the answers have nobody to go to.
                sender.cancel()
                await asyncio.wait({sender})

    async def _reply(self, payload: dict[str, Any]) -> None:
        await self._acquire_credit()
        self.outbox.put_nowait(payload)

    async def _on_text(self, text: str, record: SessionRecord) -> bool:
        try:
            message = json.loads(text)
        except json.JSONDecodeError as error:
            await self._reply({"type": "error", "detail": f"message is not valid JSON: {error}"})
            return False
        if not isinstance(message, dict):
            await self._reply({"type": "error", "detail": "messages must be JSON objects"})
            return False
        kind = message.get("type")
        if kind == "frame":
            await self._start_frame(message)
        elif kind == "imu":
            try:
                samples = parse_imu({"samples": message.get("samples")}, self.settings)
                _live(self.state, record).add_imu(samples)
            except HTTPException as error:
                await self._reply({"type": "error", "detail": str(error.detail)})
            except FrameRejected as error:
                await self._reply({"type": "error", "detail": error.detail})
        elif kind == "ping":
            await self._reply({"type": "pong"})
        elif kind == "close":
            return True
        else:
            await self._reply(
                {"type": "error", "detail": f"unknown message type {kind!r} (frame|imu|ping|close)"}
            )
        return False

    async def _start_frame(self, message: dict[str, Any]) -> None:
        if self.header is not None:
            await self._reply(
                {
                    "type": "error",
                    "detail": "a new frame header arrived before the images of the previous "
                    "one; the previous frame was discarded",
                }
            )
        self.header, self.parts, self.received = None, [], 0
        timestamp = message.get("timestamp_ns")
        sizes = (message.get("left_bytes"), message.get("right_bytes"))
        problem = None
        if not isinstance(timestamp, int) or isinstance(timestamp, bool):
            problem = "timestamp_ns must be an integer"
        elif not 0 <= timestamp < 2**63:
            problem = "timestamp_ns is out of range"
        elif not all(isinstance(n, int) and not isinstance(n, bool) and n > 0 for n in sizes):
            problem = "left_bytes and right_bytes must be positive integers"
        elif sum(sizes) > self.settings.ws_max_message_bytes:  # type: ignore[arg-type]
            problem = f"images exceed {self.settings.ws_max_message_bytes} bytes"
        else:
            problem = self._raw_problem(message, sizes)  # type: ignore[arg-type]
        imu = None
        if problem is None and message.get("imu") is not None:
            try:
                imu = parse_imu({"samples": message["imu"]}, self.settings)
            except HTTPException as error:
                problem = str(error.detail)
        if problem is not None:
            await self._reply(
                {
                    "type": "rejected",
                    "timestamp_ns": timestamp,
                    "status": 422,
                    "detail": f"bad frame header: {problem}",
                }
            )
            return
        self.header = {"timestamp_ns": timestamp, "sizes": sizes, "imu": imu,
                       "raw": message.get("encoding") == "raw8"}

    def _raw_problem(self, message: dict[str, Any], sizes: tuple[int, int]) -> str | None:
        """Check the optional ``encoding`` of a frame header (``png`` default, or ``raw8``)."""
        encoding = message.get("encoding", "png")
        if encoding in ("png", "jpeg", "image"):
            return None
        if encoding != "raw8":
            return f"unknown encoding {encoding!r} (png|raw8)"
        width, height = message.get("width"), message.get("height")
        if not all(isinstance(n, int) and not isinstance(n, bool) and n > 0
                   for n in (width, height)):
            return "raw8 frames need positive integer width and height"
        if (width, height) != self.image_size:
            return (f"raw8 image is {width}x{height} but the session's calibration is for "
                    f"{self.image_size[0]}x{self.image_size[1]}")
        if sizes != (width * height, width * height):
            return (f"raw8 left_bytes and right_bytes must both be width*height = "
                    f"{width * height}")
        return None

    async def _on_bytes(self, data: bytes, record: SessionRecord) -> None:
        if self.header is None:
            await self._reply(
                {"type": "error", "detail": "binary message without a preceding frame header"}
            )
            return
        self.parts.append(data)
        self.received += len(data)
        left_size, right_size = self.header["sizes"]
        expected = left_size + right_size
        if self.received < expected:
            return
        header, blob = self.header, b"".join(self.parts)
        self.header, self.parts, self.received = None, [], 0
        if len(blob) != expected:
            await self._reply(
                {
                    "type": "rejected",
                    "timestamp_ns": header["timestamp_ns"],
                    "status": 422,
                    "detail": f"expected {expected} image bytes, received {len(blob)}",
                }
            )
            return
        await self._acquire_credit()
        try:
            future = _live(self.state, record).submit(
                header["timestamp_ns"], blob[:left_size], blob[left_size:], header["imu"],
                raw=header["raw"],
            )
        except (FrameRejected, HTTPException) as error:
            refusal = error if isinstance(error, FrameRejected) else FrameRejected(
                error.status_code, str(error.detail), "unknown_session")
            self.state.metrics.errors.labels(refusal.kind).inc()
            self.outbox.put_nowait({"type": "rejected", "timestamp_ns": header["timestamp_ns"],
                                    "status": refusal.status_code, "detail": refusal.detail})
            return
        self.outbox.put_nowait((future, header["timestamp_ns"]))

    async def _acquire_credit(self) -> None:
        """Wait for room for one more unanswered frame, unless the sender has died."""
        assert self.sender is not None
        acquire = asyncio.ensure_future(self.credit.acquire())
        await asyncio.wait({acquire, self.sender}, return_when=asyncio.FIRST_COMPLETED)
        if not acquire.done():
            acquire.cancel()
            raise WebSocketDisconnect(1011)

    async def _send_loop(self) -> None:
        while True:
            item = await self.outbox.get()
            if item is None:
                return
            if isinstance(item, dict):
                await self.websocket.send_json(item)
                self.credit.release()
                continue
            future, timestamp = item
            try:
                result = await asyncio.shield(future)
                payload = {"type": "pose", **PoseOut.of(
                    result.session_id, result.record, result.imu_samples, result.odometry,
                    result.smoothed,
                ).model_dump(mode="json")}
            except FrameDropped as error:
                payload = {"type": "dropped", "timestamp_ns": timestamp, "detail": error.detail}
            except FrameRejected as error:
                payload = {"type": "rejected", "timestamp_ns": timestamp,
                           "status": error.status_code, "detail": error.detail}
            await self.websocket.send_json(payload)
            self.credit.release()
