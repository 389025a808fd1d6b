"""Stereo calibration: camera models, the stereo rig and its rectification.

The front end works on rectified images, where a 3D point appears on the same row in both
cameras and depth follows from the column difference alone (Z = f b / d). A validated
:class:`StereoRig` holds in :attr:`StereoRig.rectification` precomputed fixed-point remap
tables, so rectifying a frame costs two ``cv2.remap`` calls. The calibration file readers
(EuRoC ``sensor.yaml``, KITTI ``calib.txt``, the plain JSON/YAML form) that build it live in
``calibration_files.py``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property
from typing import Any, Literal

import cv2
import numpy as np

from estimator.geometry import invert_pose

__all__ = [
    "CameraModel",
    "Rectification",
    "StereoRig",
]

DistortionModel = Literal["radtan", "equidistant", "none"]

# Accepted coefficient counts per distortion model (radtan: k1 k2 p1 p2 [k3]).
_DISTORTION_LENGTHS: dict[str, tuple[int, ...]] = {
    "radtan": (4, 5),
    "equidistant": (4,),
    "none": (0,),
}
# Calibration files print T_BS with ~12 digits; a rotation further from orthonormal than this
# is a mistyped matrix, not rounding.
_RIGID_TOLERANCE = 1e-4


def _check_rigid(transform: np.ndarray, name: str) -> np.ndarray:
    """Validate a 4x4 rigid transform and return it as a read-only float array."""
    matrix = np.array(transform, dtype=float)
    if matrix.shape == (16,):
        matrix = matrix.reshape(4, 4)
    if matrix.shape != (4, 4):
        raise ValueError(f"{name} must be a 4x4 matrix, got shape {matrix.shape}")
    if not np.isfinite(matrix).all():
        raise ValueError(f"{name} contains NaN or inf")
    if not np.allclose(matrix[3], [0.0, 0.0, 0.0, 1.0], atol=_RIGID_TOLERANCE):
        raise ValueError(f"{name} last row must be [0, 0, 0, 1], got {matrix[3].tolist()}")
    rotation = matrix[:3, :3]
    orthogonality = float(np.abs(rotation.T @ rotation - np.eye(3)).max())
    if orthogonality > _RIGID_TOLERANCE:
        raise ValueError(
            f"{name} is not rigid: its rotation block deviates from orthonormal by "
            f"{orthogonality:.2e} (R^T R != I)"
        )
    determinant = float(np.linalg.det(rotation))
    if abs(determinant - 1.0) > _RIGID_TOLERANCE:
        raise ValueError(f"{name} is not a proper rotation (det = {determinant:.6f}, expected +1)")
    matrix.setflags(write=False)
    return matrix


@dataclass(frozen=True, eq=False)
class CameraModel:
    """One camera: pinhole intrinsics, lens distortion and its pose in the body frame."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    distortion_model: DistortionModel
    distortion: tuple[float, ...]
    T_BS: np.ndarray  # 4x4, camera -> body

    def __post_init__(self) -> None:
        for name in ("width", "height"):
            value = getattr(self, name)
            if isinstance(value, float) and value.is_integer():
                value = int(value)
            if not isinstance(value, int | np.integer) or isinstance(value, bool) or value <= 0:
                raise ValueError(f"camera {name} must be a positive integer, got {value!r}")
            object.__setattr__(self, name, int(value))
        for name in ("fx", "fy", "cx", "cy"):
            value = float(getattr(self, name))
            if not math.isfinite(value):
                raise ValueError(f"camera {name} must be finite, got {value}")
            object.__setattr__(self, name, value)
        if self.fx <= 0 or self.fy <= 0:
            raise ValueError(f"focal lengths must be positive, got fx={self.fx}, fy={self.fy}")
        if self.distortion_model not in _DISTORTION_LENGTHS:
            raise ValueError(
                f"unknown distortion model {self.distortion_model!r}; "
                f"expected one of {sorted(_DISTORTION_LENGTHS)}"
            )
        coefficients = tuple(float(c) for c in self.distortion)
        allowed = _DISTORTION_LENGTHS[self.distortion_model]
        if len(coefficients) not in allowed:
            raise ValueError(
                f"{self.distortion_model} distortion needs {' or '.join(map(str, allowed))} "
                f"coefficients, got {len(coefficients)}"
            )
        if not all(math.isfinite(c) for c in coefficients):
            raise ValueError(f"distortion coefficients must be finite, got {coefficients}")
        object.__setattr__(self, "distortion", coefficients)
        object.__setattr__(self, "T_BS", _check_rigid(self.T_BS, "T_BS"))

    @property
    def size(self) -> tuple[int, int]:
        """(width, height), the order OpenCV expects."""
        return self.width, self.height

    @property
    def K(self) -> np.ndarray:
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def D(self) -> np.ndarray:
        """Distortion coefficients as OpenCV wants them (zeros for an ideal pinhole)."""
        if self.distortion_model == "none":
            return np.zeros(4)
        return np.array(self.distortion, dtype=float)

    def to_dict(self) -> dict[str, Any]:
        return {
            "width": self.width,
            "height": self.height,
            "fx": self.fx,
            "fy": self.fy,
            "cx": self.cx,
            "cy": self.cy,
            "distortion_model": self.distortion_model,
            "distortion": list(self.distortion),
            "T_BS": self.T_BS.tolist(),
        }

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> CameraModel:
        if not isinstance(data, dict):
            raise ValueError(f"a camera must be a mapping, got {type(data).__name__}")
        required = ("width", "height", "fx", "fy", "cx", "cy", "T_BS")
        missing = [key for key in required if key not in data]
        if missing:
            raise ValueError(f"camera is missing field(s): {', '.join(missing)}")
        unknown = set(data) - {*required, "distortion_model", "distortion"}
        if unknown:
            raise ValueError(f"camera has unknown field(s): {', '.join(sorted(unknown))}")
        try:
            return cls(
                width=data["width"],
                height=data["height"],
                fx=float(data["fx"]),
                fy=float(data["fy"]),
                cx=float(data["cx"]),
                cy=float(data["cy"]),
                distortion_model=data.get("distortion_model", "none"),
                distortion=tuple(data.get("distortion", ())),
                T_BS=np.asarray(data["T_BS"], dtype=float),
            )
        except (TypeError, ValueError) as error:
            raise ValueError(f"invalid camera: {error}") from error


