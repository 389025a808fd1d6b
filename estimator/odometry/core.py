"""``Odometry``: one stereo frame in, one pose report out (the steps are in the package doc)."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np

from estimator.config import SwarmvoConfig
from estimator.formats.calibration import StereoRig
from estimator.frontend.detection import FeatureDetector
from estimator.frontend.disparity_offset import DisparityOffset, configured_offset
from estimator.frontend.photometric import normalise_contrast
from estimator.frontend.shutter_offset import StereoTiming
from estimator.frontend.stereo import StereoMatcher, StereoPoints
from estimator.frontend.stereo_noise import NoiseLevel, StereoNoiseModel
from estimator.frontend.tracks import KeyframeView, Tracker
from estimator.geometry import invert_pose, nearest_rigid
from estimator.odometry.combination import ChainCombination, chains_through_previous
from estimator.odometry.estimation import PoseEstimation
from estimator.odometry.frames import CurrentFrame, Estimate, checked_pose, failed, grey_pair, stage
from estimator.odometry.fusion_step import FusionStep
from estimator.odometry.gyro_prediction import GyroPrediction, gyro_prediction_for
from estimator.odometry.measurements import CameraFrames
from estimator.odometry.observation import MeasurementObserver
from estimator.odometry.references import References
from estimator.odometry.revisits import KeyframeRevisits, revisits_on
from estimator.odometry.tracking import Tracking
from estimator.types import (
    FrameReport,
    FrameStatus,
    ImuBatch,
    ImuNoise,
    StereoFrame,
    check_timestamp_order,
)

if TYPE_CHECKING:
    from estimator.backend.recording import BackendObserver

__all__ = ["Odometry"]

# A frame's answer: pose, front-end pose, relative pose (front end), status, message.
Answer = tuple[np.ndarray, np.ndarray, np.ndarray, FrameStatus, str]


class Odometry:
    """Stereo visual odometry with an optional GTSAM/IMU back end (``config.backend``)."""

    def __init__(
        self,
        rig: StereoRig,
        config: SwarmvoConfig | None = None,
        imu_noise: ImuNoise | None = None,
        initial_pose: np.ndarray | None = None,
        first_index: int = 0,
        observer: MeasurementObserver | None = None,
        backend_observer: BackendObserver | None = None,
    ) -> None:
        """``observer``, when given, sees every measurement the frames make (observation.py);
        ``backend_observer`` everything the back end is given (backend/recording.py)."""
        self.rig = rig
        self.config = config if config is not None else SwarmvoConfig()
        self.rectification = rig.rectification
        self.detector = FeatureDetector(self.config.frontend)
        self.stereo = StereoMatcher(self.config.frontend, self.rectification)
        self.stereo_timing = StereoTiming(
            self.rectification, self.config.frontend.stereo_time_offset_ms
        )
        track_mode = self.config.frontend.mode == "track"
        self.disparity_offset = DisparityOffset(
            self.rectification, configured_offset(self.config.frontend)
        )
        self._tracker = Tracker(self.config.frontend, self.rectification) if track_mode else None
        self._frames = CameraFrames(self.rectification.R_left, self.rectification)
        self._initial_pose = checked_pose(initial_pose) if initial_pose is not None else None
        self._index = int(first_index) - 1
        self._count = 0
        self._last_timestamp_ns: int | None = None
        self._pose = self._initial_pose if self._initial_pose is not None else np.eye(4)
        gyro = gyro_prediction_for(rig, self.config.frontend)
        self._references = References(self.config.frontend, gyro)
        self._frame_interval_ns = 0  # time since the previous frame
        self._restored = False  # continued from state(): the first frame is predicted
        self._answered = self._pose  # the pose answered for the last frame (fused or not)
        frontend = self.config.frontend
        self.noise = StereoNoiseModel(
            self.rectification,
            NoiseLevel(
                frontend.pixel_sigma_u_px, frontend.pixel_sigma_v_px, frontend.disparity_sigma_px
            ),
            disparity_growth=self.config.registration.disparity_noise_growth,
        )
        self._fusion: FusionStep | None = None
        if self.config.backend.enabled:
            self._fusion = FusionStep(
                self.config.backend, rig, imu_noise, self._frames, self.noise, backend_observer
            )
        imu_fused = self._fusion is not None and self._fusion.backend.use_imu
        through_previous = chains_through_previous(frontend, imu_fused)
        chains = through_previous or frontend.fuse_previous_keyframe
        self._estimation = PoseEstimation(
            self.config, self.rectification, self.noise, chains, observer
        )
        self._chains = ChainCombination(
            frontend, rig, self._estimation, self._references, through_previous
        )
        self._tracking = Tracking(self._estimation, self._references, self._chains)
        self._revisits: KeyframeRevisits | None = None
        if revisits_on(frontend, imu_fused):
            self._revisits = KeyframeRevisits(
                frontend, self._estimation, self._references, self._frames
            )

    @property
    def frame_count(self) -> int:
        return self._count

    @property
    def fuses_previous_frame(self) -> bool:
        """Whether each frame is also measured through the previous frame
        (``frontend.fuse_previous_frame``, its default resolved by the IMU's presence)."""
        return self._chains.through_previous

    @property
    def reference_index(self) -> int | None:
        """Index of the frame the next one is matched against (None before the first frame).

        Each keyframe is measured once against the previous keyframe, so the errors of those
        measurements are independent and their sum is the drift: evaluations need to know them.
        """
        reference = self._references.reference
        return reference.index if reference is not None else None

    @property
    def keyframe_revisits(self) -> int | None:
        """How often the reference went back to an older keyframe (None: revisits off)."""
        return self._revisits.count if self._revisits is not None else None

    @property
    def common_rotation_bias(self) -> float:
        """The rate of the keyframe measurement's error that combining chains cannot average
        out, in force (``frontend.chain_common_rotation_bias``; unset: the rig's)."""
        return self._chains.common_rate

    @property
    def gyro_prediction(self) -> GyroPrediction | None:
        """The gyro's rotation that centres the search windows (None: not used)."""
        return self._references.gyro

    # ------------------------------------------------------------------ continuing elsewhere

    def state(self) -> dict[str, Any]:
        """What another process needs to continue this run after its last frame (JSON-ready).

        The last answered pose and its keyframe's pose, the measured motion (the velocity that
        predicts the next frame), the back end's biases and the disparity offset in use: the
        continuation predicts its first frame at constant velocity from here instead of
        restarting at rest.
        """
        references = self._references
        keyframe = references.reference.pose if references.reference is not None else self._pose
        return {
            "index": self._index,
            "timestamp_ns": self._last_timestamp_ns,
            "pose": self._answered.tolist(),
            "keyframe_pose": keyframe.tolist(),
            "motion": references.motion.tolist(),
            "motion_interval_ns": references.motion_interval_ns,
            "backend": self._fusion.backend.state() if self._fusion is not None else None,
            "disparity_offset_px": self.disparity_offset.applied,
        }

    def restore(self, state: dict[str, Any]) -> None:
        """Continue from :meth:`state` of another instance (before this one saw any frame)."""
        if self._count:
            raise ValueError("restore() must come before the first frame")
        self._index = int(state["index"])
        self._last_timestamp_ns = state["timestamp_ns"]
        self._pose = checked_pose(np.array(state["pose"], dtype=float))
        self._initial_pose = self._pose
        self._references.motion = nearest_rigid(np.array(state["motion"], dtype=float))
        self._references.motion_interval_ns = max(int(state["motion_interval_ns"]), 1)
        if self._fusion is not None and state.get("backend"):
            self._fusion.backend.restore(state["backend"])
        self.disparity_offset.resume(float(state.get("disparity_offset_px", 0.0)))
        self._restored = True

    # ------------------------------------------------------------------ the algorithm

    def process(self, frame: StereoFrame, imu: ImuBatch | None = None) -> FrameReport:
        """Pose of the left camera at ``frame``; ``imu`` holds the samples since the last frame."""
        timings: dict[str, float] = {}
        with stage(timings, "total"):
            left, right = self._rectified(frame, timings)
            self._references.advance_gyro(imu, frame.timestamp_ns)
            points = self._stereo_points(left, right, timings)
            current = CurrentFrame(self._index, int(frame.timestamp_ns), points, left, timings)
            estimate = self._track(current)
            answer, estimate = self._answer(frame, imu, estimate, timings)
            self._learn(frame, current, estimate, answer)
        return self._report(frame, answer, estimate, timings)

    def finish(self) -> tuple[tuple[int, np.ndarray], ...]:
        """Smoothed poses of the frames the back end still holds (end of a run), oldest first.

        With the back end, every frame's final estimate arrives once: in a later
        ``FrameReport.final_poses`` or here. Without it there is nothing to smooth.
        """
        return self._fusion.finish() if self._fusion is not None else ()

    # ------------------------------------------------------------------ stages

    def _answer(
        self,
        frame: StereoFrame,
        imu: ImuBatch | None,
        estimate: Estimate,
        timings: dict[str, float],
    ) -> tuple[Answer, Estimate]:
        """The frame's answer (pose, front-end pose, relative pose, status, message): the
        estimate chained onto its reference and fused; the estimate as it counts afterwards
        (failed when the back end's gate rejected it, and the front end coasts instead)."""
        previous_pose = self._pose
        frontend_pose, status, message = self._chain(estimate)
        relative_pose = invert_pose(previous_pose) @ frontend_pose
        with stage(timings, "fuse"):
            poses = (frontend_pose, relative_pose)
            pose, status, message = self._fuse(frame, imu, poses, estimate, status, message)
        if self._vision_rejected():
            estimate = failed(estimate, "rejected by the back end's gate")
            frontend_pose = self._chain(estimate)[0]
            relative_pose = invert_pose(previous_pose) @ frontend_pose
        return (pose, frontend_pose, relative_pose, status, message), estimate

    def _learn(
        self, frame: StereoFrame, current: CurrentFrame, estimate: Estimate, answer: Answer
    ) -> None:
        """What the next frame starts from: the noise level, the poses and the references."""
        self._estimation.measure_noise(estimate)
        self._measure_disparity_offset(current, estimate)
        if self._tracker is not None and self._references.reference is not None:
            if estimate.reference_from_current is None:  # no frame to follow the tracks by
                self._tracker.forget_frame()
        self._answered, self._pose = answer[0], answer[1]
        replaced = self._references.reference
        self._references.update(
            current.index, current.points, current.image, self._pose, estimate, frame.timestamp_ns
        )
        if self._revisits is not None:
            self._revisits.after_update(current, replaced, estimate)
        self.stereo_timing.learn(self._references.measured_velocity())

    def _measure_disparity_offset(self, current: CurrentFrame, estimate: Estimate) -> None:
        """Fold the frame's measurement against its reference into the disparity offset."""
        pairs, result, pose = estimate.pairs, estimate.result, estimate.reference_from_current
        if pairs is None or result is None or pose is None or estimate.reference is None:
            return
        inliers = result.inliers
        self.disparity_offset.observe(
            estimate.reference.points, current.points, pairs.reference_index[inliers],
            pairs.current_index[inliers], pose, self.noise,
        )  # fmt: skip

    def _rectified(
        self, frame: StereoFrame, timings: dict[str, float]
    ) -> tuple[np.ndarray, np.ndarray]:
        """The frame's images checked, rectified and normalised; the frame counts from here."""
        left, right = self._validated(frame)
        self._index += 1
        self._count += 1
        with stage(timings, "rectify"):
            left, right = self.rectification.rectify(left, right)
            return self._normalised(left), self._normalised(right)

    def _track(self, current: CurrentFrame) -> Estimate:
        """The frame's estimate against its references (none on the first frame)."""
        if self._references.reference is None:
            return Estimate(None, None, "")
        return self._tracking.track(current)

    def _validated(self, frame: StereoFrame) -> tuple[np.ndarray, np.ndarray]:
        timestamp = int(frame.timestamp_ns)
        check_timestamp_order(timestamp, self._last_timestamp_ns)
        left, right = grey_pair(frame, (self.rig.left.height, self.rig.left.width))
        if self._last_timestamp_ns is not None:
            self._frame_interval_ns = timestamp - self._last_timestamp_ns
        self._last_timestamp_ns = timestamp
        return left, right

    def _stereo_points(
        self, left: np.ndarray, right: np.ndarray, timings: dict[str, float]
    ) -> StereoPoints:
        """Detect and match both images, or follow the tracks (``frontend.mode``)."""
        if self._tracker is not None:
            with stage(timings, "detect"):
                step = self._references.motion_over(self._frame_interval_ns)
                self._tracker.follow(left, invert_pose(step), self._keyframe_view())
            with stage(timings, "stereo"):
                return self._in_step(self._tracker.stereo(right))
        with stage(timings, "detect"):
            left_features = self.detector.detect(left)
            right_features = self.detector.detect(right, same_scene=True)
        with stage(timings, "stereo"):
            return self._in_step(self.stereo.match(left_features, right_features, left, right))

    def _keyframe_view(self) -> KeyframeView | None:
        """The keyframe's tracks, image and predicted motion to this frame, for the tracker
        to find lost keyframe tracks again (None before the first keyframe)."""
        references = self._references
        keyframe, previous = references.reference, references.previous
        if keyframe is None or previous is None or self._last_timestamp_ns is None:
            return None
        keyframe_from_current = references.predicted_reference_from(self._last_timestamp_ns)
        return KeyframeView(keyframe.points, keyframe.image, invert_pose(keyframe_from_current))

    def _in_step(self, points: StereoPoints) -> StereoPoints:
        """``points`` as if both shutters had opened together (frontend/shutter_offset.py;
        the predicted velocity only when there is an offset to undo) and without the rig's
        disparity offset (frontend/disparity_offset.py)."""
        timing = self.stereo_timing
        velocity = self._references.velocity(self._frame_interval_ns) if timing.correcting else None
        return self.disparity_offset.corrected(timing.corrected(points, velocity))

    def _normalised(self, image: np.ndarray) -> np.ndarray:
        frontend = self.config.frontend
        if not frontend.normalise_contrast:
            return image
        return normalise_contrast(image, frontend.normalised_mean, frontend.normalised_std)

    def _chain(self, estimate: Estimate) -> tuple[np.ndarray, FrameStatus, str]:
        """pose_k = pose_ref @ T_ref_cur (paper eq. 2), in the original left camera frame."""
        references = self._references
        if references.reference is None and self._restored:
            step = references.motion_over(self._frame_interval_ns)
            motion = self._frames.in_camera(step)
            return self._pose @ motion, FrameStatus.OK, "resumed from stored state"
        if references.reference is None:
            message = (
                "resumed from stored pose"
                if self._initial_pose is not None
                else ("first frame: world = this left camera")
            )
            return self._pose, FrameStatus.OK, message
        if estimate.reference_from_current is None or estimate.reference is None:
            assert self._last_timestamp_ns is not None
            if not references.held(self._last_timestamp_ns):
                # Constant velocity: a moving camera keeps moving; a still one stays still.
                step = references.motion_over(self._frame_interval_ns)
                motion = self._frames.in_camera(step)
                message = f"{estimate.message}; pose predicted at constant velocity"
                return self._pose @ motion, FrameStatus.DEGRADED, message
            return self._pose, FrameStatus.LOST, f"{estimate.message}; pose held"
        reference_from_current = self._frames.reference_from_current(estimate)
        return estimate.reference.pose @ reference_from_current, FrameStatus.OK, estimate.message

    def _fuse(
        self,
        frame: StereoFrame,
        imu: ImuBatch | None,
        poses: tuple[np.ndarray, np.ndarray],
        estimate: Estimate,
        status: FrameStatus,
        message: str,
    ) -> tuple[np.ndarray, FrameStatus, str]:
        """Back-end pose and status (the front-end ones when the back end is off)."""
        if self._fusion is None:
            return poses[0], status, message
        first, anchored = self._references.reference is None, self._initial_pose is not None
        pose, status, fused_message = self._fusion.add(
            int(frame.timestamp_ns), imu, estimate, poses, first, anchored
        )
        return pose, status, "; ".join(part for part in (message, fused_message) if part)

    def _vision_rejected(self) -> bool:
        """Whether the back end's gate rejected this frame's vision."""
        fused = self._fusion.fused if self._fusion is not None else None
        return fused is not None and fused.vision_rejected

    def _report(
        self,
        frame: StereoFrame,
        answer: Answer,
        estimate: Estimate,
        timings: dict[str, float],
    ) -> FrameReport:
        """The frame's report: the answer (pose, front-end pose, relative pose, status,
        message) with the estimate's matches, covariance and the back end's marginals."""
        pose, frontend_pose, relative_pose, status, message = answer
        result, pairs = estimate.result, estimate.pairs
        fused = self._fusion.fused if self._fusion is not None else None
        final_poses = self._fusion.final_poses if self._fusion is not None else ()
        measured = estimate.reference_from_current is not None and estimate.reference is not None
        covariance = (
            self._frames.report_covariance(estimate, self.config.backend) if measured else None
        )
        return FrameReport(
            index=self._index,
            timestamp_ns=int(frame.timestamp_ns),
            pose=pose,
            frontend_pose=frontend_pose,
            relative_pose=relative_pose,
            status=status,
            matches=len(pairs) if pairs is not None else 0,
            inliers=int(result.inliers.sum()) if result is not None else 0,
            support=int(result.support) if result is not None else 0,
            timings_s=timings,
            message=message,
            final_poses=final_poses,
            measurement_covariance=covariance,
            reference_timestamp_ns=estimate.reference.timestamp_ns if measured else None,
            body_covariance=fused.body_covariance if fused is not None else None,
            body_motion=fused.body_motion if fused is not None else None,
            body_motion_covariance=fused.body_motion_covariance if fused is not None else None,
            covariance_scale=fused.covariance_scale if fused is not None else 1.0,
            pose_covariance_scale=fused.pose_covariance_scale if fused is not None else 1.0,
        )
