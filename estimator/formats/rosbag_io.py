"""ROS bags without ROS: a stereo (+ IMU) recording in a bag as a ``Sequence``.

Reads ROS 1 ``.bag`` files and ROS 2 bag folders (sqlite3 or mcap storage) with the ``rosbags``
library. Left and right images (sensor_msgs/Image in mono8, mono16, bgr8, rgb8, or
sensor_msgs/CompressedImage) are paired by their header stamps, nearest within a tolerance
(``estimator.formats.stereo_sync``: cameras without a common trigger are stamped apart); the
IMU topic (sensor_msgs/Imu) becomes the sequence's IMU stream. Topics are guessed when the bag
holds one stereo pair (two image topics whose names tell left from right, e.g. ``cam0``/``cam1``
or ``left``/``right``) and one IMU; otherwise the error lists them.

Images stay in the bag and are decoded frame by frame while the run streams through it, so a
long recording never sits in memory. The calibration comes from elsewhere
(``estimator.formats.bag_calibration``): bags carry no camera model the pipeline can trust.
"""

from __future__ import annotations

import re
import warnings
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from rosbags.highlevel import AnyReader, AnyReaderError

from estimator.formats.bag_calibration import BagCalibration
from estimator.formats.datasets import FrameRecord, Sequence, UnreadableImageError
from estimator.formats.png import decode_image as decode_compressed
from estimator.formats.stereo_sync import pair_stamps
from estimator.types import ImuBatch, StereoFrame

__all__ = ["BagSequence", "BagTopics", "decode_image", "is_bag", "open_bag"]

IMAGE_TYPE = "sensor_msgs/msg/Image"
COMPRESSED_TYPE = "sensor_msgs/msg/CompressedImage"
IMU_TYPE = "sensor_msgs/msg/Imu"
# Raw encodings: (numpy dtype, channels); colour is handed on as BGR.
_ENCODINGS: dict[str, tuple[type, int]] = {
    "mono8": (np.uint8, 1),
    "8UC1": (np.uint8, 1),
    "mono16": (np.uint16, 1),
    "16UC1": (np.uint16, 1),
    "bgr8": (np.uint8, 3),
    "rgb8": (np.uint8, 3),
}
_LEFT = re.compile(r"left|cam0|camera0|image0|_l\b|/l/", re.IGNORECASE)
_RIGHT = re.compile(r"right|cam1|camera1|image1|_r\b|/r/", re.IGNORECASE)
# The library's own errors for a broken bag (truncated, bad index, unknown storage).
_BAG_ERRORS = (AnyReaderError, OSError, KeyError, ValueError, AssertionError, EOFError)


def is_bag(path: Path) -> bool:
    """A ROS 1 ``.bag`` file or a ROS 2 bag folder (``metadata.yaml``)."""
    path = Path(path)
    return (path.is_file() and path.suffix == ".bag") or (path / "metadata.yaml").is_file()


@dataclass(frozen=True)
class BagTopics:
    left: str
    right: str
    imu: str | None


def _stamp_ns(message: object) -> int:
    stamp = message.header.stamp  # type: ignore[attr-defined]
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def decode_image(message: object, msgtype: str, topic: str) -> np.ndarray:
    """Pixels of a sensor_msgs/Image or CompressedImage (grey stays grey, colour as BGR).

    An unknown encoding is a ValueError (the topic is unusable); one image whose data cannot be
    decoded is an ``UnreadableImageError`` (the run skips that frame, as for a broken file).
    """
    if msgtype == COMPRESSED_TYPE:
        data = bytes(message.data)  # type: ignore[attr-defined]
        image = decode_compressed(data) if data else None
        if image is None:
            fmt = message.format  # type: ignore[attr-defined]
            raise UnreadableImageError(f"{topic}: cannot decode a compressed image ({fmt!r})")
        return image
    encoding = str(message.encoding)  # type: ignore[attr-defined]
    if encoding not in _ENCODINGS:
        raise ValueError(
            f"{topic}: unsupported image encoding {encoding!r} "
            f"(supported: {', '.join(_ENCODINGS)}, or sensor_msgs/CompressedImage)"
        )
    dtype, channels = _ENCODINGS[encoding]
    height, width, step = (int(message.height), int(message.width), int(message.step))  # type: ignore[attr-defined]
    item = np.dtype(dtype).itemsize
    raw = np.asarray(message.data, dtype=np.uint8)  # type: ignore[attr-defined]
    if step < width * channels * item or raw.size < step * height:
        raise UnreadableImageError(
            f"{topic}: image data of {raw.size} bytes does not hold {width}x{height} "
            f"{encoding} with row step {step}"
        )
    rows = raw[: step * height].reshape(height, step)[:, : width * channels * item]
    order = ">" if message.is_bigendian else "<"  # type: ignore[attr-defined]
    image = rows.copy().view(np.dtype(dtype).newbyteorder(order)).astype(dtype)
    image = image.reshape(height, width, channels) if channels > 1 else image
    return image[:, :, ::-1].copy() if encoding == "rgb8" else image


