"""Writing ROS bags with ``rosbags``: the odometry result, and stereo recordings for tests.

``write_odometry_bag`` stores a run as nav_msgs/Odometry on ``/swarmvo/odometry`` (base_link in
odom, with covariances: ``estimator.formats.odometry_msg``) and geometry_msgs/PoseStamped on
``/swarmvo/camera_pose`` (the left-camera poses of ``trajectory.tum``, frame ``world``), each
message at its frame's stamp, which evo reads with ``evo_traj bag``/``bag2``. A path ending in
``.bag`` gives a ROS 1 bag, any other a ROS 2 bag folder (sqlite3 by default, or mcap).

``write_stereo_bag`` turns a dataset folder into a bag (images as sensor_msgs/Image or
CompressedImage, the IMU as sensor_msgs/Imu), which is how the bag reader is tested on the real
EuRoC clips.
"""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path
from typing import Literal

import cv2
import numpy as np
from rosbags.highlevel import AnyReader
from rosbags.rosbag1 import Writer as Ros1Writer
from rosbags.rosbag2 import StoragePlugin
from rosbags.rosbag2 import Writer as Ros2Writer
from rosbags.typesys import Stores, get_typestore

from estimator.formats.datasets import Sequence
from estimator.formats.odometry_msg import OdometryMessage
from estimator.geometry import make_pose, matrix_to_quat, quat_to_matrix
from estimator.types import ImuBatch

__all__ = [
    "CAMERA_POSE_TOPIC",
    "ODOMETRY_TOPIC",
    "read_pose_topic",
    "write_odometry_bag",
    "write_stereo_bag",
]

ODOMETRY_TOPIC = "/swarmvo/odometry"
CAMERA_POSE_TOPIC = "/swarmvo/camera_pose"
Storage = Literal["sqlite3", "mcap"]
ImageEncoding = Literal["mono8", "mono16", "bgr8", "png"]


class _BagWriter:
    """One writer for both ROS versions: connections by topic, messages serialised to fit."""

    def __init__(self, path: Path, storage: Storage = "sqlite3") -> None:
        self.path = Path(path)
        self.ros1 = self.path.suffix == ".bag"
        if self.path.exists():
            raise ValueError(f"{self.path} exists already; choose a new bag path")
        self.typestore = get_typestore(Stores.ROS1_NOETIC if self.ros1 else Stores.ROS2_HUMBLE)
        if self.ros1:
            self._writer = Ros1Writer(self.path)
        else:
            plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
            self._writer = Ros2Writer(self.path, version=9, storage_plugin=plugin)
        self._connections: dict[str, object] = {}

    def __enter__(self) -> _BagWriter:
        self._writer.open()
        return self

    def __exit__(self, *exc: object) -> None:
        self._writer.close()

    def type(self, name: str):
        return self.typestore.types[name]

    def header(self, stamp_ns: int, frame_id: str):
        seconds, nanoseconds = divmod(int(stamp_ns), 1_000_000_000)
        stamp = self.type("builtin_interfaces/msg/Time")(sec=seconds, nanosec=nanoseconds)
        fields = {"seq": 0} if self.ros1 else {}
        return self.type("std_msgs/msg/Header")(**fields, stamp=stamp, frame_id=frame_id)

    def write(self, topic: str, msgtype: str, stamp_ns: int, message: object) -> None:
        if topic not in self._connections:
            self._connections[topic] = self._writer.add_connection(
                topic, msgtype, typestore=self.typestore
            )
        serialize = self.typestore.serialize_ros1 if self.ros1 else self.typestore.serialize_cdr
        self._writer.write(self._connections[topic], int(stamp_ns), serialize(message, msgtype))


def _point(writer: _BagWriter, vector: np.ndarray):
    return writer.type("geometry_msgs/msg/Point")(x=vector[0], y=vector[1], z=vector[2])


def _vector3(writer: _BagWriter, vector: np.ndarray):
    return writer.type("geometry_msgs/msg/Vector3")(x=vector[0], y=vector[1], z=vector[2])


def _pose(writer: _BagWriter, pose: np.ndarray):
    w, x, y, z = (float(v) for v in matrix_to_quat(pose[:3, :3]))
    orientation = writer.type("geometry_msgs/msg/Quaternion")(x=x, y=y, z=z, w=w)
    return writer.type("geometry_msgs/msg/Pose")(
        position=_point(writer, pose[:3, 3]), orientation=orientation
    )


def write_odometry_bag(
    path: Path,
    messages: Iterable[OdometryMessage],
    camera_poses: Iterable[tuple[int, np.ndarray]],
    storage: Storage = "sqlite3",
) -> None:
    """The odometry messages and the left-camera poses (world frame) as a bag (module doc)."""
    with _BagWriter(path, storage) as writer:
        for message in messages:
            twist = writer.type("geometry_msgs/msg/Twist")(
                linear=_vector3(writer, message.linear_velocity),
                angular=_vector3(writer, message.angular_velocity),
            )
            odometry = writer.type("nav_msgs/msg/Odometry")(
                header=writer.header(message.stamp_ns, message.frame_id),
                child_frame_id=message.child_frame_id,
                pose=writer.type("geometry_msgs/msg/PoseWithCovariance")(
                    pose=_pose(writer, message.pose), covariance=message.pose_covariance.ravel()
                ),
                twist=writer.type("geometry_msgs/msg/TwistWithCovariance")(
                    twist=twist, covariance=message.twist_covariance.ravel()
                ),
            )
            writer.write(ODOMETRY_TOPIC, "nav_msgs/msg/Odometry", message.stamp_ns, odometry)
        for stamp_ns, pose in camera_poses:
            stamped = writer.type("geometry_msgs/msg/PoseStamped")(
                header=writer.header(stamp_ns, "world"), pose=_pose(writer, pose)
            )
            writer.write(CAMERA_POSE_TOPIC, "geometry_msgs/msg/PoseStamped", stamp_ns, stamped)


