"""Frames and IMU samples sent over REST: one stereo pair per request, answered with its pose;
and the end of a robot's stream (``finish``), which makes the smoothed poses final."""

from __future__ import annotations

import asyncio
import math

from fastapi import APIRouter, Request

from service.answer import FrameAnswer
from service.dependencies import ActiveSession, State, live_session
from service.errors import ERROR_RESPONSES, Refusal
from service.imu_input import imu_arrays, parse_imu
from service.multipart import BINARY, file_field, int_field, multipart_body, read_form, text_field
from service.schemas import ErrorOut, ImuBatchIn, ImuBatchOut, SmoothedOut
from service.sessions import FrameRejected, SessionGone

router = APIRouter(prefix="/v1/sessions/{session_id}", tags=["frames"])

_MULTIPART_FRAME = multipart_body(
    ["left", "right", "timestamp_ns"],
    {
        "left": BINARY,
        "right": BINARY,
        "timestamp_ns": {"type": "integer", "minimum": 0},
        "imu": {
            "type": "string",
            "description": 'JSON {"samples": [{"timestamp_ns", "gyro", '
            '"accel"}]}: IMU samples since the previous frame',
        },
    },
)


@router.post(
    "/frames", response_model=FrameAnswer, openapi_extra=_MULTIPART_FRAME,
    responses={**ERROR_RESPONSES, 503: {"model": ErrorOut}},
)
async def post_frame(record: ActiveSession, request: Request, state: State) -> FrameAnswer:
    """Process one stereo pair; answers once its pose is stored."""
    form = await read_form(request, max_files=2, max_fields=2)
    left = await file_field(form, "left")
    right = await file_field(form, "right")
    timestamp_ns = int_field(form, "timestamp_ns", 0, 2**63 - 1)
    imu_text = text_field(form, "imu", required=False)
    imu = parse_imu(imu_text, state.settings) if imu_text and imu_text.strip() else None
    live = live_session(state, record)
    try:
        future = live.submit(timestamp_ns, left, right, imu)
    except FrameRejected as error:
        raise frame_refusal(error, error.kind) from error
    try:
        # Shielded: a client that hangs up does not cancel a frame already accepted.
        answered = await asyncio.shield(future)
    except FrameRejected as error:  # counted by the session's consumer
        raise frame_refusal(error, None) from error
    return answered.answer


def frame_refusal(error: FrameRejected, kind: str | None) -> Refusal:
    """The HTTP answer to a refused frame; a passing 503 says when to retry (Retry-After)."""
    headers = None
    if error.retry_after_s is not None:
        headers = {"Retry-After": str(max(1, math.ceil(error.retry_after_s)))}
    return Refusal(error.status_code, error.detail, kind, headers)


@router.post("/imu", response_model=ImuBatchOut, responses=ERROR_RESPONSES)
async def post_imu(record: ActiveSession, body: ImuBatchIn, state: State) -> ImuBatchOut:
    """Buffer IMU samples; each frame consumes those up to its timestamp."""
    samples = imu_arrays(body.samples, state.settings)
    live = live_session(state, record)
    try:
        buffered = live.add_imu(samples)
    except FrameRejected as error:
        raise Refusal(error.status_code, error.detail, error.kind) from error
    return ImuBatchOut(accepted=len(samples), buffered=buffered)


@router.post("/finish", response_model=SmoothedOut, responses=ERROR_RESPONSES)
async def finish_stream(record: ActiveSession, state: State) -> SmoothedOut:
    """End of stream: once the frames sent so far are answered, the back end's window is
    flushed; its final poses are stored (``GET /smoothed`` then holds every frame) and
    returned, as a WebSocket's ``close`` message does. A frame sent later is processed too,
    by a pipeline resumed from the last stored pose."""
    try:
        flushed = await state.manager.finish(record.id)
    except SessionGone as error:
        raise Refusal(error.status_code, error.detail, error.kind) from error
    return SmoothedOut.of(record.id, flushed)
