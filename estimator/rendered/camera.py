"""The ideal stereo rigs of the rendered sequences (EuRoC-, KITTI-, RealSense- and ZED-like).

Undistorted and exactly rectified: the right camera sits at +x of the left one; the body
frame is EuRoC's (cam0 -> body extrinsics of V1).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np

from estimator.geometry import make_pose


@dataclass(frozen=True)
class SimCamera:
    """An ideal (undistorted, exactly rectified) stereo pair: pinhole, right camera at +x."""

    width: int
    height: int
    f: float
    cx: float
    cy: float
    baseline: float

    def __getitem__(self, key: str) -> float:
        return getattr(self, key)

    def matrix(self) -> np.ndarray:
        return np.array([[self.f, 0.0, self.cx], [0.0, self.f, self.cy], [0.0, 0.0, 1.0]])


# EuRoC-like stereo camera, but ideal (undistorted) and exactly rectified.
CAMERA = SimCamera(width=752, height=480, f=458.0, cx=367.0, cy=248.0, baseline=0.11)
# KITTI-like (sequence 00 grey cameras): 1241x376, 718.856 px, 0.54 m baseline.
KITTI_CAMERA = SimCamera(width=1241, height=376, f=718.856, cx=607.1928, cy=185.2157, baseline=0.54)
# RealSense D435-like infrared pair at 848x480: about 87 degrees wide, a 5 cm baseline.
REALSENSE_CAMERA = SimCamera(width=848, height=480, f=425.0, cx=424.0, cy=240.0, baseline=0.05)
# ZED-like pair at 1280x720 (HD720): about 85 degrees wide, a 12 cm baseline.
ZED_CAMERA = SimCamera(width=1280, height=720, f=700.0, cx=640.0, cy=360.0, baseline=0.12)

CameraName = Literal["euroc", "kitti", "realsense", "zed"]
CAMERAS: dict[CameraName, SimCamera] = {
    "euroc": CAMERA,
    "kitti": KITTI_CAMERA,
    "realsense": REALSENSE_CAMERA,
    "zed": ZED_CAMERA,
}


def _euroc_cam0_T_BS() -> np.ndarray:
    """EuRoC V1 cam0 -> body extrinsics, projected onto SO(3) so it is exactly rigid."""
    rotation = np.array(
        [
            [0.0148655429818, -0.999880929698, 0.00414029679422],
            [0.999557249008, 0.0149672133247, 0.025715529948],
            [-0.0257744366974, 0.00375618835797, 0.999660727178],
        ]
    )
    u, _, vt = np.linalg.svd(rotation)
    return make_pose(u @ vt, [-0.0216401454975, -0.064676986768, 0.00981073058949])


T_BS_CAM0 = _euroc_cam0_T_BS()
T_CAM0_CAM1 = make_pose(np.eye(3), [CAMERA["baseline"], 0.0, 0.0])  # right camera at +x
T_BS_CAM1 = T_BS_CAM0 @ T_CAM0_CAM1
# Columns: the camera's x (right), y (down), z (forward) in the heading frame (x fwd, z up).
R_HEADING_CAM = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


def camera_matrix(camera: SimCamera = CAMERA) -> np.ndarray:
    return camera.matrix()