def _guess_topics(
    connections: dict[str, str],
    left: str | None,
    right: str | None,
    imu: str | None,
    calibration: BagCalibration,
) -> BagTopics:
    """The stereo pair and IMU topics: given, from the calibration, or guessed when unique."""
    images = sorted(t for t, kind in connections.items() if kind in (IMAGE_TYPE, COMPRESSED_TYPE))
    imus = sorted(t for t, kind in connections.items() if kind == IMU_TYPE)
    listing = ", ".join(f"{t} ({kind})" for t, kind in sorted(connections.items())) or "none"
    left = left or calibration.left_topic
    right = right or calibration.right_topic
    if imu is None and connections.get(calibration.imu_topic or "") == IMU_TYPE:
        imu = calibration.imu_topic  # named by the IMU calibration and present
    if left is None or right is None:
        lefts = [t for t in images if _LEFT.search(t) and not _RIGHT.search(t)]
        rights = [t for t in images if _RIGHT.search(t) and not _LEFT.search(t)]
        if len(images) == 2 and len(lefts) == 1 and len(rights) == 1:
            left, right = left or lefts[0], right or rights[0]
        else:
            raise ValueError(
                f"cannot tell the stereo pair among the bag's image topics "
                f"({', '.join(images) or 'none'}): pass --left-topic and --right-topic. "
                f"Topics: {listing}"
            )
    for role, topic, kinds in (
        ("left", left, (IMAGE_TYPE, COMPRESSED_TYPE)),
        ("right", right, (IMAGE_TYPE, COMPRESSED_TYPE)),
        ("IMU", imu, (IMU_TYPE,)),
    ):
        if topic is not None and connections.get(topic) not in kinds:
            found = connections.get(topic, "not in the bag")
            raise ValueError(f"{role} topic {topic}: {found}; topics: {listing}")
    if imu is None and len(imus) > 1:
        raise ValueError(f"several IMU topics ({', '.join(imus)}): pass --imu-topic")
    return BagTopics(left, right, imu or (imus[0] if imus else None))


@dataclass
class BagSequence(Sequence):
    """A Sequence whose images are decoded from the bag as the run streams through it."""

    topics: BagTopics | None = None
    # Right image stamp of each frame (frames carry the left image's stamp).
    right_stamps: list[int] = field(default_factory=list)
    _stream: Iterator[tuple[int, StereoFrame | UnreadableImageError]] | None = field(
        default=None, repr=False
    )
    _next: int = 0

    def load(self, index: int) -> StereoFrame:
        if not 0 <= index < len(self.frames):
            raise IndexError(f"frame {index} out of range for {len(self.frames)} frames")
        if self._stream is None or index < self._next:
            self._stream, self._next = self._pairs(), 0
        for position, frame in self._stream:
            self._next = position + 1
            if position == index:
                if self._next == len(self.frames):
                    self.close()
                if isinstance(frame, UnreadableImageError):
                    raise frame
                return frame
        raise ValueError(f"{self.root}: frame {index} vanished from the bag while reading it")

    def close(self) -> None:
        """Stop streaming (closes the bag when a run ends before the last frame)."""
        if self._stream is not None:
            self._stream.close()  # type: ignore[attr-defined]
            self._stream = None

    def _pairs(self) -> Iterator[tuple[int, StereoFrame | UnreadableImageError]]:
        """(frame index, stereo pair or why it cannot be read) in time order, one pass."""
        assert self.topics is not None
        position = {
            self.topics.left: {frame.timestamp_ns: i for i, frame in enumerate(self.frames)},
            self.topics.right: {stamp: i for i, stamp in enumerate(self.right_stamps)},
        }
        pending: dict[int, dict[str, np.ndarray | UnreadableImageError]] = {}
        ready: dict[int, StereoFrame | UnreadableImageError] = {}
        wanted = 0
        side_of = {self.topics.left: "left", self.topics.right: "right"}
        with _reader(self.root) as reader:
            chosen = [c for c in reader.connections if c.topic in side_of]
            for connection, _, raw in _messages(reader, chosen, self.root):
                message = _deserialize(reader, raw, connection, self.root)
                index = position[connection.topic].get(_stamp_ns(message))
                if index is None:
                    continue
                sides = pending.setdefault(index, {})
                try:
                    image = decode_image(message, connection.msgtype, connection.topic)
                except UnreadableImageError as error:
                    image = error
                sides[side_of[connection.topic]] = image
                if len(sides) == 2:
                    del pending[index]
                    left, right = sides["left"], sides["right"]
                    broken = next(
                        (s for s in (left, right) if isinstance(s, UnreadableImageError)), None
                    )
                    stamp = self.frames[index].timestamp_ns
                    ready[index] = broken or StereoFrame(stamp, left, right)
                while wanted in ready:
                    yield wanted, ready.pop(wanted)
                    wanted += 1