def read_pose_topic(path: Path, topic: str) -> tuple[np.ndarray, np.ndarray]:
    """(timestamps_ns, (N, 4, 4) poses) of a nav_msgs/Odometry or PoseStamped topic."""
    stamps, poses = [], []
    with AnyReader([Path(path)]) as reader:
        chosen = [c for c in reader.connections if c.topic == topic]
        if not chosen:
            raise ValueError(f"{path}: no topic {topic}")
        for connection, _, raw in reader.messages(connections=chosen):
            message = reader.deserialize(raw, connection.msgtype)
            pose = message.pose.pose if hasattr(message.pose, "pose") else message.pose
            q, p = pose.orientation, pose.position
            rotation = quat_to_matrix(np.array([q.w, q.x, q.y, q.z]))
            stamp = message.header.stamp
            stamps.append(int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec))
            poses.append(make_pose(rotation, np.array([p.x, p.y, p.z])))
    return np.array(stamps, dtype=np.int64), np.array(poses).reshape(-1, 4, 4)


def _image_message(writer: _BagWriter, image: np.ndarray, encoding: ImageEncoding, header):
    """sensor_msgs/Image (mono8, mono16 = grey x 257, bgr8 = grey x 3) or PNG CompressedImage."""
    if encoding == "png":
        ok, data = cv2.imencode(".png", image)
        assert ok
        return "sensor_msgs/msg/CompressedImage", writer.type("sensor_msgs/msg/CompressedImage")(
            header=header, format="png", data=np.asarray(data, dtype=np.uint8).ravel()
        )
    if encoding == "mono16":
        image = image.astype(np.uint16) * 257
    elif encoding == "bgr8":
        image = np.repeat(image[:, :, None], 3, axis=2)
    data = np.ascontiguousarray(image).view(np.uint8).ravel()
    height, width = image.shape[:2]
    return "sensor_msgs/msg/Image", writer.type("sensor_msgs/msg/Image")(
        header=header,
        height=height,
        width=width,
        encoding=encoding,
        is_bigendian=0,
        step=data.size // height,
        data=data,
    )


def write_stereo_bag(
    path: Path,
    sequence: Sequence,
    limit: int | None = None,
    encoding: ImageEncoding = "mono8",
    storage: Storage = "sqlite3",
    imu_before_ns: int = 200_000_000,
    topics: tuple[str, str, str] = ("/cam0/image_raw", "/cam1/image_raw", "/imu0"),
) -> None:
    """The first ``limit`` frames of a grey 8-bit sequence (and its IMU from ``imu_before_ns``
    before the first frame to the last one) as a bag, with EuRoC's topic names."""
    count = len(sequence) if limit is None else min(limit, len(sequence))
    left_topic, right_topic, imu_topic = topics
    stamps = sequence.timestamps_ns[:count]
    imu = sequence.imu_between(int(stamps[0]) - imu_before_ns, int(stamps[-1]))
    written = 0  # IMU samples written so far: the bag is written in time order
    with _BagWriter(path, storage) as writer:
        for index in range(count):
            frame = sequence.load(index)
            upto = int(np.searchsorted(imu.timestamps_ns, frame.timestamp_ns, side="right"))
            for sample in range(written, upto):
                _write_imu(writer, imu_topic, imu, sample)
            written = upto
            for topic, image, frame_id in (
                (left_topic, frame.left, "cam0"),
                (right_topic, frame.right, "cam1"),
            ):
                header = writer.header(frame.timestamp_ns, frame_id)
                msgtype, message = _image_message(writer, image, encoding, header)
                writer.write(topic, msgtype, frame.timestamp_ns, message)


def _write_imu(writer: _BagWriter, topic: str, imu: ImuBatch, sample: int) -> None:
    stamp = int(imu.timestamps_ns[sample])
    message = writer.type("sensor_msgs/msg/Imu")(
        header=writer.header(stamp, "imu0"),
        orientation=writer.type("geometry_msgs/msg/Quaternion")(x=0.0, y=0.0, z=0.0, w=1.0),
        orientation_covariance=np.array([-1.0] + [0.0] * 8),
        angular_velocity=_vector3(writer, imu.gyro[sample]),
        angular_velocity_covariance=np.zeros(9),
        linear_acceleration=_vector3(writer, imu.accel[sample]),
        linear_acceleration_covariance=np.zeros(9),
    )
    writer.write(topic, "sensor_msgs/msg/Imu", stamp, message)
