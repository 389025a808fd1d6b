"""Replay input from a ROS bag: the stereo pair (and IMU) of a ROS 1 or ROS 2 bag.

The bag is read with the swarmvo package's own reader (``estimator.formats.rosbag_io``: topics,
encodings, stamps, calibration), so a bag replays exactly as ``swarmvo run BAG`` processes it:
each decoded image is sent as a lossless PNG (8 or 16 bit, grey or colour), which the server
decodes back to the same pixels, and the session is created from the same calibration.
Needs the ``swarmvo`` package (``pip install swarmvo``) beside the client.
"""

from __future__ import annotations

from dataclasses import asdict
from pathlib import Path
from typing import Any

from swarmvo_client.datasets import FrameFiles, LocalSequence
from swarmvo_client.models import ImuData


def is_bag(path: Path) -> bool:
    """A ROS 1 ``.bag`` file or a ROS 2 bag folder (``metadata.yaml``)."""
    path = Path(path)
    return (path.is_file() and path.suffix == ".bag") or (path / "metadata.yaml").is_file()


def open_local_bag(
    path: Path,
    calibration: Path,
    left_topic: str | None = None,
    right_topic: str | None = None,
    imu_topic: str | None = None,
    stereo_sync_tolerance_ms: float | None = None,
) -> LocalSequence:
    """A bag as a replay sequence: PNG-encoded frames, IMU, and the session's calibration.
    Left and right images pair as in ``swarmvo run`` (``--stereo-sync-tolerance``)."""
    if stereo_sync_tolerance_ms is not None and not stereo_sync_tolerance_ms >= 0:
        raise ValueError(
            f"--stereo-sync-tolerance must be >= 0 ms, got {stereo_sync_tolerance_ms}"
        )
    tolerance = None if stereo_sync_tolerance_ms is None else round(stereo_sync_tolerance_ms * 1e6)
    try:
        import cv2

        from estimator.formats.bag_calibration import load_bag_calibration
        from estimator.formats.rosbag_io import open_bag
    except ImportError as error:
        raise ValueError(
            f"replaying a bag needs the swarmvo package beside the client ({error})"
        ) from error
    rig_calibration = load_bag_calibration(calibration)
    bag = open_bag(path, rig_calibration, left_topic, right_topic, imu_topic, tolerance)

    def encode(index: int) -> tuple[bytes, bytes]:
        frame = bag.load(index)
        pair = []
        for image in (frame.left, frame.right):
            ok, data = cv2.imencode(".png", image)
            if not ok:
                raise ValueError(f"{path}: frame {index} cannot be encoded as PNG")
            pair.append(data.tobytes())
        return pair[0], pair[1]

    session: dict[str, Any] = {
        "calibration": rig_calibration.rig.to_dict(),
        "imu_noise": asdict(rig_calibration.imu_noise) if bag.imu is not None else None,
    }
    imu = None
    if bag.imu is not None:
        imu = ImuData(bag.imu.timestamps_ns, bag.imu.gyro, bag.imu.accel)
    return LocalSequence(
        kind="bag",  # type: ignore[arg-type]
        root=Path(path),
        frames=[FrameFiles(f.timestamp_ns, Path(path), Path(path)) for f in bag.frames],
        calibration_files={},
        image_size=rig_calibration.rig.size,
        imu=imu,
        frame_source=encode,
        session=session,
    )