@dataclass(frozen=True, eq=False)
class Rectification:
    """Rectified stereo geometry plus the remap tables that produce it.

    In the rectified frame both cameras share intrinsics (fx = fy, cx, cy) and differ by a pure
    x translation of ``baseline``; ``R_left`` rotates original-left-camera coordinates into the
    rectified-left frame (OpenCV's R1).
    """

    size: tuple[int, int]  # (width, height)
    fx: float
    cx: float
    cy: float
    baseline: float
    R_left: np.ndarray
    R_right: np.ndarray
    P1: np.ndarray
    P2: np.ndarray
    Q: np.ndarray
    left_maps: tuple[np.ndarray, np.ndarray] | None  # None: images are already rectified
    right_maps: tuple[np.ndarray, np.ndarray] | None

    @property
    def is_identity(self) -> bool:
        return self.left_maps is None and self.right_maps is None

    @cached_property
    def _float_maps(self) -> tuple[tuple[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]]:
        """The fixed-point tables as float x / y maps: OpenCV 5 remaps these ~1.5x faster.

        They sample the same 1/32-pixel positions; only the bilinear weights are rounded
        differently (at most one grey level).
        """
        assert self.left_maps is not None and self.right_maps is not None
        left = cv2.convertMaps(*self.left_maps, cv2.CV_32FC1)
        right = cv2.convertMaps(*self.right_maps, cv2.CV_32FC1)
        return (left[0], left[1]), (right[0], right[1])

    def rectify(self, left: np.ndarray, right: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Warp a raw stereo pair into the rectified geometry (bilinear)."""
        if self.left_maps is None or self.right_maps is None:
            return left, right
        left_maps, right_maps = self._float_maps
        return (
            cv2.remap(left, *left_maps, cv2.INTER_LINEAR),
            cv2.remap(right, *right_maps, cv2.INTER_LINEAR),
        )


@dataclass(frozen=True, eq=False)
class StereoRig:
    """A calibrated stereo pair; ``left`` is the reference camera of the odometry.

    ``calibration_exact``: the calibration is the rig's true geometry (a rendered rig), not an
    estimate with errors of its own; the covariances reported without a gyro leave out the
    calibration error for it (``estimator.rig_settings``). Real rigs: False.
    """

    left: CameraModel
    right: CameraModel
    calibration_exact: bool = False

    def __post_init__(self) -> None:
        if not isinstance(self.calibration_exact, bool):
            raise ValueError(
                f"calibration_exact must be true or false, got {self.calibration_exact!r}"
            )
        if self.left.size != self.right.size:
            raise ValueError(
                f"left and right resolutions differ: {self.left.size} vs {self.right.size}"
            )
        if self.baseline < 1e-6:
            raise ValueError(
                f"stereo baseline is {self.baseline:.3g} m; the two cameras must be apart"
            )
        self._check_side_by_side()

    def _check_side_by_side(self) -> None:
        """The right camera beside the left one, on its +x side: the stereo matching searches
        along rows for a right pixel left of the left one. Swapped cameras (or topics) would
        otherwise find no stereo point in any frame and a run would coast on the IMU."""
        x, y, _ = self.T_left_right[:3, 3]  # the right camera's centre, left camera's frame
        where = f"x = {x:+.3f} m, y = {y:+.3f} m in the left camera's frame"
        if abs(y) > abs(x):
            raise ValueError(
                f"the right camera sits above or below the left one ({where}); only "
                "side-by-side stereo pairs are supported"
            )
        if x < 0:
            raise ValueError(
                f"the right camera sits to the left of the left one ({where}): left and right "
                "are swapped; give the left camera's images and calibration as the left "
                "(EuRoC: cam0, KITTI: image_0)"
            )

    @property
    def size(self) -> tuple[int, int]:
        return self.left.size

    @property
    def T_left_right(self) -> np.ndarray:
        """Right camera -> left camera."""
        return invert_pose(self.left.T_BS) @ self.right.T_BS

    @property
    def baseline(self) -> float:
        return float(np.linalg.norm(self.T_left_right[:3, 3]))

    @cached_property
    def rectification(self) -> Rectification:
        """Rectifying rotations, projections and remap tables (computed once per rig)."""
        if self._already_rectified():
            return self._identity_rectification()
        models = {self.left.distortion_model, self.right.distortion_model}
        if "equidistant" in models and models != {"equidistant"}:
            raise ValueError("mixed equidistant and pinhole-distortion cameras are not supported")
        if models == {"equidistant"}:
            r1, r2, p1, p2, q = self._fisheye_rectify()
            init_map = cv2.fisheye.initUndistortRectifyMap
        else:
            r1, r2, p1, p2, q = self._pinhole_rectify()
            init_map = cv2.initUndistortRectifyMap
        maps = [
            init_map(camera.K, camera.D, r, p, self.size, cv2.CV_16SC2)
            for camera, r, p in ((self.left, r1, p1), (self.right, r2, p2))
        ]
        return Rectification(
            size=self.size,
            fx=float(p1[0, 0]),
            cx=float(p1[0, 2]),
            cy=float(p1[1, 2]),
            baseline=float(-p2[0, 3] / p2[0, 0]),
            R_left=np.asarray(r1, dtype=float),
            R_right=np.asarray(r2, dtype=float),
            P1=np.asarray(p1, dtype=float),
            P2=np.asarray(p2, dtype=float),
            Q=np.asarray(q, dtype=float),
            left_maps=(maps[0][0], maps[0][1]),
            right_maps=(maps[1][0], maps[1][1]),
        )

    def _right_from_left(self) -> tuple[np.ndarray, np.ndarray]:
        """Rotation and (3, 1) translation taking left-camera points into the right camera.

        This is the direction OpenCV's stereo rectification expects.
        """
        T_right_left = invert_pose(self.T_left_right)
        return T_right_left[:3, :3].copy(), T_right_left[:3, 3].reshape(3, 1).copy()

    def _fisheye_rectify(self) -> tuple[np.ndarray, ...]:
        """R1, R2, P1, P2, Q for two equidistant (fisheye) cameras, no black border kept."""
        rotation, translation = self._right_from_left()
        return cv2.fisheye.stereoRectify(
            self.left.K,
            self.left.D,
            self.right.K,
            self.right.D,
            self.size,
            rotation,
            translation,
            flags=cv2.CALIB_ZERO_DISPARITY,
            newImageSize=self.size,
            balance=0.0,
            fov_scale=1.0,
        )

    def _pinhole_rectify(self) -> tuple[np.ndarray, ...]:
        """R1, R2, P1, P2, Q for two pinhole cameras (radtan or none), no black border kept."""
        rotation, translation = self._right_from_left()
        r1, r2, p1, p2, q, _, _ = cv2.stereoRectify(
            self.left.K,
            self.left.D,
            self.right.K,
            self.right.D,
            self.size,
            rotation,
            translation,
            flags=cv2.CALIB_ZERO_DISPARITY,
            alpha=0.0,
            newImageSize=self.size,
        )
        return r1, r2, p1, p2, q

    def _already_rectified(self) -> bool:
        """True for distortion-free cameras with equal intrinsics offset purely along x."""
        left, right = self.left, self.right
        relative = self.T_left_right
        return (
            left.distortion_model == "none"
            and right.distortion_model == "none"
            and np.allclose(
                [left.fx, left.fy, left.cx, left.cy],
                [right.fx, right.fy, right.cx, right.cy],
                rtol=0.0,
                atol=1e-6,
            )
            and abs(left.fx - left.fy) < 1e-6
            and np.allclose(relative[:3, :3], np.eye(3), atol=1e-9)
            and relative[0, 3] > 0.0
            and np.allclose(relative[1:3, 3], 0.0, atol=1e-9)
        )

    def _identity_rectification(self) -> Rectification:
        fx, cx, cy, b = self.left.fx, self.left.cx, self.left.cy, self.baseline
        p1 = np.array([[fx, 0.0, cx, 0.0], [0.0, fx, cy, 0.0], [0.0, 0.0, 1.0, 0.0]])
        p2 = p1.copy()
        p2[0, 3] = -fx * b
        q = np.array(
            [[1.0, 0, 0, -cx], [0, 1.0, 0, -cy], [0, 0, 0, fx], [0, 0, 1.0 / b, 0]], dtype=float
        )
        return Rectification(
            size=self.size,
            fx=fx,
            cx=cx,
            cy=cy,
            baseline=b,
            R_left=np.eye(3),
            R_right=np.eye(3),
            P1=p1,
            P2=p2,
            Q=q,
            left_maps=None,
            right_maps=None,
        )

    def to_dict(self) -> dict[str, Any]:
        """Plain JSON/YAML-serialisable form (what the service stores and ``load_rig`` reads);
        ``calibration_exact`` only when it is true."""
        data: dict[str, Any] = {"left": self.left.to_dict(), "right": self.right.to_dict()}
        if self.calibration_exact:
            data["calibration_exact"] = True
        return data

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> StereoRig:
        if not isinstance(data, dict) or "left" not in data or "right" not in data:
            raise ValueError("a stereo rig needs a mapping with 'left' and 'right' cameras")
        try:
            left = CameraModel.from_dict(data["left"])
        except ValueError as error:
            raise ValueError(f"left {error}") from error
        try:
            right = CameraModel.from_dict(data["right"])
        except ValueError as error:
            raise ValueError(f"right {error}") from error
        return cls(left=left, right=right, calibration_exact=data.get("calibration_exact", False))
