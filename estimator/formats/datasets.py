"""Stereo sequences on disk: EuRoC/ASL and KITTI odometry folders behind one ``Sequence``.

A ``Sequence`` knows its calibration, its frame list (left/right image paths paired by
timestamp), its IMU stream and ground truth when the dataset has them, and loads images lazily
so a long sequence never sits in memory. Real recordings are ragged (a camera drops a frame, a
CSV lists an image that was never written): unpaired rows are skipped with a warning instead of
failing the whole run, while malformed files fail with the file and line that is wrong.
"""

from __future__ import annotations

import warnings
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np

from estimator.formats.calibration import StereoRig
from estimator.formats.calibration_files import load_euroc_rig, load_kitti_rig, read_opencv_yaml
from estimator.formats.png import decode_image
from estimator.types import ImuBatch, ImuNoise, StereoFrame

__all__ = [
    "FrameRecord",
    "GroundTruth",
    "Sequence",
    "detect_format",
    "euroc_root",
    "open_sequence",
    "read_euroc_ground_truth",
    "read_euroc_imu",
    "read_euroc_imu_noise",
]

DatasetFormat = Literal["euroc", "kitti"]
KITTI_IMAGE_DIRS = (("image_0", "image_1"), ("image_l", "image_r"))
KITTI_DEFAULT_RATE_HZ = 10.0
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".pgm", ".ppm", ".tif", ".tiff", ".bmp")


# ----------------------------------------------------------------------------- ground truth


@dataclass
class GroundTruth:
    """Body poses in the world frame at ground-truth timestamps (EuRoC: p_RS_R, q_RS)."""

    timestamps_ns: np.ndarray  # (K,) int64, strictly increasing
    poses: np.ndarray  # (K, 4, 4) body -> world
    velocities: np.ndarray | None = None  # (K, 3) world frame
    gyro_bias: np.ndarray | None = None  # (K, 3)
    accel_bias: np.ndarray | None = None  # (K, 3)

    def __post_init__(self) -> None:
        self.timestamps_ns = np.asarray(self.timestamps_ns, dtype=np.int64)
        self.poses = np.asarray(self.poses, dtype=float)
        if self.poses.shape != (len(self.timestamps_ns), 4, 4):
            raise ValueError(
                f"ground truth needs (K, 4, 4) poses for K timestamps, got {self.poses.shape} "
                f"for {len(self.timestamps_ns)}"
            )
        if len(self.timestamps_ns) == 0:
            raise ValueError("ground truth is empty")
        _check_increasing(self.timestamps_ns, "ground truth")

    def __len__(self) -> int:
        return len(self.timestamps_ns)

    def covers(self, timestamps_ns: np.ndarray) -> np.ndarray:
        """Mask of the timestamps inside the ground-truth time range (interpolation is valid)."""
        t = np.asarray(timestamps_ns, dtype=np.int64)
        return (t >= self.timestamps_ns[0]) & (t <= self.timestamps_ns[-1])

    def interpolate(self, timestamps_ns: np.ndarray) -> np.ndarray:
        """Poses at arbitrary times: linear in position, slerp in rotation, exact at GT rows."""
        t = np.atleast_1d(np.asarray(timestamps_ns, dtype=np.int64))
        if not self.covers(t).all():
            outside = t[~self.covers(t)]
            raise ValueError(
                f"{len(outside)} timestamp(s) outside the ground-truth range "
                f"[{self.timestamps_ns[0]}, {self.timestamps_ns[-1]}] ns (first: {outside[0]})"
            )
        # Relative times in seconds from the first row keep float64 precision at ns level.
        reference = self.timestamps_ns[0]
        gt_s = (self.timestamps_ns - reference) * 1e-9
        query_s = (t - reference) * 1e-9
        result = np.tile(np.eye(4), (len(t), 1, 1))
        result[:, :3, 3] = np.stack(
            [np.interp(query_s, gt_s, self.poses[:, :3, 3][:, axis]) for axis in range(3)], -1
        )
        if len(self.timestamps_ns) == 1:
            result[:, :3, :3] = self.poses[0, :3, :3]
        else:
            # Imported here: reading a rig or IMU noise (what the service's workers do) needs
            # no SciPy, and scipy.spatial costs a process about 25 MB.
            from scipy.spatial.transform import Rotation, Slerp

            slerp = Slerp(gt_s, Rotation.from_matrix(self.poses[:, :3, :3]))
            result[:, :3, :3] = slerp(query_s).as_matrix()
        # Where the query hits a row exactly, return that row untouched (no float round trip).
        index = np.searchsorted(self.timestamps_ns, t)
        index = np.clip(index, 0, len(self.timestamps_ns) - 1)
        exact = self.timestamps_ns[index] == t
        result[exact] = self.poses[index[exact]]
        return result


