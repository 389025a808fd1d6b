"""Calibration readers, validation and stereo rectification."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from estimator.formats.calibration import CameraModel, StereoRig
from estimator.formats.calibration_files import load_euroc_rig, load_kitti_rig, load_rig
from estimator.geometry import make_pose, quat_to_matrix, rotation_vector_to_quat

KITTI_P0 = "7.188560e+02 0 6.071928e+02 0 0 7.188560e+02 1.852157e+02 0 0 0 1 0"
KITTI_P1 = "7.188560e+02 0 6.071928e+02 -3.861448e+02 0 7.188560e+02 1.852157e+02 0 0 0 1 0"


def _camera(**overrides) -> dict:
    camera = {
        "width": 640,
        "height": 480,
        "fx": 400.0,
        "fy": 400.0,
        "cx": 320.0,
        "cy": 240.0,
        "distortion_model": "radtan",
        "distortion": [-0.1, 0.01, 0.0, 0.0],
        "T_BS": np.eye(4).tolist(),
    }
    camera.update(overrides)
    return camera


def _rig_dict(baseline: float = 0.12, **right_overrides) -> dict:
    right_pose = make_pose(np.eye(3), [baseline, 0.0, 0.0]).tolist()
    return {"left": _camera(), "right": _camera(T_BS=right_pose, **right_overrides)}


def _euroc_rig(root: Path) -> StereoRig:
    mav = root / "mav0"
    return load_euroc_rig(mav / "cam0" / "sensor.yaml", mav / "cam1" / "sensor.yaml")


# ----------------------------------------------------------------------------- EuRoC


def test_euroc_calibration_loads(euroc_v101_micro: Path) -> None:
    rig = _euroc_rig(euroc_v101_micro)
    assert rig.size == (752, 480)
    assert rig.left.fx == pytest.approx(458.654)
    assert rig.right.cy == pytest.approx(255.238)
    assert rig.left.distortion_model == "radtan"
    assert len(rig.left.distortion) == 4
    assert rig.baseline == pytest.approx(0.110, abs=0.002)
    # The right camera sits to the right (+x) of the left one.
    assert rig.T_left_right[0, 3] > 0.1


def _subpixel_matches(left: np.ndarray, right: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    sift = cv2.SIFT_create(1500)
    kp_l, des_l = sift.detectAndCompute(left, None)
    kp_r, des_r = sift.detectAndCompute(right, None)
    matches = cv2.BFMatcher(cv2.NORM_L2, crossCheck=True).match(des_l, des_r)
    pts_l = np.array([kp_l[m.queryIdx].pt for m in matches])
    pts_r = np.array([kp_r[m.trainIdx].pt for m in matches])
    return pts_l, pts_r


def _row_errors(left: np.ndarray, right: np.ndarray) -> np.ndarray:
    """|y_l - y_r| of plausible stereo matches (positive disparity, loose row gate)."""
    pts_l, pts_r = _subpixel_matches(left, right)
    dy = pts_l[:, 1] - pts_r[:, 1]
    dx = pts_l[:, 0] - pts_r[:, 0]
    plausible = (np.abs(dy) < 10.0) & (dx > 0.0) & (dx < 150.0)
    return np.abs(dy[plausible])


def test_euroc_rectification_aligns_epipolar_rows(euroc_v101_micro: Path) -> None:
    rig = _euroc_rig(euroc_v101_micro)
    mav = euroc_v101_micro / "mav0"
    name = sorted((mav / "cam0" / "data").glob("*.png"))[10].name
    left = cv2.imread(str(mav / "cam0" / "data" / name), cv2.IMREAD_GRAYSCALE)
    right = cv2.imread(str(mav / "cam1" / "data" / name), cv2.IMREAD_GRAYSCALE)
    rect_left, rect_right = rig.rectification.rectify(left, right)
    rectified = _row_errors(rect_left, rect_right)
    raw = _row_errors(left, right)
    assert len(rectified) > 150
    assert np.median(rectified) < 0.5
    # The raw pair is far off, so the check above measures the rectification.
    assert len(raw) == 0 or np.median(raw) > 2.0


def test_euroc_rectified_geometry(euroc_v101_micro: Path) -> None:
    rect = _euroc_rig(euroc_v101_micro).rectification
    assert rect.baseline == pytest.approx(0.110, abs=0.002)
    assert 350.0 < rect.fx < 500.0
    np.testing.assert_allclose(rect.R_left @ rect.R_left.T, np.eye(3), atol=1e-9)
    assert rect.left_maps is not None and rect.left_maps[0].dtype == np.int16


# ----------------------------------------------------------------------------- KITTI


@pytest.mark.parametrize(
    "text",
    [
        f"P0: {KITTI_P0}\nP1: {KITTI_P1}\nP2: {KITTI_P0}\nTr: {KITTI_P0}\n",
        f"{KITTI_P0}\n{KITTI_P1}\n",
    ],
    ids=["labelled", "bare"],
)
def test_kitti_calibration_forms(tmp_path: Path, text: str) -> None:
    path = tmp_path / "calib.txt"
    path.write_text(text)
    rig = load_kitti_rig(path, (1241, 376))
    assert rig.baseline == pytest.approx(386.1448 / 718.856)
    assert rig.left.fx == pytest.approx(718.856)
    assert rig.left.distortion_model == "none"
    rect = rig.rectification
    # Already rectified: no remapping, identity rectifying rotation.
    assert rect.is_identity
    np.testing.assert_allclose(rect.R_left, np.eye(3))
    image = np.zeros((376, 1241), np.uint8)
    out_left, _ = rect.rectify(image, image)
    assert out_left is image


def test_kitti_rejects_short_projection(tmp_path: Path) -> None:
    path = tmp_path / "calib.txt"
    path.write_text("P0: 1 2 3\nP1: 4 5 6\n")
    with pytest.raises(ValueError, match="12 numbers"):
        load_kitti_rig(path, (100, 100))


def test_kitti_missing_file(tmp_path: Path) -> None:
    with pytest.raises(FileNotFoundError):
        load_kitti_rig(tmp_path / "absent.txt", (100, 100))


# ----------------------------------------------------------------------------- plain form


@pytest.mark.parametrize("suffix", [".json", ".yaml"])
def test_round_trip(tmp_path: Path, suffix: str) -> None:
    rig = StereoRig.from_dict(_rig_dict())
    path = tmp_path / f"rig{suffix}"
    dump = json.dumps if suffix == ".json" else yaml.safe_dump
    path.write_text(dump(rig.to_dict()))
    loaded = load_rig(path)
    assert loaded.to_dict() == rig.to_dict()
    np.testing.assert_array_equal(loaded.T_left_right, rig.T_left_right)


@pytest.mark.parametrize(
    ("model", "distortion"), [("radtan", [-0.1, 0.01, 0.0, 0.0]), ("equidistant", [0.01, 0, 0, 0])]
)
def test_rectification_of_synthetic_rig_is_consistent(model: str, distortion: list) -> None:
    """A rotated right camera: rectified projections must put a 3D point on one row."""
    rotation = quat_to_matrix(rotation_vector_to_quat(np.array([0.01, -0.02, 0.015])))
    right_pose = make_pose(rotation, [0.12, 0.004, -0.002]).tolist()
    camera = {"distortion_model": model, "distortion": distortion}
    rig = StereoRig.from_dict(
        {"left": _camera(**camera), "right": _camera(T_BS=right_pose, **camera)}
    )
    rect = rig.rectification
    assert rect.left_maps is not None and rect.left_maps[0].shape == (480, 640, 2)
    points = np.array([[0.3, -0.2, 2.0], [-0.5, 0.4, 5.0], [0.0, 0.0, 1.5]])
    # Points in the rectified left frame, seen by both rectified projections.
    rectified = points @ rect.R_left.T
    homogeneous = np.c_[rectified, np.ones(3)]
    left_px = homogeneous @ rect.P1.T
    right_px = homogeneous @ rect.P2.T
    left_px = left_px[:, :2] / left_px[:, 2:]
    right_px = right_px[:, :2] / right_px[:, 2:]
    np.testing.assert_allclose(left_px[:, 1], right_px[:, 1], atol=1e-9)
    depth = rect.fx * rect.baseline / (left_px[:, 0] - right_px[:, 0])
    np.testing.assert_allclose(depth, rectified[:, 2], rtol=1e-9)
    assert rect.baseline == pytest.approx(np.linalg.norm([0.12, 0.004, -0.002]))


# ----------------------------------------------------------------------------- validation


_RIGHT_ABOVE = make_pose(np.eye(3), [0.01, 0.1, 0.0]).tolist()  # a vertical pair


@pytest.mark.parametrize(
    ("rig", "message"),
    [
        (_rig_dict(width=320), "resolutions differ"),
        ({"left": _camera(width=0), "right": _camera()}, "width must be a positive"),
        ({"left": _camera(height=-5), "right": _camera()}, "height must be a positive"),
        ({"left": _camera(fx=0.0), "right": _camera()}, "focal lengths must be positive"),
        ({"left": _camera(fy=-3.0), "right": _camera()}, "focal lengths must be positive"),
        (_rig_dict(baseline=0.0), "baseline"),
        (_rig_dict(baseline=-0.12), r"to the left of the left one \(x = -0.120 m.*swapped"),
        (
            {"left": _camera(), "right": _camera(T_BS=_RIGHT_ABOVE)},
            "above or below the left one.*side-by-side",
        ),
        ({"left": _camera(cx=float("nan")), "right": _camera()}, "finite"),
        ({"left": _camera(distortion=[0.1, 0.2, 0.3]), "right": _camera()}, "coefficients"),
        (
            {"left": _camera(distortion_model="equidistant", distortion=[0.1]), "right": _camera()},
            "coefficients",
        ),
        ({"left": _camera(distortion=[0.1, np.inf, 0, 0]), "right": _camera()}, "finite"),
        ({"left": _camera(distortion_model="fancy"), "right": _camera()}, "distortion model"),
        (
            {"left": _camera(T_BS=(np.eye(4) * [1.0, 1.0, 1.1, 1.0]).tolist()), "right": _camera()},
            "not rigid",
        ),
        (
            {"left": _camera(T_BS=np.diag([1.0, 1.0, -1.0, 1.0]).tolist()), "right": _camera()},
            "proper rotation",
        ),
        ({"left": _camera(T_BS=[[1.0, 0.0], [0.0, 1.0]]), "right": _camera()}, "4x4"),
        (
            {
                "left": _camera(T_BS=make_pose(np.eye(3), [np.nan, 0, 0]).tolist()),
                "right": _camera(),
            },
            "NaN",
        ),
        ({"left": {"width": 10}, "right": _camera()}, "missing"),
        ({"left": _camera()}, "'left' and 'right'"),
    ],
)
def test_validation_errors(rig: dict, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        StereoRig.from_dict(rig)


def test_direct_construction_validates() -> None:
    with pytest.raises(ValueError, match="focal"):
        CameraModel(10, 10, -1.0, 1.0, 5.0, 5.0, "none", (), np.eye(4))


def test_load_rig_errors(tmp_path: Path) -> None:
    with pytest.raises(FileNotFoundError):
        load_rig(tmp_path / "missing.yaml")
    broken = tmp_path / "broken.json"
    broken.write_text("{not json")
    with pytest.raises(ValueError, match="not valid JSON"):
        load_rig(broken)
    bad = tmp_path / "bad.yaml"
    bad.write_text(yaml.safe_dump(_rig_dict(baseline=0.0)))
    with pytest.raises(ValueError, match="baseline"):
        load_rig(bad)


def test_euroc_reader_rejects_bad_file(tmp_path: Path) -> None:
    path = tmp_path / "sensor.yaml"
    path.write_text("%YAML:1.0\nresolution: [752, 480]\n")
    with pytest.raises(ValueError, match="malformed"):
        load_euroc_rig(path, path)
