"""Replay a EuRoC or KITTI folder against a server (HTTP or WebSocket) with a progress bar.

The IMU samples sent with frame k are those with t_{k-1} < t <= t_k (with the first frame,
those of the 100 ms before it, for the server's gravity alignment), which is what an offline
``swarmvo run`` feeds the odometry, so a replay with the same seed reproduces the offline
trajectory.
"""

from __future__ import annotations

import asyncio
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from swarmvo_client.client import Client
from swarmvo_client.datasets import LocalSequence, open_local_sequence
from swarmvo_client.encoding import Encoding, raw8_pair
from swarmvo_client.evaluation import TrajectoryError, trajectory_error
from swarmvo_client.models import DroppedFrame, ImuData, Pose, RejectedFrame, Session
from swarmvo_client.stream import stream


@dataclass
class ReplayResult:
    session: Session
    poses: list[Pose]
    dropped: list[DroppedFrame] = field(default_factory=list)
    rejected: list[RejectedFrame] = field(default_factory=list)
    wall_time_s: float = 0.0
    error: TrajectoryError | None = None
    # The back end's final poses of the last frames, sent when the stream ended (WebSocket).
    final_smoothed: list[tuple[int, np.ndarray]] = field(default_factory=list)

    @property
    def timestamps_ns(self) -> np.ndarray:
        return np.array([p.timestamp_ns for p in self.poses], dtype=np.int64)

    @property
    def matrices(self) -> np.ndarray:
        return np.array([p.pose for p in self.poses], dtype=float).reshape(-1, 4, 4)


def create_session_for(
    client: Client, sequence: LocalSequence, config: dict[str, Any] | None, name: str = ""
) -> Session:
    """A session from the dataset's own calibration files, uploaded as they are."""
    if sequence.session is not None:  # a bag: the calibration it was opened with
        return client.create_session(
            sequence.session["calibration"], config, sequence.session["imu_noise"],
            name or sequence.root.name,
        )
    files = sequence.calibration_files
    if not name:
        name = sequence.root.parent.name if sequence.kind == "euroc" else sequence.root.name
    if sequence.kind == "euroc":
        return client.create_session_euroc(
            files["cam0"], files["cam1"], files.get("imu0"), config=config, name=name
        )
    width, height = sequence.image_size
    return client.create_session_kitti(files["calib"], width, height, config=config, name=name)


# Samples sent with the first frame: this window before it (as ``swarmvo run`` does).
FIRST_FRAME_IMU_WINDOW_NS = 100_000_000


def frame_imu(sequence: LocalSequence, index: int) -> ImuData | None:
    """The IMU samples to send with frame ``index`` (see the module doc)."""
    if sequence.imu is None:
        return None
    end = sequence.frames[index].timestamp_ns
    start = sequence.frames[index - 1].timestamp_ns if index else end - FIRST_FRAME_IMU_WINDOW_NS
    return sequence.imu.between(start, end)


def _frame_indices(sequence: LocalSequence, start: int, limit: int | None) -> range:
    end = len(sequence.frames) if limit is None else min(len(sequence.frames), start + limit)
    return range(start, end)


def replay_http(
    client: Client,
    session: Session,
    sequence: LocalSequence,
    start: int = 0,
    limit: int | None = None,
    progress: bool = True,
) -> ReplayResult:
    """Send frames one by one over HTTP; each answer arrives after its pose is stored."""
    result = ReplayResult(session, [])
    began = time.perf_counter()
    for index in tqdm(_frame_indices(sequence, start, limit), disable=not progress,
                      unit="frame", desc="replay (HTTP)"):
        left, right = sequence.frame_bytes(index)
        result.poses.append(
            client.send_frame(
                session.id,
                sequence.frames[index].timestamp_ns,
                left,
                right,
                frame_imu(sequence, index),
            )
        )
    result.wall_time_s = time.perf_counter() - began
    return result


async def replay_ws(
    url: str,
    api_key: str | None,
    session: Session,
    sequence: LocalSequence,
    start: int = 0,
    limit: int | None = None,
    progress: bool = True,
    rate_hz: float | None = None,
    window: int = 4,
    encoding: Encoding = "raw8",
) -> ReplayResult:
    """Stream frames over the WebSocket, at most ``window`` unanswered (or paced at rate_hz).

    ``raw8`` sends 8-bit grey PNG pairs as raw pixels, decoded here instead of on the server
    (see :mod:`swarmvo_client.encoding`); ``file`` sends the image files as stored.
    """
    result = ReplayResult(session, [])
    indices = list(_frame_indices(sequence, start, limit))
    began = time.perf_counter()
    bar = tqdm(total=len(indices), disable=not progress, unit="frame", desc="replay (WS)")
    async with stream(url, session.id, api_key) as connection:
        in_flight = asyncio.Semaphore(window)

        async def produce() -> None:
            for position, index in enumerate(indices):
                if rate_hz:
                    delay = began + position / rate_hz - time.perf_counter()
                    if delay > 0:
                        await asyncio.sleep(delay)
                else:
                    await in_flight.acquire()
                left, right = sequence.frame_bytes(index)
                timestamp, imu = sequence.frames[index].timestamp_ns, frame_imu(sequence, index)
                raw = raw8_pair(left, right) if encoding == "raw8" else None
                if raw is None:
                    await connection.send_frame(timestamp, left, right, imu)
                else:
                    await connection.send_raw_frame(timestamp, *raw, imu)

        producer = asyncio.create_task(produce())
        try:
            for _ in indices:
                event = await connection.recv()
                if not rate_hz:
                    in_flight.release()
                if isinstance(event, Pose):
                    result.poses.append(event)
                elif isinstance(event, DroppedFrame):
                    result.dropped.append(event)
                else:
                    result.rejected.append(event)
                bar.update()
            await producer
        finally:
            producer.cancel()
            bar.close()
        result.final_smoothed = await connection.finish()
    result.wall_time_s = time.perf_counter() - began
    return result