# ----------------------------------------------------------------------------- sequence


@dataclass
class FrameRecord:
    timestamp_ns: int
    left_path: Path
    right_path: Path


@dataclass
class Sequence:
    """A stereo sequence on disk: calibration, frames, and IMU / ground truth when present."""

    name: str
    format: DatasetFormat
    root: Path
    rig: StereoRig
    frames: list[FrameRecord]
    imu: ImuBatch | None = None
    imu_noise: ImuNoise | None = None
    ground_truth: GroundTruth | None = None
    # Stamps of pairs the camera CSVs list but whose image file is not on disk (not in
    # ``frames``): a run counts them as skipped, or stops on them when strict.
    missing_ns: list[int] = field(default_factory=list)

    def __len__(self) -> int:
        return len(self.frames)

    @property
    def timestamps_ns(self) -> np.ndarray:
        return np.array([frame.timestamp_ns for frame in self.frames], dtype=np.int64)

    def load(self, index: int) -> StereoFrame:
        """Read one stereo pair as stored (grey 8/16-bit stays 8/16-bit)."""
        if not -len(self.frames) <= index < len(self.frames):
            raise IndexError(f"frame {index} out of range for {len(self.frames)} frames")
        record = self.frames[index]
        return StereoFrame(
            timestamp_ns=record.timestamp_ns,
            left=_read_image(record.left_path),
            right=_read_image(record.right_path),
        )

    def __iter__(self) -> Iterator[StereoFrame]:
        for index in range(len(self.frames)):
            yield self.load(index)

    def imu_between(self, start_ns: int, end_ns: int) -> ImuBatch:
        """IMU samples with start_ns < t <= end_ns (empty when the sequence has no IMU)."""
        if self.imu is None:
            return ImuBatch.empty()
        return self.imu.between(start_ns, end_ns)


class UnreadableImageError(ValueError):
    """A frame's image file is missing or cannot be decoded (one bad file, not a bad dataset)."""


def _read_image(path: Path) -> np.ndarray:
    try:
        image = decode_image(path.read_bytes())
    except OSError:
        image = None
    if image is None:
        raise UnreadableImageError(f"cannot read image {path} (missing or not an image)")
    return image


# ----------------------------------------------------------------------------- detection


def euroc_root(path: Path) -> Path | None:
    """The ``mav0`` folder for a path to it or to the folder holding it; None otherwise."""
    path = Path(path)
    for candidate in (path / "mav0", path):
        if (candidate / "cam0").is_dir() and (candidate / "cam1").is_dir():
            return candidate
    return None


def _kitti_image_dirs(path: Path) -> tuple[Path, Path] | None:
    for left, right in KITTI_IMAGE_DIRS:
        if (path / left).is_dir() and (path / right).is_dir():
            return path / left, path / right
    return None


def detect_format(path: Path) -> DatasetFormat:
    """'euroc' for an ASL folder (``mav0/cam0``, ``mav0/cam1``), 'kitti' for an odometry one."""
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"dataset folder not found: {path}")
    if not path.is_dir():
        raise ValueError(f"dataset path is not a folder: {path}")
    if euroc_root(path) is not None:
        return "euroc"
    if _kitti_image_dirs(path) is not None or (path / "calib.txt").is_file():
        return "kitti"
    raise ValueError(
        f"cannot tell the dataset format of {path}: expected EuRoC/ASL (mav0/cam0 and "
        "mav0/cam1) or KITTI odometry (image_0 + image_1 or image_l + image_r, and calib.txt)"
    )


