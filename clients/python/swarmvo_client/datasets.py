"""A small reader of EuRoC/ASL and KITTI folders: what a replay needs, nothing decoded.

Images are sent as the files hold them and calibration files are uploaded as they are, so the
server sees exactly what an offline run reads from disk.
"""

from __future__ import annotations

import struct
import warnings
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np

from swarmvo_client.models import ImuData

KITTI_IMAGE_DIRS = (("image_0", "image_1"), ("image_l", "image_r"))
KITTI_DEFAULT_RATE_HZ = 10.0


@dataclass(frozen=True)
class FrameFiles:
    timestamp_ns: int
    left: Path
    right: Path


@dataclass
class LocalSequence:
    kind: Literal["euroc", "kitti", "bag"]
    root: Path
    frames: list[FrameFiles]
    calibration_files: dict[str, Path]
    image_size: tuple[int, int]  # (width, height)
    imu: ImuData | None = None
    # Ground truth positions of the reference frame (EuRoC: body, KITTI: camera 0).
    gt_timestamps_ns: np.ndarray | None = None
    gt_positions: np.ndarray | None = None
    gt_rotations: np.ndarray | None = None  # (N, 3, 3) when the ground truth has attitude
    notes: list[str] = field(default_factory=list)
    # A bag: encoded (left, right) of frame i, and the session body (calibration, imu_noise).
    frame_source: Callable[[int], tuple[bytes, bytes]] | None = None
    session: dict[str, Any] | None = None

    def frame_bytes(self, index: int) -> tuple[bytes, bytes]:
        """The encoded left and right images of frame ``index``, as they are sent."""
        if self.frame_source is not None:
            return self.frame_source(index)
        files = self.frames[index]
        return files.left.read_bytes(), files.right.read_bytes()


def quat_to_matrix(wxyz: np.ndarray) -> np.ndarray:
    """Rotation matrices (N, 3, 3) of quaternions (N, 4) given as w, x, y, z."""
    q = wxyz / np.linalg.norm(wxyz, axis=1, keepdims=True)
    w, x, y, z = q.T
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
            np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
            np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
        ],
        axis=1,
    )


def png_size(path: Path) -> tuple[int, int]:
    """(width, height) from a PNG header, without decoding the image."""
    with open(path, "rb") as handle:
        head = handle.read(24)
    if len(head) < 24 or head[:8] != b"\x89PNG\r\n\x1a\n" or head[12:16] != b"IHDR":
        raise ValueError(f"{path} is not a PNG image")
    width, height = struct.unpack(">II", head[16:24])
    return int(width), int(height)


def _csv_rows(path: Path) -> list[list[str]]:
    rows = []
    for line in path.read_text().splitlines():
        line = line.strip()
        if line and not line.startswith("#"):
            rows.append([v.strip() for v in line.split(",")])
    return rows


def _euroc_root(path: Path) -> Path | None:
    for candidate in (path / "mav0", path):
        if (candidate / "cam0").is_dir() and (candidate / "cam1").is_dir():
            return candidate
    return None


def _camera_files(mav0: Path, camera: str) -> dict[int, Path]:
    return {
        int(row[0]): mav0 / camera / "data" / row[1]
        for row in _csv_rows(mav0 / camera / "data.csv")
    }


