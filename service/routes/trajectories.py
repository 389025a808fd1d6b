"""A session's poses as downloads: stored odometry (TUM, KITTI, JSON) and the smoother's poses."""

from __future__ import annotations

import tempfile
from pathlib import Path
from typing import Annotated, Any, Literal

import numpy as np
from fastapi import APIRouter, Query, Response
from fastapi.responses import JSONResponse, PlainTextResponse

from service.dependencies import State, StoredSession
from service.errors import ERROR_RESPONSES
from service.schemas import SmoothedOut, TrajectoryOut

# Listed with the session itself: a trajectory is a read of the session resource.
router = APIRouter(prefix="/v1/sessions/{session_id}", tags=["sessions"])

# format=json answers the response model (added by FastAPI); tum and kitti answer plain text.
_TRAJECTORY_CONTENT: dict[str, Any] = {
    "description": "JSON for format=json; text for format=tum (t x y z qx qy qz qw per line) "
    "and format=kitti (12 numbers of the 3x4 pose per line)",
    "content": {"text/plain": {"schema": {"type": "string"}}},
}


@router.get(
    "/trajectory", responses={**ERROR_RESPONSES, 200: _TRAJECTORY_CONTENT},
    response_model=TrajectoryOut,
)
def get_trajectory(
    record: StoredSession,
    state: State,
    format: Annotated[Literal["tum", "kitti", "json"], Query()] = "json",
) -> Response:
    """All stored poses: TUM (``t x y z qx qy qz qw``), KITTI (3x4 rows) or JSON."""
    records = state.store.poses(record.id)
    if format == "json":
        body = TrajectoryOut(session_id=record.id, poses=records)
        return JSONResponse(body.model_dump(mode="json"))
    return trajectory_file(
        format,
        np.array([r.timestamp_ns for r in records], dtype=np.int64),
        np.array([r.pose for r in records], dtype=float).reshape(-1, 4, 4),
        f"{record.id}.{format}.txt",
    )


@router.get(
    "/smoothed", responses={**ERROR_RESPONSES, 200: _TRAJECTORY_CONTENT},
    response_model=SmoothedOut,
)
def get_smoothed(
    record: StoredSession,
    state: State,
    format: Annotated[Literal["tum", "kitti", "json"], Query()] = "json",
) -> Response:
    """The smoother's final poses (left camera in world, each frame once, oldest first):
    the smoothed twin of ``/trajectory``, stored as the frames are finalised; the last
    frames follow when the session's stream ends (``close``, ``POST /finish``) or the
    session is unloaded."""
    smoothed = state.store.smoothed(record.id)
    if format == "json":
        return JSONResponse(SmoothedOut.of(record.id, smoothed).model_dump(mode="json"))
    return trajectory_file(
        format,
        np.array([t for t, _ in smoothed], dtype=np.int64),
        np.array([p for _, p in smoothed], dtype=float).reshape(-1, 4, 4),
        f"{record.id}.smoothed.{format}.txt",
    )


def trajectory_file(
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