def open_sequence(
    path: Path, format: DatasetFormat | None = None, stereo_sync_tolerance_ns: int | None = None
) -> Sequence:
    """Open a EuRoC or KITTI sequence folder (format detected when not given).

    EuRoC's left and right rows pair by the nearest stamp within ``stereo_sync_tolerance_ns``
    (default: a tenth of the frame period); KITTI pairs by file name.
    """
    path = Path(path)
    if format is None:
        format = detect_format(path)
    elif not path.is_dir():
        raise FileNotFoundError(f"dataset folder not found: {path}")
    if format == "euroc":
        return _open_euroc(path, stereo_sync_tolerance_ns)
    if format == "kitti":
        return _open_kitti(path)
    raise ValueError(f"unknown dataset format {format!r}; expected 'euroc' or 'kitti'")


# ----------------------------------------------------------------------------- CSV parsing


def _check_increasing(timestamps: np.ndarray, what: str) -> None:
    steps = np.diff(timestamps)
    if (steps <= 0).any():
        row = int(np.flatnonzero(steps <= 0)[0]) + 1
        raise ValueError(
            f"{what}: timestamps must increase strictly, but entry {row} "
            f"({timestamps[row]}) follows {timestamps[row - 1]}"
        )


def _csv_rows(path: Path, min_columns: int) -> list[tuple[int, list[str]]]:
    """Non-comment rows of a CSV as (line number, fields), with at least ``min_columns``."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"file not found: {path}")
    rows = []
    with path.open() as handle:
        for number, line in enumerate(handle, start=1):
            line = line.strip()
            if not line or line.startswith("#"):
                continue
            fields = [field.strip() for field in line.split(",")]
            if len(fields) < min_columns:
                raise ValueError(
                    f"{path}:{number}: expected at least {min_columns} comma-separated values, "
                    f"got {len(fields)}: {line[:80]!r}"
                )
            rows.append((number, fields))
    return rows


def _numeric_table(path: Path, min_columns: int) -> tuple[np.ndarray, np.ndarray, int]:
    """(timestamps_ns int64, values float (N, C-1), C) from a numeric CSV; C = narrowest row."""
    rows = _csv_rows(path, min_columns)
    if not rows:
        raise ValueError(f"{path} has no data rows")
    columns = min(len(fields) for _, fields in rows)
    timestamps = np.empty(len(rows), dtype=np.int64)
    values = np.empty((len(rows), columns - 1))
    for i, (number, fields) in enumerate(rows):
        try:
            timestamps[i] = int(fields[0])
            values[i] = [float(v) for v in fields[1:columns]]
        except ValueError as error:
            raise ValueError(f"{path}:{number}: malformed value ({error})") from error
    if not np.isfinite(values).all():
        row = int(np.flatnonzero(~np.isfinite(values).all(axis=1))[0])
        raise ValueError(f"{path}:{rows[row][0]}: NaN or inf value")
    _check_increasing(timestamps, str(path))
    return timestamps, values, columns


def read_euroc_imu(csv: Path) -> ImuBatch:
    """EuRoC ``imu0/data.csv``: t [ns], gyro xyz [rad/s], accel xyz [m/s^2]."""
    timestamps, values, _ = _numeric_table(csv, 7)
    return ImuBatch(timestamps, values[:, 0:3].copy(), values[:, 3:6].copy())


def read_euroc_ground_truth(csv: Path) -> GroundTruth:
    """EuRoC ``state_groundtruth_estimate0/data.csv``: t, p, q (wxyz), [v, b_w, b_a]."""
    timestamps, values, columns = _numeric_table(csv, 8)
    quats_wxyz = values[:, 3:7]
    norms = np.linalg.norm(quats_wxyz, axis=1)
    if (norms < 1e-6).any():
        raise ValueError(f"{csv}: zero quaternion in row {int(np.argmax(norms < 1e-6)) + 1}")
    from scipy.spatial.transform import Rotation  # here: see GroundTruth.interpolate

    poses = np.tile(np.eye(4), (len(timestamps), 1, 1))
    poses[:, :3, :3] = Rotation.from_quat(quats_wxyz[:, [1, 2, 3, 0]]).as_matrix()
    poses[:, :3, 3] = values[:, 0:3]
    return GroundTruth(
        timestamps_ns=timestamps,
        poses=poses,
        velocities=values[:, 7:10].copy() if columns >= 11 else None,
        gyro_bias=values[:, 10:13].copy() if columns >= 14 else None,
        accel_bias=values[:, 13:16].copy() if columns >= 17 else None,
    )


def read_euroc_imu_noise(path: Path) -> ImuNoise:
    """IMU noise densities and random walks from EuRoC ``imu0/sensor.yaml``."""
    data = read_opencv_yaml(path)
    keys = {
        "gyro_noise_density": "gyroscope_noise_density",
        "gyro_random_walk": "gyroscope_random_walk",
        "accel_noise_density": "accelerometer_noise_density",
        "accel_random_walk": "accelerometer_random_walk",
        "rate_hz": "rate_hz",
    }
    missing = [yaml_key for yaml_key in keys.values() if yaml_key not in data]
    if missing:
        raise ValueError(f"{path}: missing IMU noise field(s): {', '.join(missing)}")
    try:
        values = {field: float(data[yaml_key]) for field, yaml_key in keys.items()}
    except (TypeError, ValueError) as error:
        raise ValueError(f"{path}: non-numeric IMU noise value ({error})") from error
    if any(v < 0 for v in values.values()) or values["rate_hz"] <= 0:
        raise ValueError(f"{path}: IMU noise values must be >= 0 and the rate > 0: {values}")
    return ImuNoise(**values)


# ----------------------------------------------------------------------------- EuRoC


def _read_camera_csv(csv: Path) -> dict[int, Path]:
    rows = _csv_rows(csv, 2)
    entries: dict[int, Path] = {}
    timestamps = []
    for number, fields in rows:
        try:
            timestamp = int(fields[0])
        except ValueError as error:
            raise ValueError(f"{csv}:{number}: malformed timestamp {fields[0]!r}") from error
        timestamps.append(timestamp)
        entries[timestamp] = csv.parent / "data" / fields[1]
    _check_increasing(np.array(timestamps, dtype=np.int64), str(csv))
    return entries


def _warn(message: str) -> None:
    warnings.warn(message, stacklevel=3)


def _pair_frames(
    left: dict[int, Path], right: dict[int, Path], where: Path, tolerance_ns: int | None = None
) -> tuple[list[FrameRecord], list[int]]:
    """Frames present in both cameras (stamps nearest each other within the tolerance, see
    ``estimator.formats.stereo_sync``) with both image files on disk, in time order; and the
    stamps of the pairs with an image file missing."""
    from estimator.formats.stereo_sync import pair_stamps

    pairing = pair_stamps(
        np.fromiter(left, np.int64, len(left)), np.fromiter(right, np.int64, len(right)),
        tolerance_ns,
    )
    if pairing.dropped:
        _warn(pairing.summary(str(where)))
    frames, missing = [], []
    for timestamp, partner in zip(
        pairing.left_ns.tolist(), pairing.right_ns.tolist(), strict=True
    ):
        if left[timestamp].is_file() and right[partner].is_file():
            frames.append(FrameRecord(timestamp, left[timestamp], right[partner]))
        else:
            missing.append(timestamp)
    if missing:
        _warn(
            f"{where}: skipping {len(missing)} stereo pair(s) whose image file is missing "
            f"(first at {missing[0]} ns)"
        )
    return frames, missing


def _open_euroc(path: Path, stereo_sync_tolerance_ns: int | None = None) -> Sequence:
    mav0 = euroc_root(path)
    if mav0 is None:
        raise FileNotFoundError(f"{path}: no EuRoC mav0/cam0 and mav0/cam1 folders")
    for camera in ("cam0", "cam1"):
        for name in ("data.csv", "sensor.yaml"):
            if not (mav0 / camera / name).is_file():
                raise FileNotFoundError(f"EuRoC file missing: {mav0 / camera / name}")
    rig = load_euroc_rig(mav0 / "cam0" / "sensor.yaml", mav0 / "cam1" / "sensor.yaml")
    frames, missing = _pair_frames(
        _read_camera_csv(mav0 / "cam0" / "data.csv"),
        _read_camera_csv(mav0 / "cam1" / "data.csv"),
        mav0,
        stereo_sync_tolerance_ns,
    )
    if not frames:
        raise ValueError(f"{mav0}: no stereo pair with both images on disk")
    imu = imu_noise = ground_truth = None
    if (mav0 / "imu0" / "data.csv").is_file():
        imu = read_euroc_imu(mav0 / "imu0" / "data.csv")
        if (mav0 / "imu0" / "sensor.yaml").is_file():
            imu_noise = read_euroc_imu_noise(mav0 / "imu0" / "sensor.yaml")
    gt_csv = mav0 / "state_groundtruth_estimate0" / "data.csv"
    if gt_csv.is_file():
        ground_truth = read_euroc_ground_truth(gt_csv)
    name = mav0.parent.name if mav0.name == "mav0" else mav0.name
    return Sequence(name, "euroc", mav0, rig, frames, imu, imu_noise, ground_truth, missing)


# ----------------------------------------------------------------------------- KITTI


def _image_files(folder: Path) -> list[Path]:
    return sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)


def _read_kitti_times(path: Path) -> np.ndarray:
    rows = []
    for number, line in enumerate(path.read_text().splitlines(), start=1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        try:
            rows.append(round(float(line.split()[0]) * 1e9))
        except ValueError as error:
            raise ValueError(f"{path}:{number}: malformed time {line[:40]!r}") from error
    timestamps = np.array(rows, dtype=np.int64)
    _check_increasing(timestamps, str(path))
    return timestamps


def _kitti_poses_file(path: Path) -> Path | None:
    """``poses.txt`` in the sequence folder, or KITTI's own ``poses/NN.txt`` beside sequences/."""
    for candidate in (path / "poses.txt", path.parent.parent / "poses" / f"{path.name}.txt"):
        if candidate.is_file():
            return candidate
    return None