def _open_euroc(mav0: Path) -> LocalSequence:
    left, right = _camera_files(mav0, "cam0"), _camera_files(mav0, "cam1")
    frames, skipped = [], 0
    for timestamp in sorted(set(left) | set(right)):
        pair = (left.get(timestamp), right.get(timestamp))
        if pair[0] is not None and pair[1] is not None and pair[0].is_file() and pair[1].is_file():
            frames.append(FrameFiles(timestamp, pair[0], pair[1]))
        else:
            skipped += 1
    if not frames:
        raise ValueError(f"{mav0}: no stereo pair with both image files")
    sequence = LocalSequence(
        "euroc",
        mav0,
        frames,
        {"cam0": mav0 / "cam0" / "sensor.yaml", "cam1": mav0 / "cam1" / "sensor.yaml"},
        png_size(frames[0].left),
    )
    if skipped:
        sequence.notes.append(f"skipped {skipped} camera row(s) without a partner or a file")
    imu_csv = mav0 / "imu0" / "data.csv"
    if imu_csv.is_file():
        table = np.array([[float(v) for v in row[1:7]] for row in _csv_rows(imu_csv)])
        times = np.array([int(row[0]) for row in _csv_rows(imu_csv)], dtype=np.int64)
        sequence.imu = ImuData(times, table[:, 0:3], table[:, 3:6])
        if (mav0 / "imu0" / "sensor.yaml").is_file():
            sequence.calibration_files["imu0"] = mav0 / "imu0" / "sensor.yaml"
    gt_csv = mav0 / "state_groundtruth_estimate0" / "data.csv"
    if gt_csv.is_file():
        rows = _csv_rows(gt_csv)
        sequence.gt_timestamps_ns = np.array([int(r[0]) for r in rows], dtype=np.int64)
        sequence.gt_positions = np.array([[float(v) for v in r[1:4]] for r in rows])
        sequence.gt_rotations = quat_to_matrix(np.array([[float(v) for v in r[4:8]] for r in rows]))
    return sequence


def _open_kitti(path: Path) -> LocalSequence:
    dirs = next(
        ((path / a, path / b) for a, b in KITTI_IMAGE_DIRS if (path / a).is_dir()
         and (path / b).is_dir()),
        None,
    )
    if dirs is None or not (path / "calib.txt").is_file():
        raise ValueError(f"{path}: not a KITTI sequence (image_0/image_1 and calib.txt)")
    left_files = sorted(p for p in dirs[0].iterdir() if p.suffix.lower() == ".png")
    right_by_stem = {p.stem: p for p in dirs[1].iterdir() if p.suffix.lower() == ".png"}
    times_file = path / "times.txt"
    if times_file.is_file():
        times = [
            round(float(line.split()[0]) * 1e9)
            for line in times_file.read_text().splitlines()
            if line.strip() and not line.startswith("#")
        ]
    else:
        times = [i * round(1e9 / KITTI_DEFAULT_RATE_HZ) for i in range(len(left_files))]
    if len(times) != len(left_files):
        raise ValueError(f"{times_file} has {len(times)} entries for {len(left_files)} images")
    frames = [
        FrameFiles(int(t), p, right_by_stem[p.stem])
        for t, p in zip(times, left_files, strict=True)
        if p.stem in right_by_stem
    ]
    if not frames:
        raise ValueError(f"{path}: no left/right PNG pairs")
    sequence = LocalSequence(
        "kitti", path, frames, {"calib": path / "calib.txt"}, png_size(frames[0].left)
    )
    poses_file = path / "poses.txt"
    if poses_file.is_file():
        poses = np.array(
            [[float(v) for v in line.split()] for line in poses_file.read_text().splitlines()
             if line.strip()]
        )
        if len(poses) == len(times):
            sequence.gt_timestamps_ns = np.array(times, dtype=np.int64)
            sequence.gt_positions = poses[:, [3, 7, 11]]
            sequence.gt_rotations = poses.reshape(-1, 3, 4)[:, :, :3]
    return sequence


def open_local_sequence(path: str | Path) -> LocalSequence:
    """EuRoC/ASL (``mav0/cam0``, ``mav0/cam1``) or KITTI (``image_0``, ``calib.txt``)."""
    path = Path(path)
    if not path.is_dir():
        raise FileNotFoundError(f"dataset folder not found: {path}")
    mav0 = _euroc_root(path)
    sequence = _open_euroc(mav0) if mav0 is not None else _open_kitti(path)
    for note in sequence.notes:
        warnings.warn(f"{path}: {note}", stacklevel=2)
    return sequence
