"""The stereo odometry pipeline: one stereo frame in, one pose report out.

Per frame: rectify -> detect -> match stereo -> triangulate -> match in time -> estimate the
relative pose by rigid 3D-3D registration (optionally refined on its inliers with the full
stereo point covariances, ``registration.mahalanobis_refine``) -> chain it onto the reference
pose -> fuse with the IMU in the back end. Frames are matched against a *reference*: by default
a keyframe that is kept while the view still overlaps well, so that standing still (or hovering)
measures the same relative pose again and again instead of integrating frame-to-frame noise into
a creeping drift; ``frontend.tracking = "frame"`` matches against the previous frame instead.

Geometry runs in the rectified left camera frame; reported poses are of the original
(unrectified) left camera, so the relative pose is conjugated by the rectifying rotation.
When the keyframe cannot be tracked the previous frame is tried before giving up. A frame
without any estimate coasts at the last measured velocity (``degraded``) for at most
``frontend.max_coast_frames`` frames, after which the pose is held (``lost``). While it
coasts, the next frame is matched against the last good references at once (predictions scale
with the time between frames); once the pose is held, a frame with enough points becomes the
new reference, so tracking restarts from it. With the back end enabled, the fused
pose and status are the back end's (it bridges such frames with the IMU).
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import cv2
import numpy as np

from estimator.config import SwarmvoConfig
from estimator.formats.calibration import StereoRig
from estimator.frontend.features import FeatureDetector
from estimator.frontend.photometric import normalise_contrast
from estimator.frontend.stereo import StereoMatcher, StereoPoints
from estimator.frontend.stereo_noise import NoiseLevel, StereoNoiseModel
from estimator.frontend.temporal import Correspondences, match_temporal
from estimator.geometry import (
    invert_pose,
    make_pose,
    nearest_rigid,
    rotation_angle_deg,
    scale_motion,
    transform_points,
)
from estimator.registration.refine import refine_pose_mahalanobis
from estimator.registration.registry import RegistrationResult, estimator_spec, register
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

__all__ = ["Odometry", "frame_seed", "to_grey8"]


def frame_seed(seed: int, index: int) -> int:
    """Estimator seed of frame ``index``: reproducible in any process, distinct per frame."""
    return int(np.random.SeedSequence([seed, index]).generate_state(1)[0])


def to_grey8(image: np.ndarray, name: str = "image") -> np.ndarray:
    """8-bit grey from grey / BGR / BGRA images of 8 or 16 bits (16-bit scaled by 1/257)."""
    image = np.asarray(image)
    if image.dtype not in (np.uint8, np.uint16):
        raise ValueError(f"{name} must be uint8 or uint16, got {image.dtype}")
    if image.ndim == 3 and image.shape[2] == 1:
        image = image[:, :, 0]
    if image.ndim == 3 and image.shape[2] in (3, 4):
        code = cv2.COLOR_BGR2GRAY if image.shape[2] == 3 else cv2.COLOR_BGRA2GRAY
        image = cv2.cvtColor(image, code)
    if image.ndim != 2:
        raise ValueError(f"{name} must be (H, W) grey or (H, W, 3|4) colour, got {image.shape}")
    if image.dtype == np.uint16:
        image = (image.astype(np.uint32) * 255 + 32767) // 65535  # full range onto 0..255
    return np.ascontiguousarray(image, dtype=np.uint8)


@dataclass
class _Reference:
    """The frame the current one is matched against, with its front-end pose."""

    index: int
    timestamp_ns: int
    points: StereoPoints
    image: np.ndarray  # rectified left image
    pose: np.ndarray  # left camera in world (original camera frame)


@dataclass
class _Estimate:
    """A relative pose of the current frame w.r.t. the reference, or why there is none."""

    reference_from_current: np.ndarray | None  # rectified frames; None when the estimate failed
    result: RegistrationResult | None
    message: str
    pairs: Correspondences | None = None
    reference: _Reference | None = None  # the frame it was measured against
    # 6x6 of (rotation, translation), right perturbation, when the pose was refined.
    covariance: np.ndarray | None = None
    # (N, 3, 3) covariances of the current and reference points of ``pairs``.
    point_covariances: tuple[np.ndarray, np.ndarray] | None = None


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
        self._rect_from_camera = make_pose(self.rectification.R_left, np.zeros(3))
        self._camera_from_rect = invert_pose(self._rect_from_camera)
        self._initial_pose = _checked_pose(initial_pose) if initial_pose is not None else None
        self._backend = self._make_backend(imu_noise) if self.config.backend.enabled else None
        self._world_from_backend = np.eye(4)  # anchors the back end's world on initial_pose
        self._index = int(first_index) - 1
        self._count = 0
        self._last_timestamp_ns: int | None = None
        self._pose = self._initial_pose if self._initial_pose is not None else np.eye(4)
        self._reference: _Reference | None = None  # keyframe (or previous frame)
        self._previous: _Reference | None = None  # the last frame with an estimate
        self._fallback: _Reference | None = None  # a later failed frame with enough points
        self._reference_from_previous = np.eye(4)  # rectified; for predicting the search
        self._motion = np.eye(4)  # last measured motion (rectified), constant velocity ...
        self._motion_interval_ns = 1  # ... over this time: predictions scale it to theirs
        self._frame_interval_ns = 0  # time since the previous frame
        self._failures = 0  # consecutive frames without a vision estimate
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

    def _make_backend(self, imu_noise: ImuNoise | None):
        from estimator.backend import FusionBackend  # GTSAM loads only when the back end runs

        return FusionBackend(
            self.config.backend, body_from_camera=self.rig.left.T_BS, imu_noise=imu_noise
        )

    @property
    def frame_count(self) -> int:
        return self._count

    @property
    def reference_index(self) -> int | None:
        """Index of the frame the next one is matched against (None before the first frame).

        Each keyframe is measured once against the previous keyframe, so the errors of those
        measurements are independent and their sum is the drift: evaluations need to know them.
        """
        return self._reference.index if self._reference is not None else None

    # ------------------------------------------------------------------ continuing elsewhere

    def state(self) -> dict[str, Any]:
        """What another process needs to continue this run after its last frame (JSON-ready).

        The last answered pose and its keyframe's pose, the measured motion (the velocity that
        predicts the next frame) and the back end's biases: the continuation predicts its first
        frame at constant velocity from here instead of restarting at rest.
        """
        keyframe = self._reference.pose if self._reference is not None else self._pose
        return {
            "index": self._index,
            "timestamp_ns": self._last_timestamp_ns,
            "pose": self._answered.tolist(),
            "keyframe_pose": keyframe.tolist(),
            "motion": self._motion.tolist(),
            "motion_interval_ns": self._motion_interval_ns,
            "backend": self._backend.state() if self._backend is not None else None,
        }

    def restore(self, state: dict[str, Any]) -> None:
        """Continue from :meth:`state` of another instance (before this one saw any frame)."""
        if self._count:
            raise ValueError("restore() must come before the first frame")
        self._index = int(state["index"])
        self._last_timestamp_ns = state["timestamp_ns"]
        self._pose = _checked_pose(np.array(state["pose"], dtype=float))
        self._initial_pose = self._pose
        self._motion = nearest_rigid(np.array(state["motion"], dtype=float))
        self._motion_interval_ns = max(int(state["motion_interval_ns"]), 1)
        if self._backend is not None and state.get("backend"):
            self._backend.restore(state["backend"])
        self._restored = True

    # ------------------------------------------------------------------ the algorithm

    def process(self, frame: StereoFrame, imu: ImuBatch | None = None) -> FrameReport:
        """Pose of the left camera at ``frame``; ``imu`` holds the samples since the last frame."""
        timings: dict[str, float] = {}
        with _stage(timings, "total"):
            left, right = self._validated(frame)
            self._index += 1
            self._count += 1
            with _stage(timings, "rectify"):
                left, right = self.rectification.rectify(left, right)
                left, right = self._normalised(left), self._normalised(right)
            with _stage(timings, "detect"):
                left_features = self.detector.detect(left)
                right_features = self.detector.detect(right)
            with _stage(timings, "stereo"):
                points = self.stereo.match(left_features, right_features, left, right)
            if self._reference is None:
                estimate = _Estimate(None, None, "")
            else:
                estimate = self._track(points, left, timings)
                self._measure_noise(estimate)
            previous_pose = self._pose
            frontend_pose, status, message = self._chain(estimate)
            relative_pose = invert_pose(previous_pose) @ frontend_pose
            with _stage(timings, "fuse"):
                pose, status, message = self._fuse(
                    frame, imu, frontend_pose, relative_pose, estimate, status, message
                )
            self._answered = pose
            self._update_reference(points, left, frontend_pose, estimate, frame.timestamp_ns)
        result, pairs, fused = estimate.result, estimate.pairs, self._fused
        measured = estimate.reference_from_current is not None and estimate.reference is not None
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
            measurement_covariance=self._report_covariance(estimate) if measured else None,
            reference_timestamp_ns=estimate.reference.timestamp_ns if measured else None,
            body_covariance=fused.body_covariance if fused is not None else None,
            body_motion=fused.body_motion if fused is not None else None,
            body_motion_covariance=fused.body_motion_covariance if fused is not None else None,
            covariance_scale=fused.covariance_scale if fused is not None else 1.0,
        )

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

    def _normalised(self, image: np.ndarray) -> np.ndarray:
        frontend = self.config.frontend
        if not frontend.normalise_contrast:
            return image
        return normalise_contrast(image, frontend.normalised_mean, frontend.normalised_std)

    def _track(
        self, points: StereoPoints, image: np.ndarray, timings: dict[str, float]
    ) -> _Estimate:
        """Relative pose against the keyframe; if that fails, against the previous good frame,
        and then against the last failed frame that had points (its pose coasted)."""
        assert self._reference is not None and self._previous is not None
        assert self._last_timestamp_ns is not None
        since_previous = self._motion_over(self._last_timestamp_ns - self._previous.timestamp_ns)
        keyframe_prediction = self._reference_from_previous @ since_previous
        estimate = self._estimate_against(
            self._reference, keyframe_prediction, points, image, timings
        )
        retries = [(self._previous, since_previous, "the previous frame")]
        if self._fallback is not None:
            since_fallback = self._last_timestamp_ns - self._fallback.timestamp_ns
            retries.append(
                (self._fallback, self._motion_over(since_fallback), "the last frame with points")
            )
        for reference, prediction, name in retries:
            if estimate.reference_from_current is not None or reference is self._reference:
                continue
            retry = self._estimate_against(reference, prediction, points, image, timings)
            if retry.reference_from_current is not None:
                retry.message = (
                    f"keyframe {self._reference.index} not tracked ({estimate.message}); "
                    f"tracked against {name}"
                )
                return retry
        return estimate

    def _estimate_against(
        self,
        reference: _Reference,
        predicted_reference_from_current: np.ndarray,
        points: StereoPoints,
        image: np.ndarray,
        timings: dict[str, float],
    ) -> _Estimate:
        with _stage(timings, "temporal"):
            pairs = match_temporal(
                reference.points,
                points,
                self.config.frontend,
                self.rectification,
                predicted_current_from_reference=invert_pose(predicted_reference_from_current),
                images=(reference.image, image),
            )
        with _stage(timings, "estimate"):
            covariances = (
                self.noise.covariances(pairs.current_points),
                self.noise.covariances(pairs.reference_points),
            )
            estimate = self._estimate(pairs, covariances)
            estimate.point_covariances = covariances
            if self.config.registration.mahalanobis_refine:
                estimate = self._refine(estimate, pairs)
        estimate.pairs, estimate.reference = pairs, reference
        return estimate

    def _estimate(
        self, correspondences: Correspondences, covariances: tuple[np.ndarray, np.ndarray]
    ) -> _Estimate:
        """Rigid registration: reference points ~ R current points + t (T_ref_cur)."""
        frontend = self.config.frontend
        needed = frontend.min_matches
        if len(correspondences) < needed:
            return _Estimate(None, None, f"{len(correspondences)} temporal matches (< {needed})")
        registration = self.config.registration
        options: dict[str, object] = dict(registration.options)
        if registration.use_point_sigmas and estimator_spec(registration.method).takes_covariances:
            options["source_cov"], options["target_cov"] = covariances
            gate = self.noise.gate_for(
                correspondences.current_points, correspondences.reference_points
            )
            options.setdefault("gate_chi2", gate)
        result = register(
            correspondences.current_points,
            correspondences.reference_points,
            method=registration.method,
            seed=frame_seed(self.config.seed, self._index),
            **options,
        )
        inliers = int(result.inliers.sum())
        if not result.success:
            return _Estimate(None, result, f"registration failed: {result.message}")
        if inliers < needed:
            return _Estimate(None, result, f"{inliers} registration inliers (< {needed})")
        if inliers < frontend.min_inlier_ratio * len(correspondences):
            # Matches that passed the ratio and mutual checks are mostly right in a static
            # scene; a pose that explains only a sliver of them is a failed search.
            return _Estimate(
                None,
                result,
                f"only {inliers} of {len(correspondences)} matches are inliers "
                f"(< {frontend.min_inlier_ratio:.0%})",
            )
        pose = make_pose(result.rotation, result.translation)
        return _Estimate(pose, result, "")

    def _refine(self, estimate: _Estimate, correspondences: Correspondences) -> _Estimate:
        """Maximum-likelihood pose on the registration inliers, each point weighed by its full
        stereo covariance (uncertain along the ray); the inlier set stays the estimator's.
        When the refinement cannot improve on the registration its pose is kept."""
        if estimate.reference_from_current is None or estimate.result is None:
            return estimate
        assert estimate.point_covariances is not None
        registration = self.config.registration
        inliers = estimate.result.inliers
        current_cov, reference_cov = estimate.point_covariances
        refined = refine_pose_mahalanobis(
            correspondences.current_points[inliers],
            correspondences.reference_points[inliers],
            current_cov[inliers],
            reference_cov[inliers],
            estimate.reference_from_current[:3, :3],
            estimate.reference_from_current[:3, 3],
            iterations=registration.refine_iterations,
            robust=registration.refine_robust,
            robust_scale=registration.refine_robust_scale,
        )
        if refined.success:
            estimate.reference_from_current = make_pose(refined.rotation, refined.translation)
            estimate.covariance = refined.covariance
        return estimate

    def _measure_noise(self, estimate: _Estimate) -> None:
        """Fold this frame's inlier residuals into the session's noise level."""
        pairs, result, pose = estimate.pairs, estimate.result, estimate.reference_from_current
        if pairs is None or result is None or pose is None:
            return
        if self.config.registration.noise_model == "fixed":
            return
        inliers = result.inliers
        self.noise.update(
            pairs.reference_points[inliers], pairs.current_points[inliers], pose[:3, :3],
            pose[:3, 3],
        )  # fmt: skip

    def _chain(self, estimate: _Estimate) -> tuple[np.ndarray, FrameStatus, str]:
        """pose_k = pose_ref @ T_ref_cur (paper eq. 2), in the original left camera frame."""
        if self._reference is None and self._restored:
            step = self._motion_over(self._frame_interval_ns)
            motion = self._camera_from_rect @ step @ self._rect_from_camera
            return self._pose @ motion, FrameStatus.OK, "resumed from stored state"
        if self._reference is None:
            message = (
                "resumed from stored pose"
                if self._initial_pose is not None
                else ("first frame: world = this left camera")
            )
            return self._pose, FrameStatus.OK, message
        if estimate.reference_from_current is None or estimate.reference is None:
            if self._failures < self.config.frontend.max_coast_frames:
                # Constant velocity: a moving camera keeps moving; a still one stays still.
                step = self._motion_over(self._frame_interval_ns)
                motion = self._camera_from_rect @ step @ self._rect_from_camera
                message = f"{estimate.message}; pose predicted at constant velocity"
                return self._pose @ motion, FrameStatus.DEGRADED, message
            return self._pose, FrameStatus.LOST, f"{estimate.message}; pose held"
        reference_from_current = self._reference_from_current(estimate)
        return estimate.reference.pose @ reference_from_current, FrameStatus.OK, estimate.message

    def _fuse(
        self,
        frame: StereoFrame,
        imu: ImuBatch | None,
        frontend_pose: np.ndarray,
        relative_pose: np.ndarray,
        estimate: _Estimate,
        status: FrameStatus,
        message: str,
    ) -> tuple[np.ndarray, FrameStatus, str]:
        """Back-end pose and status (the front-end ones when the back end is off)."""
        if self._backend is None:
            return frontend_pose, status, message
        failed = estimate.reference_from_current is None
        first = self._reference is None
        residuals = None
        inliers = 0
        measured: np.ndarray | None = None
        reference_ns = None
        points = None
        covariance = None
        if first:
            measured = relative_pose
        elif not failed:
            assert estimate.result is not None and estimate.reference is not None
            inliers = int(estimate.result.inliers.sum())
            residuals = self._inlier_residuals(estimate)
            # The measurement itself, T_ref_cur against the frame it was made from: the back
            # end ties the two frames directly instead of through the poses in between.
            measured = self._reference_from_current(estimate)
            reference_ns = estimate.reference.timestamp_ns
            points = self._inlier_points(estimate)
            covariance = self._measurement_covariance(estimate)
        fused = self._backend.add_frame(
            int(frame.timestamp_ns),
            relative_pose=measured,
            inlier_residuals=residuals,
            inlier_count=inliers,
            imu=imu,
            reference_ns=reference_ns,
            inlier_points=points,
            covariance=covariance,
        )
        self._fused = fused
        if first:
            self._world_from_backend = frontend_pose @ invert_pose(fused.pose)
            if self._initial_pose is None:
                self._world_from_backend = np.eye(4)
        self._final_poses = self._in_world(fused.final_poses)
        text = "; ".join(part for part in (message, fused.message) if part)
        return self._world_from_backend @ fused.pose, fused.status, text

    def _measurement_covariance(self, estimate: _Estimate) -> np.ndarray | None:
        """The refinement's 6x6 covariance, rotated from the rectified into the camera frame.

        The rectifying transform is a pure rotation, whose adjoint rotates both the rotation and
        the translation block of the (right-perturbation) tangent.
        """
        if estimate.covariance is None:
            return None
        rotation = self._camera_from_rect[:3, :3]
        adjoint = np.zeros((6, 6))
        adjoint[:3, :3] = adjoint[3:, 3:] = rotation
        return adjoint @ estimate.covariance @ adjoint.T

    def _report_covariance(self, estimate: _Estimate) -> np.ndarray:
        """Covariance of the measured T_ref_cur as the back end weighs it: the refinement's,
        else the rigid fit's from the inlier points, scaled and floored by ``config.backend``."""
        from estimator.backend.noise import fit_covariance, measured_covariance

        covariance = self._measurement_covariance(estimate)
        if covariance is not None:
            return measured_covariance(covariance, self.config.backend)
        points, residuals = self._inlier_points(estimate), self._inlier_residuals(estimate)
        return fit_covariance(points, residuals, self.config.backend)

    def _reference_from_current(self, estimate: _Estimate) -> np.ndarray:
        """T_ref_cur of the original left camera (the estimate is in rectified frames)."""
        assert estimate.reference_from_current is not None
        return self._camera_from_rect @ estimate.reference_from_current @ self._rect_from_camera

    def _inlier_points(self, estimate: _Estimate) -> np.ndarray:
        """The registration inliers of the current frame in its (original) left camera frame:
        their spread and lever arm give the back end the full covariance of the fit."""
        pairs, result = estimate.pairs, estimate.result
        assert pairs is not None and result is not None
        return transform_points(self._camera_from_rect, pairs.current_points[result.inliers])

    def _inlier_residuals(self, estimate: _Estimate) -> np.ndarray:
        """||p - (R q + t)|| of the registration inliers (metres), for the back-end covariance."""
        pairs, result = estimate.pairs, estimate.result
        assert pairs is not None and result is not None
        assert estimate.reference_from_current is not None
        mask = result.inliers
        moved = transform_points(estimate.reference_from_current, pairs.current_points[mask])
        return np.linalg.norm(pairs.reference_points[mask] - moved, axis=1)

    def _update_reference(
        self,
        points: StereoPoints,
        image: np.ndarray,
        pose: np.ndarray,
        estimate: _Estimate,
        timestamp_ns: int,
    ) -> None:
        """Keep the keyframe while it still tracks well; otherwise this frame becomes it.

        A failed frame (black, blurred, or just not registered) replaces neither the keyframe
        nor the previous frame while the pose coasts: the next frame is matched against the
        last good ones at once, with the prediction scaled to the time since them, so the
        failure does not reach later frames. A failed frame with enough points is kept as a
        last resort (when the view has moved on, the next frame may only match it); once the
        pose is held such a frame becomes the new reference, so that tracking restarts.
        """
        frontend = self.config.frontend
        self._pose = pose
        current = _Reference(self._index, int(timestamp_ns), points, image, pose)
        reference_from_current = estimate.reference_from_current
        first = self._reference is None
        failed = reference_from_current is None and not first
        self._failures = self._failures + 1 if failed else 0
        if failed:
            held = self._failures > frontend.max_coast_frames
            if held:
                self._motion = np.eye(4)  # the pose is held from now on
            usable = len(points) >= frontend.keyframe_min_inliers
            if usable:
                self._fallback = current  # the last resort if the good references fail
            if not held or not usable:
                return  # keep the last good references
        elif reference_from_current is not None:
            assert self._previous is not None and estimate.reference is not None
            if estimate.reference is self._reference:
                self._motion = invert_pose(self._reference_from_previous) @ reference_from_current
                since_ns = self._previous.timestamp_ns
            else:
                self._motion = reference_from_current  # measured against a later frame
                since_ns = estimate.reference.timestamp_ns
            self._motion_interval_ns = max(int(timestamp_ns) - since_ns, 1)
        self._fallback = None
        if first or failed or self._needs_new_reference(estimate):
            self._reference = current
            self._reference_from_previous = np.eye(4)
        else:
            assert reference_from_current is not None
            self._reference_from_previous = reference_from_current
        self._previous = current

    def _motion_over(self, interval_ns: int) -> np.ndarray:
        """The last measured motion at the same velocity over ``interval_ns`` (rectified)."""
        return scale_motion(self._motion, interval_ns / self._motion_interval_ns)

    def _needs_new_reference(self, estimate: _Estimate) -> bool:
        frontend = self.config.frontend
        if frontend.tracking == "frame" or estimate.reference is not self._reference:
            return True
        motion = estimate.reference_from_current
        assert estimate.result is not None and motion is not None
        return bool(
            estimate.result.inliers.sum() < frontend.keyframe_min_inliers
            or np.linalg.norm(motion[:3, 3]) > frontend.keyframe_max_translation_m
            or rotation_angle_deg(motion[:3, :3]) > frontend.keyframe_max_rotation_deg
        )


def _checked_pose(pose: np.ndarray) -> np.ndarray:
    matrix = np.asarray(pose, dtype=float)
    if matrix.shape != (4, 4) or not np.isfinite(matrix).all():
        raise ValueError(f"initial_pose must be a finite 4x4 matrix, got shape {matrix.shape}")
    rotation = matrix[:3, :3]
    if (
        np.abs(rotation.T @ rotation - np.eye(3)).max() > 1e-6
        or np.linalg.det(rotation) < 0
        or not np.allclose(matrix[3], [0, 0, 0, 1])
    ):
        raise ValueError("initial_pose must be a rigid transform (rotation block orthonormal)")
    return matrix


@contextmanager
def _stage(timings: dict[str, float], name: str) -> Iterator[None]:
    start = time.perf_counter()
    try:
        yield
    finally:
        timings[name] = timings.get(name, 0.0) + time.perf_counter() - start