def _open_kitti(path: Path) -> Sequence:
    # Imported here: trajectory_io has no reason to load for EuRoC-only use.
    from estimator.formats.trajectory_io import read_kitti

    dirs = _kitti_image_dirs(path)
    if dirs is None:
        raise FileNotFoundError(
            f"{path}: no KITTI image folders (image_0 + image_1, or image_l + image_r)"
        )
    calib = path / "calib.txt"
    if not calib.is_file():
        raise FileNotFoundError(f"KITTI calibration missing: {calib}")
    left_files, right_files = _image_files(dirs[0]), _image_files(dirs[1])
    right_by_name = {p.stem: p for p in right_files}
    unpaired = (
        len(left_files)
        + len(right_files)
        - 2 * len(set(right_by_name) & {p.stem for p in left_files})
    )
    if unpaired:
        _warn(f"{path}: skipping {unpaired} image(s) without a partner in the other camera")
    pairs = [(p, right_by_name[p.stem]) for p in left_files if p.stem in right_by_name]
    if not pairs:
        raise ValueError(f"{path}: no left/right image pairs with matching file names")
    first = _read_image(pairs[0][0])
    rig = load_kitti_rig(calib, (first.shape[1], first.shape[0]))
    all_left_stems = [p.stem for p in left_files]
    times_file = path / "times.txt"
    if times_file.is_file():
        times = _read_kitti_times(times_file)
        if len(times) != len(left_files):
            raise ValueError(
                f"{times_file} has {len(times)} entries but {dirs[0]} holds "
                f"{len(left_files)} images"
            )
    else:
        times = np.arange(len(left_files), dtype=np.int64) * round(1e9 / KITTI_DEFAULT_RATE_HZ)
    time_of = dict(zip(all_left_stems, times.tolist(), strict=True))
    frames = [FrameRecord(int(time_of[left.stem]), left, right) for left, right in pairs]
    ground_truth = None
    poses_file = _kitti_poses_file(path)
    if poses_file is not None:
        poses = read_kitti(poses_file)
        if len(poses) != len(left_files):
            raise ValueError(
                f"{poses_file} has {len(poses)} poses but {dirs[0]} holds {len(left_files)} images"
            )
        # KITTI poses are camera-0 poses; the body frame is camera 0 (T_BS = I).
        ground_truth = GroundTruth(times, poses)
    return Sequence(path.name, "kitti", path, rig, frames, None, None, ground_truth)
