"""The odometry answer in the robotics convention (REP 105, nav_msgs/Odometry).

Per frame: the pose of ``base_link`` in ``odom`` with its 6x6 covariance, the twist of
``base_link`` in its own axes with its 6x6 covariance, and the status.

* ``base_link`` is the body (IMU) frame of the rig (``T_BS`` of the left camera; on a rig
  without an IMU, such as KITTI, that is the left camera itself).
* ``odom`` is one rule, whatever the flags: the first body pose, rotated so that z points up
  (roll and pitch from the mean accelerometer reading of the IMU samples given with the first
  frame, yaw = 0) when there are such samples, else the first body pose as it is.
* Covariances follow ROS: the pose's in (x, y, z, rotation about the odom X, Y, Z axes), the
  twist's in (vx, vy, vz, wx, wy, wz) of ``base_link``. With the back end they are its
  marginals; without it they are chained from the front end's measurement covariances along
  the keyframes (each keyframe-to-keyframe measurement is independent, so their transported sum
  is the drift). Frames without a measurement add the back end's constant-velocity noise. Every
  covariance is floored by the smallest fit sigmas (``backend.fit_min_*``): never zero, never NaN.
  Both are then multiplied by the session's covariance scale, measured online against the gyro
  (``estimator.backend.covariance_scale``). Without the gyro the chain carries the reported
  measurement covariance of ``estimator.backend.systematic_noise`` (a smaller floor and a
  calibration error proportional to the motion), also with the back end, and the twist
  covariance is the chain's growth from the previous frame.

``OdometryBuilder`` turns the pipeline's ``FrameReport`` stream into these messages; it must
see every frame in order.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import gtsam
import numpy as np

from estimator.backend.systematic_noise import (
    drift_growth,
    fit_floor_covariance,
    reported_measurement_covariance,
)
from estimator.config import BackendConfig
from estimator.geometry import (
    invert_pose,
    make_pose,
    matrix_to_quat,
    quat_to_matrix,
    se3_adjoint,
    transport_covariance,
)
from estimator.types import FrameReport, FrameStatus

__all__ = ["BASE_FRAME", "ODOM_FRAME", "OdometryBuilder", "OdometryMessage", "odom_rotation"]

ODOM_FRAME = "odom"
BASE_FRAME = "base_link"
# Variance of the twist of the first frame (nothing is known about its motion yet).
_UNKNOWN_TWIST_VARIANCE = 1e2


@dataclass(frozen=True)
class OdometryMessage:
    """One frame's odometry: nav_msgs/Odometry fields plus status and the left-camera pose."""

    stamp_ns: int
    frame_id: str
    child_frame_id: str
    pose: np.ndarray  # (4, 4) child in odom
    pose_covariance: np.ndarray  # (6, 6) x y z, rotation about odom X Y Z
    linear_velocity: np.ndarray  # (3,) m/s in the child frame
    angular_velocity: np.ndarray  # (3,) rad/s in the child frame
    twist_covariance: np.ndarray  # (6, 6) vx vy vz wx wy wz
    status: FrameStatus
    camera_pose: np.ndarray  # (4, 4) left camera in odom

    def to_dict(self) -> dict[str, Any]:
        """JSON form, laid out like nav_msgs/Odometry (quaternion x, y, z, w)."""
        w, x, y, z = matrix_to_quat(self.pose[:3, :3])
        position = self.pose[:3, 3]
        return {
            "header": {"stamp_ns": int(self.stamp_ns), "frame_id": self.frame_id},
            "child_frame_id": self.child_frame_id,
            "pose": {
                "pose": {
                    "position": _xyz(position),
                    "orientation": {"x": x, "y": y, "z": z, "w": w},
                },
                "covariance": [float(v) for v in self.pose_covariance.ravel()],
            },
            "twist": {
                "twist": {
                    "linear": _xyz(self.linear_velocity),
                    "angular": _xyz(self.angular_velocity),
                },
                "covariance": [float(v) for v in self.twist_covariance.ravel()],
            },
            "status": str(self.status),
            "camera_pose": [float(v) for v in self.camera_pose.ravel()],
        }

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> OdometryMessage:
        """Inverse of :meth:`to_dict`."""
        pose = data["pose"]["pose"]
        q = pose["orientation"]
        twist = data["twist"]["twist"]
        return cls(
            stamp_ns=int(data["header"]["stamp_ns"]),
            frame_id=str(data["header"]["frame_id"]),
            child_frame_id=str(data["child_frame_id"]),
            pose=make_pose(
                quat_to_matrix(np.array([q["w"], q["x"], q["y"], q["z"]], dtype=float)),
                _vector(pose["position"]),
            ),
            pose_covariance=np.asarray(data["pose"]["covariance"], dtype=float).reshape(6, 6),
            linear_velocity=_vector(twist["linear"]),
            angular_velocity=_vector(twist["angular"]),
            twist_covariance=np.asarray(data["twist"]["covariance"], dtype=float).reshape(6, 6),
            status=FrameStatus(data["status"]),
            camera_pose=np.asarray(data["camera_pose"], dtype=float).reshape(4, 4),
        )