@contextmanager
def _reader(path: Path) -> Iterator[AnyReader]:
    """An open reader; the library's errors on a broken bag become one ValueError line."""
    reader = AnyReader([Path(path)])
    try:
        reader.open()
    except _BAG_ERRORS as error:
        raise ValueError(f"cannot read the bag {path}: {error}") from error
    try:
        yield reader
    finally:
        reader.close()


def _messages(reader: AnyReader, connections: list, path: Path) -> Iterator[tuple]:
    try:
        yield from reader.messages(connections=connections)
    except _BAG_ERRORS as error:
        raise ValueError(f"cannot read the bag {path} (truncated or corrupt?): {error}") from error


def _deserialize(reader: AnyReader, raw: bytes, connection, path: Path) -> object:
    try:
        return reader.deserialize(raw, connection.msgtype)
    except Exception as error:  # the library raises plain errors on bad bytes
        message = f"{path}: a {connection.topic} message cannot be decoded: {error}"
        raise ValueError(message) from error


def _scan(path: Path, topics: BagTopics) -> tuple[dict[str, list[int]], ImuBatch | None]:
    """Header stamps of both image topics and the whole IMU stream, in one pass."""
    stamps: dict[str, list[int]] = {topics.left: [], topics.right: []}
    imu_rows: list[tuple[int, float, float, float, float, float, float]] = []
    with _reader(path) as reader:
        wanted = {topics.left, topics.right, topics.imu}
        chosen = [c for c in reader.connections if c.topic in wanted]
        for connection, _, raw in _messages(reader, chosen, path):
            message = _deserialize(reader, raw, connection, path)
            if connection.topic == topics.imu:
                w, a = message.angular_velocity, message.linear_acceleration  # type: ignore[attr-defined]
                imu_rows.append((_stamp_ns(message), w.x, w.y, w.z, a.x, a.y, a.z))
            else:
                stamps[connection.topic].append(_stamp_ns(message))
    imu = None
    if imu_rows:
        imu_rows.sort(key=lambda row: row[0])
        table = np.array([row[1:] for row in imu_rows], dtype=float)
        times = np.array([row[0] for row in imu_rows], dtype=np.int64)
        keep = np.concatenate([[True], np.diff(times) > 0])  # duplicate stamps: the first
        imu = ImuBatch(times[keep], table[keep, :3], table[keep, 3:])
    return stamps, imu


def open_bag(
    path: Path,
    calibration: BagCalibration,
    left_topic: str | None = None,
    right_topic: str | None = None,
    imu_topic: str | None = None,
    stereo_sync_tolerance_ns: int | None = None,
) -> BagSequence:
    """A stereo recording in a ROS 1 or ROS 2 bag as a Sequence (module doc).

    Left and right images pair when their stamps are nearest each other and at most
    ``stereo_sync_tolerance_ns`` apart (default: a tenth of the frame period).
    """
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"bag not found: {path}")
    if not is_bag(path):
        raise ValueError(f"{path} is neither a ROS 1 .bag file nor a ROS 2 bag folder")
    with _reader(path) as reader:
        connections = {c.topic: c.msgtype for c in reader.connections}
        is_ros1 = reader.is2 is False
    topics = _guess_topics(connections, left_topic, right_topic, imu_topic, calibration)
    stamps, imu = _scan(path, topics)
    pairing = pair_stamps(
        np.array(stamps[topics.left], dtype=np.int64),
        np.array(stamps[topics.right], dtype=np.int64),
        stereo_sync_tolerance_ns,
    )
    if not len(pairing.left_ns):
        raise ValueError(
            f"{path}: no left/right image pair within {pairing.tolerance_ns / 1e6:g} ms on "
            f"{topics.left} ({len(stamps[topics.left])} images) and {topics.right} "
            f"({len(stamps[topics.right])} images); see --stereo-sync-tolerance"
        )
    if pairing.dropped:
        warnings.warn(pairing.summary(str(path)), stacklevel=2)
    paired = pairing.left_ns.tolist()
    frames = [FrameRecord(stamp, path, path) for stamp in paired]
    name = path.stem if path.is_file() else path.name
    return BagSequence(
        name=name,
        format="rosbag1" if is_ros1 else "rosbag2",  # type: ignore[arg-type]
        root=path,
        rig=calibration.rig,
        frames=frames,
        imu=imu,
        imu_noise=calibration.imu_noise if imu is not None else None,
        ground_truth=None,
        topics=topics,
        right_stamps=pairing.right_ns.tolist(),
    )
