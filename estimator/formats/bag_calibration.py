"""Calibration for a bag: EuRoC ``sensor.yaml`` files, a Kalibr camchain, or the plain rig form.

A bag carries images but no camera model the pipeline can use, so ``swarmvo run BAG`` takes
``--calibration`` pointing to one of:

* a EuRoC/ASL folder (``mav0`` or the folder holding it) with ``cam0/sensor.yaml`` and
  ``cam1/sensor.yaml``, and ``imu0/sensor.yaml`` for the IMU noise when present;
* a Kalibr camchain YAML (``cam0``/``cam1`` with ``intrinsics``, ``distortion_coeffs``,
  ``distortion_model``, ``resolution``, ``T_cam_imu`` and/or ``T_cn_cnm1``, and ``rostopic``,
  which also names the image topics). Kalibr's IMU YAML beside it (``imu.yaml``, or
  ``imu-NAME.yaml`` for ``camchain-imucam-NAME.yaml``) gives the IMU noise densities, random
  walks and rate (``update_rate``), flat or under ``imu0``, and its ``rostopic`` the IMU topic;
* the rig's own JSON/YAML form (``StereoRig.to_dict``, as the service takes it).

Without an IMU noise file the IMU gets the default noise model (``ImuNoise()``, the ADIS16448
of the EuRoC MAV).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from estimator.formats.calibration import CameraModel, StereoRig
from estimator.formats.calibration_files import (
    load_euroc_rig,
    load_rig,
    pinhole_camera,
    read_opencv_yaml,
)
from estimator.formats.datasets import euroc_root, read_euroc_imu_noise
from estimator.geometry import invert_pose
from estimator.types import ImuNoise

__all__ = [
    "BagCalibration",
    "find_kalibr_imu",
    "load_bag_calibration",
    "load_kalibr_imu",
    "load_kalibr_rig",
]

# Kalibr IMU YAML keys -> ImuNoise fields (the same continuous-time units as EuRoC's).
_KALIBR_IMU_KEYS = {
    "gyro_noise_density": "gyroscope_noise_density",
    "gyro_random_walk": "gyroscope_random_walk",
    "accel_noise_density": "accelerometer_noise_density",
    "accel_random_walk": "accelerometer_random_walk",
    "rate_hz": "update_rate",
}

# Kalibr distortion model names -> the project's.
@dataclass(frozen=True)
class BagCalibration:
    rig: StereoRig
    imu_noise: ImuNoise
    left_topic: str | None = None  # from a Kalibr camchain's ``rostopic``
    right_topic: str | None = None
    imu_topic: str | None = None  # from a Kalibr IMU YAML's ``rostopic``
    imu_file: Path | None = None  # where the IMU noise was read (None: the default model)


def load_bag_calibration(path: Path) -> BagCalibration:
    """The calibration at ``path`` (module doc for the accepted forms)."""
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"calibration not found: {path}")
    if path.is_dir():
        mav0 = euroc_root(path)
        if mav0 is None:
            raise ValueError(f"{path}: no EuRoC cam0/ and cam1/ folders with sensor.yaml")
        rig = load_euroc_rig(mav0 / "cam0" / "sensor.yaml", mav0 / "cam1" / "sensor.yaml")
        noise_file = mav0 / "imu0" / "sensor.yaml"
        if noise_file.is_file():
            return BagCalibration(rig, read_euroc_imu_noise(noise_file), imu_file=noise_file)
        return BagCalibration(rig, ImuNoise())
    if path.suffix.lower() != ".json":
        data = read_opencv_yaml(path)
        if "cam0" in data and "cam1" in data:
            rig, topics = load_kalibr_rig(path)
            imu_file = find_kalibr_imu(path)
            if imu_file is None:
                return BagCalibration(rig, ImuNoise(), *topics)
            noise, imu_topic = load_kalibr_imu(imu_file)
            return BagCalibration(rig, noise, *topics, imu_topic, imu_file)
    return BagCalibration(load_rig(path), ImuNoise())


def load_kalibr_rig(path: Path) -> tuple[StereoRig, tuple[str | None, str | None]]:
    """Stereo rig (cam0 = left) and the image topics from a Kalibr camchain YAML.

    Kalibr gives ``T_cam_imu`` (IMU -> camera), so T_BS = T_cam_imu^-1; a camera without it
    is placed through ``T_cn_cnm1`` (previous camera -> this one), and a chain without any IMU
    puts the body at cam0.
    """
    data = read_opencv_yaml(path)
    cameras: list[CameraModel] = []
    topics: list[str | None] = []
    camera_from_body = np.eye(4)
    for name in ("cam0", "cam1"):
        entry = data.get(name)
        if not isinstance(entry, dict):
            raise ValueError(f"{path}: no {name} section")
        try:
            if "T_cam_imu" in entry:
                camera_from_body = np.asarray(entry["T_cam_imu"], dtype=float)
            elif name != "cam0":
                camera_from_body = np.asarray(entry["T_cn_cnm1"], dtype=float) @ camera_from_body
            body_from_camera = invert_pose(camera_from_body.reshape(4, 4))
            cameras.append(pinhole_camera(entry, "distortion_coeffs", body_from_camera))
        except (KeyError, TypeError) as error:
            raise ValueError(f"{path}: malformed Kalibr {name} ({error!r})") from error
        except ValueError as error:
            raise ValueError(f"{path}: {name}: {error}") from error
        topic = entry.get("rostopic")
        topics.append(str(topic) if topic else None)
    return StereoRig(left=cameras[0], right=cameras[1]), (topics[0], topics[1])


def find_kalibr_imu(camchain: Path) -> Path | None:
    """Kalibr's IMU YAML beside a camchain: ``imu-NAME.yaml`` for ``camchain-imucam-NAME.yaml``
    (as Kalibr names its results), else ``imu.yaml`` (its input); None when neither exists."""
    folder, name = camchain.parent, camchain.name
    candidates = [
        folder / ("imu-" + name.removeprefix(prefix))
        for prefix in ("camchain-imucam-", "camchain-")
        if name.startswith(prefix)
    ]
    candidates += [folder / "imu.yaml", folder / "imu.yml"]
    return next((c for c in candidates if c.is_file()), None)


def load_kalibr_imu(path: Path) -> tuple[ImuNoise, str | None]:
    """IMU noise (densities, random walks, rate) and topic from a Kalibr IMU YAML."""
    data = read_opencv_yaml(path)
    entry = data.get("imu0", data)
    if not isinstance(entry, dict):
        raise ValueError(f"{path}: imu0 is not a mapping")
    missing = [key for key in _KALIBR_IMU_KEYS.values() if key not in entry]
    if missing:
        raise ValueError(f"{path}: missing Kalibr IMU field(s): {', '.join(missing)}")
    try:
        values = {name: float(entry[key]) for name, key in _KALIBR_IMU_KEYS.items()}
    except (TypeError, ValueError) as error:
        raise ValueError(f"{path}: non-numeric Kalibr IMU value ({error})") from error
    if not all(np.isfinite(v) and v >= 0 for v in values.values()) or values["rate_hz"] <= 0:
        raise ValueError(f"{path}: IMU noise values must be finite and >= 0, the rate > 0")
    topic = entry.get("rostopic")
    return ImuNoise(**values), str(topic) if topic else None