def replay(
    url: str,
    dataset: str | Path,
    api_key: str | None = None,
    use_ws: bool = False,
    limit: int | None = None,
    config: dict[str, Any] | None = None,
    progress: bool = True,
    session_id: str | None = None,
    bag: dict[str, Any] | None = None,
    encoding: Encoding = "raw8",
) -> ReplayResult:
    """Create a session from the dataset (or continue ``session_id``) and replay its frames.

    Over the WebSocket, ``encoding`` says how the images travel (:func:`replay_ws`); HTTP
    uploads are always the files as stored.

    Continuing a session starts with the first frame newer than its last stored timestamp.
    A ROS bag needs ``bag={"calibration": path, "left_topic": ..., ...}`` (``bags.py``).
    """
    from swarmvo_client.bags import is_bag, open_local_bag

    if is_bag(Path(dataset)):
        options = dict(bag or {})
        if options.get("calibration") is None:
            raise ValueError("replaying a bag needs --calibration (EuRoC folder, Kalibr or rig)")
        sequence = open_local_bag(Path(dataset), **options)
    else:
        if (bag or {}).get("stereo_sync_tolerance_ms") is not None:
            raise ValueError("--stereo-sync-tolerance is for bags (folders pair equal stamps)")
        sequence = open_local_sequence(dataset)
    with Client(url, api_key) as client:
        if session_id is None:
            session = create_session_for(client, sequence, config)
            start = 0
        else:
            session = client.get_session(session_id)
            last = session.last_timestamp_ns
            start = next(
                (i for i, f in enumerate(sequence.frames) if last is None or f.timestamp_ns > last),
                len(sequence.frames),
            )
        if use_ws:
            result = asyncio.run(
                replay_ws(url, api_key, session, sequence, start, limit, progress,
                          encoding=encoding)
            )
        else:
            result = replay_http(client, session, sequence, start, limit, progress)
    result.error = evaluate(sequence, result.session, result.poses)
    return result


def evaluate(
    sequence: LocalSequence, session: Session, poses: list[Pose]
) -> TrajectoryError | None:
    """ATE of the left-camera positions against the ground truth moved to the left camera.

    Ground truth describes the body (EuRoC) frame; the camera sits ``T_BS`` away from it, so
    the reference position is p_WB + R_WB t_BS with t_BS from the session's calibration.
    """
    if sequence.gt_positions is None or sequence.gt_timestamps_ns is None or not poses:
        return None
    reference = sequence.gt_positions
    lever = np.asarray(session.calibration["left"]["T_BS"], dtype=float)[:3, 3]
    if sequence.gt_rotations is not None:
        reference = reference + np.einsum("nij,j->ni", sequence.gt_rotations, lever)
    timestamps = np.array([p.timestamp_ns for p in poses], dtype=np.int64)
    positions = np.array([p.pose[:3, 3] for p in poses], dtype=float)
    return trajectory_error(timestamps, positions, sequence.gt_timestamps_ns, reference)


def format_seconds(timestamp_ns: int) -> str:
    """Nanoseconds as seconds with nine exact decimals (no float rounding)."""
    sign = "-" if timestamp_ns < 0 else ""
    seconds, nanos = divmod(abs(int(timestamp_ns)), 1_000_000_000)
    return f"{sign}{seconds}.{nanos:09d}"


def write_tum(path: str | Path, timestamps_ns: np.ndarray, poses: np.ndarray) -> None:
    """``t x y z qx qy qz qw`` lines of the acknowledged poses."""
    lines = ["# timestamp tx ty tz qx qy qz qw"]
    for timestamp, pose in zip(timestamps_ns, poses, strict=True):
        w, x, y, z = _quaternion(pose[:3, :3])
        px, py, pz = pose[:3, 3]
        lines.append(
            f"{format_seconds(int(timestamp))} {px:.17g} {py:.17g} {pz:.17g} "
            f"{x:.17g} {y:.17g} {z:.17g} {w:.17g}"
        )
    Path(path).write_text("\n".join(lines) + "\n")


def _quaternion(rotation: np.ndarray) -> tuple[float, float, float, float]:
    """Unit quaternion (w, x, y, z), w >= 0, of a rotation matrix (Shepperd's method)."""
    m = rotation
    trace = m[0, 0] + m[1, 1] + m[2, 2]
    candidates = [trace, m[0, 0], m[1, 1], m[2, 2]]
    k = int(np.argmax(candidates))
    if k == 0:
        s = 2.0 * np.sqrt(1.0 + trace)
        q = [0.25 * s, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s]
    elif k == 1:
        s = 2.0 * np.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2])
        q = [(m[2, 1] - m[1, 2]) / s, 0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s]
    elif k == 2:
        s = 2.0 * np.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2])
        q = [(m[0, 2] - m[2, 0]) / s, (m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s]
    else:
        s = 2.0 * np.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1])
        q = [(m[1, 0] - m[0, 1]) / s, (m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s]
    quat = np.array(q) / np.linalg.norm(q)
    if quat[0] < 0:
        quat = -quat
    return float(quat[0]), float(quat[1]), float(quat[2]), float(quat[3])
