"""Sessions: create (JSON, EuRoC or KITTI calibration files), list, read and delete."""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter, Request, Response
from starlette.concurrency import run_in_threadpool

from service.dependencies import Owner, ServiceState, State, StoredSession
from service.errors import ERROR_RESPONSES, Refusal
from service.estimator_adapter import (
    euroc_calibration,
    euroc_frame_rate,
    euroc_imu_noise,
    kitti_calibration,
)
from service.limits import image_size_problems, work_limit_problems
from service.multipart import (
    BINARY,
    CONFIG_FIELD,
    MAX_CALIBRATION_FILE,
    file_field,
    int_field,
    json_object_field,
    multipart_body,
    rate_field,
    read_form,
    text_field,
)
from service.schemas import SessionCreate, SessionList, SessionOut

router = APIRouter(prefix="/v1/sessions", tags=["sessions"], responses=ERROR_RESPONSES)

_MULTIPART_EUROC = multipart_body(
    ["cam0", "cam1"],
    {"cam0": BINARY, "cam1": BINARY, "imu0": BINARY, "name": {"type": "string"},
     "config": CONFIG_FIELD},
)  # the frame rate is cam0/sensor.yaml's rate_hz
_MULTIPART_KITTI = multipart_body(
    ["calib", "width", "height"],
    {
        "calib": BINARY,
        "width": {"type": "integer", "minimum": 1},
        "height": {"type": "integer", "minimum": 1},
        "name": {"type": "string"},
        "config": CONFIG_FIELD,
        "frame_rate_hz": {"type": "number", "exclusiveMinimum": 0,
                          "description": "camera frame rate (else from the first two frames)"},
    },
)
# The most frames per second a session may declare.
MAX_FRAME_RATE_HZ = 10_000.0


def _create_session(
    state: ServiceState,
    owner: str,
    name: str,
    calibration: dict[str, Any],
    config: dict[str, Any],
    imu_noise: dict[str, Any] | None,
    frame_rate_hz: float | None = None,
) -> SessionOut:
    """Check the key's quota and the prepared session's limits, then store it."""
    if state.store.count_sessions(owner) >= state.settings.max_sessions_per_key:
        raise Refusal(
            429,
            f"session limit reached ({state.settings.max_sessions_per_key} per API key); "
            "delete sessions you no longer need",
            "too_many_sessions",
        )
    try:
        prepared = state.manager.runner.prepare_session(
            (calibration, config, imu_noise, frame_rate_hz))
        problems = work_limit_problems(prepared.config) + image_size_problems(
            prepared.image_size, state.settings
        )
        if problems:
            raise ValueError("; ".join(problems))
        state.manager.runner.check_session(prepared)
    except ValueError as error:
        raise Refusal(422, str(error), "bad_session") from error
    record = state.store.create_session(
        owner, name, prepared.calibration, prepared.config, prepared.imu_noise, prepared.image_size
    )
    return SessionOut.of(record)


@router.post("", status_code=201, response_model=SessionOut)
def create_session(body: SessionCreate, owner: Owner, state: State) -> SessionOut:
    noise = None if body.imu_noise is None else body.imu_noise.model_dump()
    return _create_session(state, owner, body.name, body.calibration, body.config, noise,
                           body.frame_rate_hz)


@router.post("/euroc", status_code=201, response_model=SessionOut, openapi_extra=_MULTIPART_EUROC)
async def create_session_euroc(request: Request, owner: Owner, state: State) -> SessionOut:
    """Session from EuRoC ``cam0/sensor.yaml``, ``cam1/sensor.yaml`` (and ``imu0``)."""
    form = await read_form(request, max_files=3, max_fields=2)
    cam0 = await file_field(form, "cam0", MAX_CALIBRATION_FILE)
    cam1 = await file_field(form, "cam1", MAX_CALIBRATION_FILE)
    imu0 = await file_field(form, "imu0", MAX_CALIBRATION_FILE) if "imu0" in form else None
    name = text_field(form, "name", required=False) or ""
    config = json_object_field(form, "config")
    try:
        # In a worker: reading the rig loads OpenCV and SciPy, which the server does without.
        call = state.manager.runner.call
        calibration = await run_in_threadpool(call, euroc_calibration, cam0, cam1)
        noise = None if imu0 is None else await run_in_threadpool(call, euroc_imu_noise, imu0)
        rate = await run_in_threadpool(call, euroc_frame_rate, cam0)
    except ValueError as error:
        raise Refusal(422, str(error), "bad_session") from error
    return await run_in_threadpool(
        _create_session, state, owner, name[:200], calibration, config, noise, rate
    )


@router.post("/kitti", status_code=201, response_model=SessionOut, openapi_extra=_MULTIPART_KITTI)
async def create_session_kitti(request: Request, owner: Owner, state: State) -> SessionOut:
    """Session from a KITTI ``calib.txt`` plus the image size."""
    form = await read_form(request, max_files=1, max_fields=5)
    calib = await file_field(form, "calib", MAX_CALIBRATION_FILE)
    width = int_field(form, "width", 1, state.settings.max_image_width)
    height = int_field(form, "height", 1, state.settings.max_image_height)
    name = text_field(form, "name", required=False) or ""
    config = json_object_field(form, "config")
    rate = rate_field(form, "frame_rate_hz", MAX_FRAME_RATE_HZ)
    try:
        calibration = await run_in_threadpool(
            state.manager.runner.call, kitti_calibration, calib, (width, height))
    except ValueError as error:
        raise Refusal(422, str(error), "bad_session") from error
    return await run_in_threadpool(
        _create_session, state, owner, name[:200], calibration, config, None, rate
    )


@router.get("", response_model=SessionList)
def list_sessions(owner: Owner, state: State) -> SessionList:
    return SessionList(sessions=[SessionOut.of(r) for r in state.store.list_sessions(owner)])


@router.get("/{session_id}", response_model=SessionOut)
def get_session(record: StoredSession) -> SessionOut:
    return SessionOut.of(record)


@router.delete("/{session_id}", status_code=204)
async def delete_session(record: StoredSession, owner: Owner, state: State) -> Response:
    await state.manager.remove(record.id)
    try:
        await run_in_threadpool(state.store.delete_session, record.id, owner)
    except Exception:
        state.manager.deleted.pop(record.id, None)  # still stored: a retry may delete it
        raise
    return Response(status_code=204)
