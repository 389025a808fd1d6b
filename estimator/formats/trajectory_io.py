"""Trajectory files: TUM (``t x y z qx qy qz qw``) and KITTI (12 numbers per line).

TUM timestamps are written as seconds with exactly nine decimals, formatted from the integer
nanoseconds (never through a float), so a nanosecond timestamp survives the round trip; a
float64 second count would lose the last digits of a 19-digit EuRoC timestamp.
"""

from __future__ import annotations

from decimal import Decimal, InvalidOperation
from pathlib import Path

import numpy as np

from estimator.geometry import matrix_to_quat, quat_to_matrix

__all__ = [
    "format_seconds",
    "parse_seconds",
    "read_kitti",
    "read_tum",
    "write_kitti",
    "write_tum",
]


def format_seconds(timestamp_ns: int) -> str:
    """Integer nanoseconds as a decimal second string with nine exact decimals."""
    timestamp_ns = int(timestamp_ns)
    sign = "-" if timestamp_ns < 0 else ""
    seconds, nanoseconds = divmod(abs(timestamp_ns), 1_000_000_000)
    return f"{sign}{seconds}.{nanoseconds:09d}"


def parse_seconds(text: str) -> int:
    """Decimal second string -> integer nanoseconds, exactly (rounded at the ns digit)."""
    try:
        value = Decimal(text)
    except InvalidOperation as error:
        raise ValueError(f"not a timestamp: {text!r}") from error
    if not value.is_finite():
        raise ValueError(f"not a finite timestamp: {text!r}")
    return int((value * 1_000_000_000).to_integral_value())


def _check_poses(poses: np.ndarray) -> np.ndarray:
    poses = np.asarray(poses, dtype=float)
    if poses.ndim != 3 or poses.shape[1:] != (4, 4):
        raise ValueError(f"poses must be an (N, 4, 4) array, got shape {poses.shape}")
    if not np.isfinite(poses).all():
        raise ValueError("poses contain NaN or inf")
    return poses


def write_tum(path: Path, timestamps_ns: np.ndarray, poses: np.ndarray) -> None:
    """Write ``t x y z qx qy qz qw`` lines (TUM RGB-D benchmark format, quaternion xyzw)."""
    poses = _check_poses(poses)
    timestamps_ns = np.asarray(timestamps_ns, dtype=np.int64)
    if timestamps_ns.shape != (len(poses),):
        raise ValueError(f"{len(timestamps_ns)} timestamps for {len(poses)} poses")
    quats = matrix_to_quat(poses[:, :3, :3]) if len(poses) else np.zeros((0, 4))
    lines = ["# timestamp tx ty tz qx qy qz qw"]
    for t, pose, (w, x, y, z) in zip(timestamps_ns, poses, quats, strict=True):
        px, py, pz = pose[:3, 3]
        lines.append(
            f"{format_seconds(t)} {px:.17g} {py:.17g} {pz:.17g} {x:.17g} {y:.17g} {z:.17g} {w:.17g}"
        )
    Path(path).write_text("\n".join(lines) + "\n")


def _data_lines(path: Path) -> list[tuple[int, list[str]]]:
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"trajectory file not found: {path}")
    rows = []
    for number, line in enumerate(path.read_text().splitlines(), start=1):
        line = line.strip()
        if line and not line.startswith("#"):
            rows.append((number, line.replace(",", " ").split()))
    return rows


def read_tum(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Read a TUM trajectory -> (timestamps_ns (N,) int64, poses (N, 4, 4))."""
    timestamps, poses = [], []
    for number, fields in _data_lines(path):
        if len(fields) != 8:
            raise ValueError(f"{path}:{number}: expected 8 values (t x y z qx qy qz qw)")
        try:
            timestamps.append(parse_seconds(fields[0]))
            values = np.array([float(v) for v in fields[1:]])
        except ValueError as error:
            raise ValueError(f"{path}:{number}: {error}") from error
        quat = values[[6, 3, 4, 5]]  # wxyz
        if not np.isfinite(values).all() or np.linalg.norm(quat) < 1e-9:
            raise ValueError(f"{path}:{number}: non-finite value or zero quaternion")
        pose = np.eye(4)
        pose[:3, :3] = quat_to_matrix(quat)
        pose[:3, 3] = values[:3]
        poses.append(pose)
    return np.array(timestamps, dtype=np.int64), np.array(poses).reshape(-1, 4, 4)


def write_kitti(path: Path, poses: np.ndarray) -> None:
    """Write the top 3x4 block of each pose row-major, 12 numbers per line (KITTI odometry)."""
    poses = _check_poses(poses)
    lines = [" ".join(f"{v:.17g}" for v in pose[:3].reshape(12)) for pose in poses]
    Path(path).write_text("".join(line + "\n" for line in lines))


def read_kitti(path: Path) -> np.ndarray:
    """Read a KITTI pose file -> (N, 4, 4)."""
    poses = []
    for number, fields in _data_lines(path):
        if len(fields) != 12:
            raise ValueError(f"{path}:{number}: expected 12 numbers, got {len(fields)}")
        try:
            values = np.array([float(v) for v in fields])
        except ValueError as error:
            raise ValueError(f"{path}:{number}: {error}") from error
        if not np.isfinite(values).all():
            raise ValueError(f"{path}:{number}: non-finite value")
        pose = np.eye(4)
        pose[:3] = values.reshape(3, 4)
        poses.append(pose)
    return np.array(poses).reshape(-1, 4, 4)
