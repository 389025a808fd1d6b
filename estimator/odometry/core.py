"""``Odometry``: one stereo frame in, one pose report out (the steps are in the package doc)."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np

from estimator.config import SwarmvoConfig
from estimator.formats.calibration import StereoRig
from estimator.frontend.features import FeatureDetector
from estimator.frontend.photometric import normalise_contrast
from estimator.frontend.stereo import StereoMatcher, StereoPoints
from estimator.frontend.stereo_noise import NoiseLevel, StereoNoiseModel, flow
from estimator.frontend.temporal import PredictionUncertainty
from estimator.frontend.tracks import Tracker
from estimator.geometry import invert_pose, nearest_rigid
from estimator.odometry.chains import (
    Measured,
    combine_chain,
    inverse_covariance,
    link_bias_covariance,
)
from estimator.odometry.estimation import PoseEstimation
from estimator.odometry.frames import (
    Estimate,
    Reference,
    checked_pose,
    failed,
    sensitivities_of,
    stage,
    to_grey8,
)
from estimator.odometry.gyro_prediction import GyroPrediction
from estimator.odometry.measurements import CameraFrames, Measurement
from estimator.odometry.references import References
from estimator.rig_settings import common_rotation_bias
from estimator.types import (
    FrameReport,
    FrameStatus,
    ImuBatch,
    ImuNoise,
    StereoFrame,
    check_timestamp_order,
)

if TYPE_CHECKING:
    from estimator.backend import FusedEstimate

__all__ = ["Odometry"]


class Odometry:
    """Stereo visual odometry with an optional GTSAM/IMU back end (``config.backend``)."""

    def __init__(
        self,
        rig: StereoRig,
        config: SwarmvoConfig | None = None,
        imu_noise: ImuNoise | None = None,
        initial_pose: np.ndarray | None = None,
        first_index: int = 0,
    ) -> None:
        self.rig = rig
        self.config = config if config is not None else SwarmvoConfig()
        self.rectification = rig.rectification
        self.detector = FeatureDetector(self.config.frontend)
        self.stereo = StereoMatcher(self.config.frontend, self.rectification)
        track_mode = self.config.frontend.mode == "track"
        self._tracker = Tracker(self.config.frontend, self.rectification) if track_mode else None
        self._frames = CameraFrames(self.rectification.R_left, self.rectification)
        self._initial_pose = checked_pose(initial_pose) if initial_pose is not None else None
        self._backend = self._make_backend(imu_noise) if self.config.backend.enabled else None
        self._world_from_backend = np.eye(4)  # anchors the back end's world on initial_pose
        self._index = int(first_index) - 1
        self._count = 0
        self._last_timestamp_ns: int | None = None
        self._pose = self._initial_pose if self._initial_pose is not None else np.eye(4)
        self._references = References(self.config.frontend, self._gyro_prediction())
        self._frame_interval_ns = 0  # time since the previous frame
        self._final_poses: tuple[tuple[int, np.ndarray], ...] = ()  # from the back end
        self._restored = False  # continued from state(): the first frame is predicted
        self._answered = self._pose  # the pose answered for the last frame (fused or not)
        self._fused: FusedEstimate | None = None  # the back end's latest answer
        frontend = self.config.frontend
        self.noise = StereoNoiseModel(
            self.rectification,
            NoiseLevel(
                frontend.pixel_sigma_u_px, frontend.pixel_sigma_v_px, frontend.disparity_sigma_px
            ),
        )
        self._fuse_previous_frame = self._chain_through_previous()
        common = frontend.chain_common_rotation_bias
        self._common_rate = common if common is not None else common_rotation_bias(rig).value
        chains = self._fuse_previous_frame or frontend.fuse_previous_keyframe
        self._estimation = PoseEstimation(self.config, self.rectification, self.noise, chains)

    def _chain_through_previous(self) -> bool:
        """``frontend.fuse_previous_frame``; unset, on only when no IMU is fused.

        Vision alone the chain through the previous frame lowers MH_01's rotation error per
        frame by a fifth; with the IMU the back end already smooths the rotation, and the
        chain's errors, shared by consecutive combined measurements, cost fused ATE
        (docs/frontend.md, "Tracking against a keyframe").
        """
        configured = self.config.frontend.fuse_previous_frame
        if configured is not None:
            return configured
        return not (self._backend is not None and self._backend.use_imu)

    def _gyro_prediction(self) -> GyroPrediction | None:
        """The gyro's rotation for the per-point search windows (``frontend.gyro_prediction``).

        Only where the windows are per point (``min_search_radius_px`` set, the drives): with
        one wide window for every point (EuRoC-like rigs) the constant-velocity centre is what
        the window was sized for, and the gyro's centre moved the noisy rendered flight's fused
        trajectory by a few per cent either way (docs/performance.md, "Driving rig").
        """
        frontend = self.config.frontend
        if not frontend.gyro_prediction or frontend.min_search_radius_px is None:
            return None
        rect_from_body = self.rectification.R_left @ self.rig.left.T_BS[:3, :3].T
        return GyroPrediction(rect_from_body, np.radians(frontend.prediction_gyro_error_deg_s))

    def _make_backend(self, imu_noise: ImuNoise | None):
        from estimator.backend import FusionBackend  # GTSAM loads only when the back end runs

        return FusionBackend(
            self.config.backend, body_from_camera=self.rig.left.T_BS, imu_noise=imu_noise
        )

    @property
    def frame_count(self) -> int:
        return self._count

    @property
    def fuses_previous_frame(self) -> bool:
        """Whether each frame is also measured through the previous frame
        (``frontend.fuse_previous_frame``, its default resolved by the IMU's presence)."""
        return self._fuse_previous_frame

    @property
    def reference_index(self) -> int | None:
        """Index of the frame the next one is matched against (None before the first frame).

        Each keyframe is measured once against the previous keyframe, so the errors of those
        measurements are independent and their sum is the drift: evaluations need to know them.
        """
        reference = self._references.reference
        return reference.index if reference is not None else None

    # ------------------------------------------------------------------ continuing elsewhere

    def state(self) -> dict[str, Any]:
        """What another process needs to continue this run after its last frame (JSON-ready).

        The last answered pose and its keyframe's pose, the measured motion (the velocity that
        predicts the next frame) and the back end's biases: the continuation predicts its first
        frame at constant velocity from here instead of restarting at rest.
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
            "backend": self._backend.state() if self._backend is not None else None,
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
        if self._backend is not None and state.get("backend"):
            self._backend.restore(state["backend"])
        self._restored = True

    # ------------------------------------------------------------------ the algorithm

    def process(self, frame: StereoFrame, imu: ImuBatch | None = None) -> FrameReport:
        """Pose of the left camera at ``frame``; ``imu`` holds the samples since the last frame."""
        timings: dict[str, float] = {}
        with stage(timings, "total"):
            left, right = self._validated(frame)
            self._index += 1
            self._count += 1
            with stage(timings, "rectify"):
                left, right = self.rectification.rectify(left, right)
                left, right = self._normalised(left), self._normalised(right)
            self._references.advance_gyro(imu, frame.timestamp_ns)
            points = self._stereo_points(left, right, timings)
            if self._references.reference is None:
                estimate = Estimate(None, None, "")
            else:
                estimate = self._track(points, left, timings)
            previous_pose = self._pose
            frontend_pose, status, message = self._chain(estimate)
            relative_pose = invert_pose(previous_pose) @ frontend_pose
            with stage(timings, "fuse"):
                pose, status, message = self._fuse(
                    frame, imu, frontend_pose, relative_pose, estimate, status, message
                )
            if self._fused is not None and self._fused.vision_rejected:
                estimate = failed(estimate, "rejected by the back end's gate")
                frontend_pose = self._chain(estimate)[0]
                relative_pose = invert_pose(previous_pose) @ frontend_pose
            self._estimation.measure_noise(estimate)
            self._answered = pose
            self._pose = frontend_pose
            self._references.update(
                self._index, points, left, frontend_pose, estimate, frame.timestamp_ns
            )
        answer = (pose, frontend_pose, relative_pose, status, message)
        return self._report(frame, answer, estimate, timings)

    def finish(self) -> tuple[tuple[int, np.ndarray], ...]:
        """Smoothed poses of the frames the back end still holds (end of a run), oldest first.

        With the back end, every frame's final estimate arrives once: in a later
        ``FrameReport.final_poses`` or here. Without it there is nothing to smooth.
        """
        if self._backend is None:
            return ()
        return self._in_world(self._backend.flush())

    def _in_world(
        self, final_poses: tuple[tuple[int, np.ndarray], ...]
    ) -> tuple[tuple[int, np.ndarray], ...]:
        return tuple((stamp, self._world_from_backend @ pose) for stamp, pose in final_poses)

    # ------------------------------------------------------------------ stages

    def _validated(self, frame: StereoFrame) -> tuple[np.ndarray, np.ndarray]:
        timestamp = int(frame.timestamp_ns)
        check_timestamp_order(timestamp, self._last_timestamp_ns)
        left = to_grey8(frame.left, "left image")
        right = to_grey8(frame.right, "right image")
        expected = (self.rig.left.height, self.rig.left.width)
        for name, image in (("left", left), ("right", right)):
            if image.shape != expected:
                raise ValueError(
                    f"{name} image is {image.shape[1]}x{image.shape[0]}, the calibration "
                    f"expects {expected[1]}x{expected[0]}"
                )
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
                self._tracker.follow(left, invert_pose(step))
            with stage(timings, "stereo"):
                return self._tracker.stereo(right)
        with stage(timings, "detect"):
            left_features = self.detector.detect(left)
            right_features = self.detector.detect(right, same_scene=True)
        with stage(timings, "stereo"):
            return self.stereo.match(left_features, right_features, left, right)

    def _normalised(self, image: np.ndarray) -> np.ndarray:
        frontend = self.config.frontend
        if not frontend.normalise_contrast:
            return image
        return normalise_contrast(image, frontend.normalised_mean, frontend.normalised_std)

    def _track(
        self, points: StereoPoints, image: np.ndarray, timings: dict[str, float]
    ) -> Estimate:
        """Relative pose against the keyframe; if that fails, against the previous good frame,
        and then against the last failed frame that had points (its pose coasted). An estimate
        far from the constant-velocity prediction counts as failed."""
        references = self._references
        keyframe, previous = references.reference, references.previous
        fallback = references.fallback
        assert keyframe is not None and previous is not None
        assert self._last_timestamp_ns is not None
        previous_ns = self._last_timestamp_ns - previous.timestamp_ns
        since_previous = references.motion_over(previous_ns)
        keyframe_prediction = references.reference_from_previous @ since_previous
        estimate = self._estimate_against(
            keyframe, keyframe_prediction, points, image, timings,
            references.prediction_uncertainty(previous_ns),
        )  # fmt: skip
        estimate = self._estimation.plausible(estimate, keyframe_prediction, previous_ns)
        if self._fuse_previous_frame or self.config.frontend.fuse_previous_keyframe:
            estimate = self._with_other_references(estimate, points, image, timings)
        retries = [(previous, since_previous, previous_ns, "the previous frame")]
        if fallback is not None:
            since_fallback = self._last_timestamp_ns - fallback.timestamp_ns
            retries.append(
                (fallback, references.motion_over(since_fallback), since_fallback,
                 "the last frame with points")
            )  # fmt: skip
        for reference, prediction, span_ns, name in retries:
            if estimate.reference_from_current is not None or reference is keyframe:
                continue
            retry = self._estimate_against(
                reference, prediction, points, image, timings,
                references.prediction_uncertainty(span_ns),
            )  # fmt: skip
            retry = self._estimation.plausible(retry, prediction, span_ns)
            if retry.reference_from_current is not None:
                retry.message = (
                    f"keyframe {keyframe.index} not tracked ({estimate.message}); "
                    f"tracked against {name}"
                )
                return retry
        return estimate

    def _with_other_references(
        self, estimate: Estimate, points: StereoPoints, image: np.ndarray, timings: dict[str, float]
    ) -> Estimate:
        """The keyframe estimate combined with the chains through the previous frame and
        through the keyframe before this one (estimator/odometry/chains.py)."""
        references = self._references
        keyframe, previous, older = references.reference, references.previous, references.older
        combine_previous = (
            self._fuse_previous_frame and previous is not keyframe and self._moving(estimate)
        )
        if previous is not None and combine_previous:
            covariance = references.reference_from_previous_covariance
            link = None
            if covariance is not None:
                link = Measured(
                    references.reference_from_previous, covariance, *references.previous_sensitivity
                )
            estimate, _ = self._combined(estimate, previous, link, points, image, timings)
        if older is not None and self.config.frontend.fuse_previous_keyframe:
            to_older = invert_pose(references.older_from_reference)
            covariance = inverse_covariance(
                references.older_from_reference, references.older_from_reference_covariance
            )
            estimate, tracked = self._combined(
                estimate, older, Measured(to_older, covariance), points, image, timings
            )
            if not tracked:
                references.older = None  # out of view: not tried again
        return estimate

    def _combined(
        self,
        estimate: Estimate,
        reference: Reference,
        link: Measured | None,
        points: StereoPoints,
        image: np.ndarray,
        timings: dict[str, float],
    ) -> tuple[Estimate, bool]:
        """``estimate`` (against the keyframe) combined with the chain keyframe -> ``reference``
        -> current (``link`` = keyframe -> ``reference``), and whether ``reference`` was
        tracked; the estimate is kept as it was when either part has no covariance."""
        measured = estimate.reference_from_current
        if measured is None or estimate.covariance is None or link is None:
            return estimate, True
        assert self._last_timestamp_ns is not None
        prediction = invert_pose(link.pose) @ measured  # sharper than velocity
        chained = self._estimate_against(reference, prediction, points, image, timings)
        span_ns = self._last_timestamp_ns - reference.timestamp_ns
        chained = self._estimation.plausible(chained, prediction, span_ns)
        step = chained.reference_from_current
        if step is None or chained.covariance is None:
            return estimate, False
        step_covariance = chained.covariance + self._link_bias(chained)
        fused = combine_chain(
            Measured(measured, estimate.covariance, *sensitivities_of(estimate)),
            link,
            Measured(step, step_covariance, *sensitivities_of(chained)),
        )
        if fused is not None:
            # The same motion-proportional error that a link carries (``_link_bias``) is in
            # the keyframe measurement too, and the blur of the current frame behind it errs
            # both estimates alike: the combination cannot average it out. Its covariance is
            # counted once on top of the combination's for the report and the back end; the
            # next frame's link takes the combination's alone (its own bias is added then).
            common = self._link_bias(estimate, self._common_rate)
            estimate.reference_from_current = fused.pose
            estimate.chain_covariance = fused.covariance
            estimate.covariance = fused.covariance + common
            estimate.sensitivity, estimate.reference_sensitivity = fused.current, fused.reference
            estimate.reported_covariance = None  # the combination's is the one to report
        return estimate, True

    def _moving(self, estimate: Estimate) -> bool:
        """Whether the keyframe measurement's inliers moved ``frontend.chain_min_flow_px`` or
        more in the image (median): the chain through the previous frame pays only then."""
        threshold = self.config.frontend.chain_min_flow_px
        if threshold == 0.0:
            return True
        moved = self._inlier_flow(estimate)
        return len(moved) > 0 and float(np.median(moved)) >= threshold

    def _link_bias(self, chained: Estimate, rate: float | None = None) -> np.ndarray:
        """Covariance of a measurement's rotation error that does not average out over its
        points, from its inliers' image motion (``frontend.chain_link_rotation_bias``,
        chains.py): for a chain link, and for the keyframe measurement it is combined with."""
        if rate is None:
            rate = self.config.frontend.chain_link_rotation_bias
        if rate == 0.0:
            return np.zeros((6, 6))
        return link_bias_covariance(rate, self._inlier_flow(chained), self.rectification.fx)

    def _inlier_flow(self, estimate: Estimate) -> np.ndarray:
        """(N,) image motion (px) of the estimate's inliers; empty when it has none."""
        if estimate.pairs is None or estimate.result is None:
            return np.zeros(0)
        inliers = estimate.result.inliers
        pairs = estimate.pairs
        return flow(
            pairs.current_points[inliers], pairs.reference_points[inliers], self.rectification
        )

    def _estimate_against(
        self,
        reference: Reference,
        predicted_reference_from_current: np.ndarray,
        points: StereoPoints,
        image: np.ndarray,
        timings: dict[str, float],
        uncertainty: PredictionUncertainty | None = None,
    ) -> Estimate:
        return self._estimation.against(
            reference, predicted_reference_from_current, points, image, timings, self._index,
            uncertainty,
        )  # fmt: skip

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
        frontend_pose: np.ndarray,
        relative_pose: np.ndarray,
        estimate: Estimate,
        status: FrameStatus,
        message: str,
    ) -> tuple[np.ndarray, FrameStatus, str]:
        """Back-end pose and status (the front-end ones when the back end is off)."""
        if self._backend is None:
            return frontend_pose, status, message
        first = self._references.reference is None
        if first:
            measurement = Measurement(relative_pose=relative_pose)
        elif estimate.reference_from_current is None:
            measurement = Measurement()
        else:
            landmarks = self.config.backend.landmarks
            noise = self._estimation.noise if landmarks else None
            measurement = self._frames.measurement(estimate, noise)
        fused = self._backend.add_frame(
            int(frame.timestamp_ns),
            relative_pose=measurement.relative_pose,
            inlier_residuals=measurement.inlier_residuals,
            inlier_count=measurement.inlier_count,
            imu=imu,
            reference_ns=measurement.reference_ns,
            inlier_points=measurement.inlier_points,
            covariance=measurement.covariance,
            stereo=measurement.stereo,
        )
        self._fused = fused
        if first:
            self._world_from_backend = frontend_pose @ invert_pose(fused.pose)
            if self._initial_pose is None:
                self._world_from_backend = np.eye(4)
        self._final_poses = self._in_world(fused.final_poses)
        text = "; ".join(part for part in (message, fused.message) if part)
        return self._world_from_backend @ fused.pose, fused.status, text

    def _report(
        self,
        frame: StereoFrame,
        answer: tuple[np.ndarray, np.ndarray, np.ndarray, FrameStatus, str],
        estimate: Estimate,
        timings: dict[str, float],
    ) -> FrameReport:
        """The frame's report: the answer (pose, front-end pose, relative pose, status,
        message) with the estimate's matches, covariance and the back end's marginals."""
        pose, frontend_pose, relative_pose, status, message = answer
        result, pairs, fused = estimate.result, estimate.pairs, self._fused
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
            final_poses=self._final_poses,
            measurement_covariance=covariance,
            reference_timestamp_ns=estimate.reference.timestamp_ns if measured else None,
            body_covariance=fused.body_covariance if fused is not None else None,
            body_motion=fused.body_motion if fused is not None else None,
            body_motion_covariance=fused.body_motion_covariance if fused is not None else None,
            covariance_scale=fused.covariance_scale if fused is not None else 1.0,
            pose_covariance_scale=fused.pose_covariance_scale if fused is not None else 1.0,
        )