def _xyz(vector: np.ndarray) -> dict[str, float]:
    return {"x": float(vector[0]), "y": float(vector[1]), "z": float(vector[2])}


def _vector(data: dict[str, float]) -> np.ndarray:
    return np.array([data["x"], data["y"], data["z"]], dtype=float)


def odom_rotation(first_accel: np.ndarray | None) -> np.ndarray:
    """Rotation of the odom frame from the first body frame: levelled with gravity when the
    first frame came with accelerometer samples that see it, else the identity."""
    from estimator.backend.imu import gravity_aligned_rotation

    if first_accel is None or len(first_accel) == 0:
        return np.eye(3)
    try:
        return gravity_aligned_rotation(first_accel)
    except ValueError:  # moving too hard to see gravity: no levelling
        return np.eye(3)


@dataclass
class _Chained:
    """A frame's front-end pose and covariance (left camera tangent) along the keyframe chain."""

    pose: np.ndarray
    covariance: np.ndarray
    measurement: np.ndarray | None  # its own T_ref_cur covariance
    reference_ns: int | None


class OdometryBuilder:
    """FrameReports in, OdometryMessages out (module doc for the frames and covariances)."""

    def __init__(
        self,
        body_from_camera: np.ndarray,
        config: BackendConfig | None = None,
        first_accel: np.ndarray | None = None,
        odom_from_world: np.ndarray | None = None,
        calibrated: bool = True,
        gyro_calibrated: bool | None = None,
    ) -> None:
        """``odom_from_world`` fixes the odom frame instead of the first report (a pipeline
        resumed from a stored pose continues in the odom frame it had). ``calibrated`` applies
        each report's ``covariance_scale`` (False: the fixed noise model's covariances).
        ``gyro_calibrated`` (default: the back end runs with the IMU and the gyro factor):
        False reports the covariances without a gyro (``backend.systematic_noise``)."""
        self.calibrated = calibrated
        config = config if config is not None else BackendConfig()
        if gyro_calibrated is None:
            gyro_calibrated = config.enabled and config.use_imu and config.covariance_scale != "off"
        self._config = config
        self._without_gyro = calibrated and not gyro_calibrated
        self.body_from_camera = np.asarray(body_from_camera, dtype=float)
        self.camera_from_body = invert_pose(self.body_from_camera)
        self._camera_to_body = se3_adjoint(self.body_from_camera)
        self._level = odom_rotation(first_accel)
        self._floor = fit_floor_covariance(config)
        self._report_floor = np.diag(
            [config.report_min_rotation_sigma_rad**2] * 3
            + [config.report_min_translation_sigma_m**2] * 3
        )
        self._coast = np.diag(
            [config.cv_rotation_sigma_rad**2] * 3 + [config.cv_translation_sigma_m**2] * 3
        )
        self._odom_from_world = odom_from_world
        self._chain: dict[int, _Chained] = {}
        self._previous_ns: int | None = None
        # (body pose, its covariance as given, as reported) of the previous frame
        self._previous_pose: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
        self._latest_reference_ns: int | None = None

    def build(self, report: FrameReport) -> OdometryMessage:
        """The message of the next frame (frames must come in order, none skipped)."""
        body_pose = report.pose @ self.camera_from_body  # body in the pipeline's world
        if self._odom_from_world is None:
            self._odom_from_world = make_pose(self._level, np.zeros(3)) @ invert_pose(body_pose)
        chained = self._chain_frontend(report)
        # Without a gyro the back end's marginals carry the graph's noise model; the chain
        # carries the reported one (the same measurements: equal to rounding on rendered data).
        pose_covariance = None if self._without_gyro else report.body_covariance
        if pose_covariance is None or not np.isfinite(pose_covariance).all():
            pose_covariance = self._to_body(chained.covariance)
        motion, motion_covariance, dt = self._motion(report, chained)
        odom_pose = self._odom_from_world @ body_pose
        self._previous_ns = report.timestamp_ns
        scale = report.covariance_scale if self.calibrated else 1.0
        pose_scale = max(report.pose_covariance_scale if self.calibrated else 1.0, 1.0)
        pose_covariance = self._scaled_pose_covariance(pose_covariance, body_pose, pose_scale)
        # Without the gyro the twist floor is a drift rate (the reporting floor per second):
        # a per-frame floor summed over a window's frames alone exceeded the drift 2-4x.
        twist_floor = self._report_floor * min(dt, 1.0) if self._without_gyro else self._floor
        return OdometryMessage(
            stamp_ns=report.timestamp_ns,
            frame_id=ODOM_FRAME,
            child_frame_id=BASE_FRAME,
            pose=odom_pose,
            pose_covariance=_pose_covariance_ros(pose_covariance + self._floor, odom_pose),
            linear_velocity=motion[3:] / dt,
            angular_velocity=motion[:3] / dt,
            twist_covariance=scale * _swap_blocks(motion_covariance + twist_floor) / dt**2,
            status=report.status,
            camera_pose=self._odom_from_world @ report.pose,
        )

    # ------------------------------------------------------------------ covariances

    def _scaled_pose_covariance(
        self, covariance: np.ndarray, body_pose: np.ndarray, scale: float
    ) -> np.ndarray:
        """The pose covariance with its change since the previous frame scaled by ``scale``.

        The factor applies to what the measurements add, frame by frame, so a factor that
        moves during the session rescales the drift from then on, not the drift so far (with a
        constant factor this is ``scale`` times the covariance). Only inflated: on rendered
        flights the noise model's pose covariance is consistent over 1 s windows although
        the measurements are conservative (other errors than theirs make up the drift), and
        shrinking it by the measurements' factor made it over-confident (docs).
        """
        previous, self._previous_pose = self._previous_pose, None
        reported = scale * covariance
        if previous is not None:
            motion = invert_pose(previous[0]) @ body_pose
            change = covariance - transport_covariance(previous[1], motion)
            values, vectors = np.linalg.eigh(0.5 * (change + change.T))
            # What the smoother takes back is not scaled: a large factor would take it many times.
            grown = (vectors * np.where(values > 0, scale * values, values)) @ vectors.T
            reported = transport_covariance(previous[2], motion) + grown
            values, vectors = np.linalg.eigh(0.5 * (reported + reported.T))
            reported = (vectors * np.clip(values, 0.0, None)) @ vectors.T
        self._previous_pose = (body_pose, covariance, reported)
        return reported

    def _to_body(self, camera_covariance: np.ndarray) -> np.ndarray:
        """Left-camera tangent -> body tangent: T_BS T Exp(xi) T_SB = (..) Exp(Ad(T_BS) xi)."""
        return self._camera_to_body @ camera_covariance @ self._camera_to_body.T

    def _chain_frontend(self, report: FrameReport) -> _Chained:
        """Front-end pose covariance: the reference's, transported, plus the measurement's."""
        pose = report.frontend_pose
        reference_ns = report.reference_timestamp_ns
        reference = self._chain.get(reference_ns) if reference_ns is not None else None
        measurement = report.measurement_covariance
        if self._previous_ns is None:
            chained = _Chained(pose, np.zeros((6, 6)), None, None)
        elif measurement is not None and reference is not None:
            motion = invert_pose(reference.pose) @ pose
            if self._without_gyro:
                measurement = reported_measurement_covariance(measurement, motion, self._config)
            covariance = transport_covariance(reference.covariance, motion) + measurement
            chained = _Chained(pose, covariance, measurement, report.reference_timestamp_ns)
        else:  # no measurement: the previous pose, moved on at constant velocity
            previous = self._chain[self._previous_ns]
            motion = invert_pose(previous.pose) @ pose
            covariance = transport_covariance(previous.covariance, motion) + self._coast
            chained = _Chained(pose, covariance, None, None)
        self._chain[report.timestamp_ns] = chained
        self._forget(report)
        return chained

    def _forget(self, report: FrameReport) -> None:
        """Keep this frame, the previous one (its motion to this one is still to come) and
        those a later frame may still be measured against: none older than the latest
        reference, since a front end's references only move forward."""
        if report.reference_timestamp_ns is not None:
            self._latest_reference_ns = report.reference_timestamp_ns
        keep = report.timestamp_ns if self._previous_ns is None else self._previous_ns
        if self._latest_reference_ns is not None:
            keep = min(keep, self._latest_reference_ns)
        for stamp in [stamp for stamp in self._chain if stamp < keep]:
            del self._chain[stamp]

    def _motion(
        self, report: FrameReport, chained: _Chained
    ) -> tuple[np.ndarray, np.ndarray, float]:
        """Body motion since the previous frame as a tangent vector, its covariance and dt."""
        if self._previous_ns is None:
            unknown = np.eye(6) * _UNKNOWN_TWIST_VARIANCE
            return np.zeros(6), unknown, 1.0
        dt = (report.timestamp_ns - self._previous_ns) * 1e-9
        if (
            report.body_motion is not None
            and report.body_motion_covariance is not None
            and not self._without_gyro
        ):
            motion, covariance = report.body_motion, report.body_motion_covariance
        else:
            camera_motion = report.relative_pose
            motion = self.body_from_camera @ camera_motion @ self.camera_from_body
            covariance = self._to_body(self._frontend_motion_covariance(chained, camera_motion))
        if not np.isfinite(covariance).all():
            covariance = self._to_body(self._coast)
        return np.asarray(gtsam.Pose3.Logmap(gtsam.Pose3(motion))), covariance, dt

    def _frontend_motion_covariance(
        self, chained: _Chained, camera_motion: np.ndarray
    ) -> np.ndarray:
        """Covariance of T_prev_cur from the measurements of both frames.

        Measured against the previous frame it is the measurement's; both measured against the
        same keyframe, T_prev_cur = T_ref_prev^-1 T_ref_cur adds the previous one's.
        """
        assert self._previous_ns is not None
        previous = self._chain[self._previous_ns]
        if chained.measurement is None:
            return self._coast
        if self._without_gyro:
            return drift_growth(chained.covariance, previous.covariance, camera_motion)
        if chained.reference_ns == self._previous_ns or previous.measurement is None:
            return chained.measurement
        return chained.measurement + transport_covariance(previous.measurement, camera_motion)


def _swap_blocks(covariance: np.ndarray) -> np.ndarray:
    """GTSAM order (rotation, translation) -> ROS order (translation, rotation)."""
    order = [3, 4, 5, 0, 1, 2]
    return covariance[np.ix_(order, order)]


def _pose_covariance_ros(covariance: np.ndarray, pose: np.ndarray) -> np.ndarray:
    """Body-frame right perturbation (rotation phi, translation rho) -> ROS pose covariance.

    T Exp(phi, rho) moves the position by R rho and turns the orientation by R phi about the
    odom axes, so the covariance is rotated into odom axes block by block.
    """
    rotation = np.zeros((6, 6))
    rotation[:3, :3] = rotation[3:, 3:] = pose[:3, :3]
    ros = rotation @ _swap_blocks(covariance) @ rotation.T
    return 0.5 * (ros + ros.T)
