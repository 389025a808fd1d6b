"""Calibration file readers: EuRoC ``sensor.yaml``, KITTI ``calib.txt`` and the plain form.

Each turns a file into a validated :class:`~estimator.formats.calibration.StereoRig`; a
malformed file is a ``ValueError`` naming the file (a missing one ``FileNotFoundError``).
A rig whose calibration is its true geometry (``swarmvo synth``) says so in its files
(``calibration_exact: true`` in both EuRoC camera files, a ``calibration_exact: 1`` line in
KITTI's ``calib.txt``); without it a rig is taken to carry calibration errors.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import yaml

from estimator.formats.calibration import CameraModel, StereoRig

__all__ = [
    "load_euroc_rig",
    "load_kitti_rig",
    "load_rig",
    "pinhole_camera",
    "read_opencv_yaml",
]

_EUROC_MODEL_NAMES = {
    "radial-tangential": "radtan",
    "radtan": "radtan",
    "equidistant": "equidistant",
    "fisheye": "equidistant",
    "none": "none",
}


def read_opencv_yaml(path: Path) -> dict:
    """A YAML file that may start with OpenCV's ``%YAML:1.0`` line (PyYAML rejects it)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"file not found: {path}")
    lines = path.read_text().splitlines()
    if lines and lines[0].startswith("%YAML"):
        lines = lines[1:]
    try:
        data = yaml.safe_load("\n".join(lines))
    except yaml.YAMLError as error:
        raise ValueError(f"{path} is not valid YAML: {error}") from error
    if not isinstance(data, dict):
        raise ValueError(f"{path} does not hold a YAML mapping")
    return data


def pinhole_camera(entry: dict, coefficients_key: str, T_BS: np.ndarray) -> CameraModel:
    """A pinhole camera from a EuRoC / Kalibr style description (``resolution``, ``intrinsics``
    fu fv cu cv, ``distortion_model`` and its coefficients under ``coefficients_key``)."""
    if entry.get("camera_model", "pinhole") != "pinhole":
        raise ValueError(f"unsupported camera_model {entry['camera_model']!r}")
    model_name = str(entry.get("distortion_model", "none"))
    if model_name not in _EUROC_MODEL_NAMES:
        raise ValueError(f"unsupported distortion_model {model_name!r}")
    width, height = entry["resolution"]
    fu, fv, cu, cv = entry["intrinsics"]
    return CameraModel(
        width=width,
        height=height,
        fx=fu,
        fy=fv,
        cx=cu,
        cy=cv,
        distortion_model=_EUROC_MODEL_NAMES[model_name],  # type: ignore[arg-type]
        distortion=tuple(entry.get(coefficients_key, ())),
        T_BS=np.asarray(T_BS, dtype=float),
    )


def _euroc_camera(path: Path) -> tuple[CameraModel, bool]:
    """The camera of a EuRoC ``sensor.yaml`` and whether it declares its calibration exact."""
    data = read_opencv_yaml(path)
    exact = data.get("calibration_exact", False)
    if not isinstance(exact, bool):
        raise ValueError(f"{path}: calibration_exact must be true or false, got {exact!r}")
    try:
        transform = data["T_BS"]
        matrix = transform["data"] if isinstance(transform, dict) else transform
        return pinhole_camera(data, "distortion_coefficients", matrix), exact
    except (KeyError, TypeError) as error:
        raise ValueError(f"{path}: malformed EuRoC camera description ({error!r})") from error
    except ValueError as error:
        raise ValueError(f"{path}: {error}") from error


def load_euroc_rig(cam0_yaml: Path, cam1_yaml: Path) -> StereoRig:
    """Stereo rig from EuRoC/ASL ``cam0/sensor.yaml`` (left) and ``cam1/sensor.yaml`` (right);
    its calibration is exact when both files say so."""
    (left, left_exact), (right, right_exact) = _euroc_camera(cam0_yaml), _euroc_camera(cam1_yaml)
    return StereoRig(left=left, right=right, calibration_exact=left_exact and right_exact)


_KITTI_LEFT_LABELS = ("P0", "P_rect_00")
_KITTI_RIGHT_LABELS = ("P1", "P_rect_01")


def load_kitti_rig(calib_txt: Path, image_size: tuple[int, int]) -> StereoRig:
    """Stereo rig from a KITTI ``calib.txt``: rectified projections P0 (left) and P1 (right).

    Accepts labelled lines (``P0: 12 numbers``) or bare 12-number lines, where the first is the
    left and the second the right camera. KITTI images are already rectified and undistorted;
    P1[0, 3] = -fx * b gives the baseline. ``image_size`` is (width, height). A line
    ``calibration_exact: 1`` declares the calibration exact (0 or absent: not).
    """
    path = Path(calib_txt)
    if not path.is_file():
        raise FileNotFoundError(f"calibration file not found: {path}")
    labelled: dict[str, np.ndarray] = {}
    bare: list[np.ndarray] = []
    for number, line in enumerate(path.read_text().splitlines(), start=1):
        line = line.strip()
        if not line:
            continue
        label, _, values = line.rpartition(":") if ":" in line else ("", "", line)
        try:
            numbers = np.array([float(v) for v in values.split()])
        except ValueError as error:
            raise ValueError(f"{path}:{number}: not a list of numbers: {line[:60]!r}") from error
        if label:
            labelled[label.strip()] = numbers
        else:
            bare.append(numbers)
    left = next((labelled[k] for k in _KITTI_LEFT_LABELS if k in labelled), None)
    right = next((labelled[k] for k in _KITTI_RIGHT_LABELS if k in labelled), None)
    if left is None or right is None:
        if len(bare) < 2:
            raise ValueError(f"{path}: no P0/P1 projection matrices found")
        left, right = bare[0], bare[1]
    for name, projection in (("left", left), ("right", right)):
        if projection.size != 12:
            raise ValueError(f"{path}: {name} projection needs 12 numbers, got {projection.size}")
    p_left, p_right = left.reshape(3, 4), right.reshape(3, 4)
    width, height = image_size
    cameras = []
    for projection in (p_left, p_right):
        fx, fy, cx, cy = projection[0, 0], projection[1, 1], projection[0, 2], projection[1, 2]
        if fx <= 0:
            raise ValueError(f"{path}: non-positive focal length {fx}")
        # P = K [I | t] with t = (-fx * x_offset, 0, 0): the camera sits at +x_offset.
        body_from_camera = np.eye(4)
        body_from_camera[0, 3] = -projection[0, 3] / fx
        # Rectified and undistorted: a pinhole without distortion coefficients.
        entry = {"resolution": [width, height], "intrinsics": [fx, fy, cx, cy]}
        cameras.append(pinhole_camera(entry, "distortion_coefficients", body_from_camera))
    exact = labelled.get("calibration_exact", np.zeros(1))
    if exact.size != 1 or float(exact[0]) not in (0.0, 1.0):
        raise ValueError(f"{path}: calibration_exact must be 0 or 1, got {exact.tolist()}")
    return StereoRig(left=cameras[0], right=cameras[1], calibration_exact=bool(exact[0]))


def load_rig(path: Path) -> StereoRig:
    """Stereo rig from the plain JSON/YAML form written by :meth:`StereoRig.to_dict`."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"calibration file not found: {path}")
    if path.suffix.lower() == ".json":
        try:
            data = json.loads(path.read_text())
        except json.JSONDecodeError as error:
            raise ValueError(f"{path} is not valid JSON: {error}") from error
    else:
        data = read_opencv_yaml(path)
    try:
        return StereoRig.from_dict(data)
    except ValueError as error:
        raise ValueError(f"{path}: {error}") from error
