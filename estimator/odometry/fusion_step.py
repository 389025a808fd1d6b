"""The fuse step: the frame's vision handed to the GTSAM/IMU back end, and the back end's
answer placed in the odometry's world (the first frame's front-end pose anchors it)."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from estimator.config import BackendConfig
from estimator.formats.calibration import StereoRig
from estimator.geometry import invert_pose
from estimator.odometry.frames import Estimate
from estimator.odometry.measurements import CameraFrames, Measurement
from estimator.types import FrameStatus, ImuBatch, ImuNoise

if TYPE_CHECKING:
    from estimator.backend import FusedEstimate
    from estimator.backend.recording import BackendObserver
    from estimator.frontend.stereo_noise import StereoNoiseModel

__all__ = ["FusionStep"]

FinalPoses = tuple[tuple[int, np.ndarray], ...]


class FusionStep:
    """The back end (``config.backend``) behind the front end, in the front end's world."""

    def __init__(
        self,
        config: BackendConfig,
        rig: StereoRig,
        imu_noise: ImuNoise | None,
        frames: CameraFrames,
        noise: StereoNoiseModel,
        observer: BackendObserver | None = None,
    ) -> None:
        from estimator.backend import FusionBackend  # GTSAM loads only when the back end runs

        self.config = config
        self.backend = FusionBackend(
            config, body_from_camera=rig.left.T_BS, imu_noise=imu_noise, observer=observer
        )
        self.frames = frames
        self.noise = noise  # the session's stereo noise, for landmarks
        self.world_from_backend = np.eye(4)  # anchors the back end's world on initial_pose
        self.fused: FusedEstimate | None = None  # the back end's latest answer
        self.final_poses: FinalPoses = ()  # smoothed by the latest frame, in the world

    def add(
        self,
        timestamp_ns: int,
        imu: ImuBatch | None,
        estimate: Estimate,
        poses: tuple[np.ndarray, np.ndarray],
        first: bool,
        anchored: bool,
    ) -> tuple[np.ndarray, FrameStatus, str]:
        """The fused pose, status and message of a frame with ``estimate`` and its
        ``poses`` (front-end pose, relative pose). On the ``first`` frame the back end's
        world is placed on the front-end pose when ``anchored`` (an initial pose was given)."""
        frontend_pose, relative_pose = poses
        measurement = self._measurement(estimate, relative_pose, first)
        fused = self.backend.add_frame(timestamp_ns, imu=imu, **measurement.keywords())
        self.fused = fused
        if first and anchored:
            self.world_from_backend = frontend_pose @ invert_pose(fused.pose)
        elif first:
            self.world_from_backend = np.eye(4)
        self.final_poses = self.in_world(fused.final_poses)
        return self.world_from_backend @ fused.pose, fused.status, fused.message

    def _measurement(
        self, estimate: Estimate, relative_pose: np.ndarray, first: bool
    ) -> Measurement:
        """The vision the back end takes: the first frame's pose, nothing, or the estimate."""
        if first:
            return Measurement(relative_pose=relative_pose)
        if estimate.reference_from_current is None:
            return Measurement()
        return self.frames.measurement(estimate, self.noise if self.config.landmarks else None)

    def finish(self) -> FinalPoses:
        """Smoothed poses of the frames the back end still holds, oldest first."""
        return self.in_world(self.backend.flush())

    def in_world(self, final_poses: FinalPoses) -> FinalPoses:
        return tuple((stamp, self.world_from_backend @ pose) for stamp, pose in final_poses)
