"""The estimate step: temporal matches -> rigid registration -> Mahalanobis refinement, the
plausibility check against the predicted motion, and the session's noise level it learns."""

from __future__ import annotations

import functools

import numpy as np

from estimator.config import SwarmvoConfig
from estimator.formats.calibration import Rectification
from estimator.frontend.disparity_offset import aligned
from estimator.frontend.stereo_noise import StereoNoiseModel
from estimator.frontend.temporal import Correspondences, PredictionUncertainty, match_temporal
from estimator.frontend.tracks import match_tracks
from estimator.geometry import invert_pose, make_pose, rotation_angle_deg
from estimator.odometry.chains import PointSensitivity
from estimator.odometry.frames import (
    CurrentFrame,
    Estimate,
    Reference,
    failed,
    frame_seed,
    stage,
)
from estimator.odometry.observation import MeasurementKind, MeasurementObserver, observed
from estimator.registration.refine import (
    RefinementResult,
    refine_pose_mahalanobis,
    residual_spread,
    squared_mahalanobis,
)
from estimator.registration.registry import estimator_spec, register
from estimator.registration.sensitivity import point_sensitivities

__all__ = ["PoseEstimation"]


class PoseEstimation:
    """Relative poses of frames against references, weighed by the measured stereo noise."""

    def __init__(
        self,
        config: SwarmvoConfig,
        rectification: Rectification,
        noise: StereoNoiseModel,
        sensitivities: bool = False,
        observer: MeasurementObserver | None = None,
    ) -> None:
        self.config = config
        self.rectification = rectification
        self.noise = noise
        # The points' sensitivities, which only the chain combinations use (chains.py).
        self.sensitivities = sensitivities
        self.observer = observer

    def measured(
        self,
        reference: Reference,
        prediction: np.ndarray,
        current: CurrentFrame,
        span_ns: int,
        uncertainty: PredictionUncertainty | None = None,
    ) -> Estimate:
        """T_ref_cur of the ``current`` frame against ``reference``, failed when implausible
        against ``prediction`` (extrapolated over ``span_ns``); the observer sees it first."""
        estimate = self.against(reference, prediction, current, uncertainty)
        self.observe(MeasurementKind.REGISTRATION, estimate, current)
        return self.plausible(estimate, prediction, span_ns)

    def observe(self, kind: MeasurementKind, estimate: Estimate, current: CurrentFrame) -> None:
        """Show the observer (if any) ``estimate`` as a measurement of ``kind``."""
        if self.observer is not None:
            self.observer(observed(kind, estimate, current, self.noise))

    def against(
        self,
        reference: Reference,
        predicted_reference_from_current: np.ndarray,
        current: CurrentFrame,
        uncertainty: PredictionUncertainty | None = None,
    ) -> Estimate:
        """T_ref_cur of the ``current`` frame; ``uncertainty`` of the prediction sizes the
        search windows (None: a wide search)."""
        points, image, timings = current.points, current.image, current.timings
        # The reference's disparities with the current frame's offset taken out of them.
        reference_points = aligned(reference.points, points.disparity_offset_px, self.rectification)
        with stage(timings, "temporal"):
            if self.config.frontend.mode == "track":
                pairs = match_tracks(
                    reference_points, points, self.config.frontend, self.rectification,
                    images=(reference.image, image),
                )  # fmt: skip
            else:
                pairs = match_temporal(
                    reference_points,
                    points,
                    self.config.frontend,
                    self.rectification,
                    predicted_current_from_reference=invert_pose(predicted_reference_from_current),
                    images=(reference.image, image),
                    uncertainty=uncertainty,
                )
        with stage(timings, "estimate"):
            covariances = (
                self.noise.covariances(pairs.current_points),
                self.noise.covariances(pairs.reference_points),
            )
            estimate = self._estimate(pairs, covariances, current.index)
            estimate.point_covariances = covariances
            if self.config.registration.mahalanobis_refine:
                estimate = self._refine(estimate, pairs)
        estimate.pairs, estimate.reference = pairs, reference
        return estimate

    def plausible(self, estimate: Estimate, prediction: np.ndarray, span_ns: int) -> Estimate:
        """The estimate, or a failed one when its rotation is further from the predicted
        reference_from_current than ``frontend.max_rotation_surprise_deg_s`` over the
        ``span_ns`` the prediction extrapolates (a camera cannot turn that much faster at
        once; a wrong fit with a flipped rotation can)."""
        rate = self.config.frontend.max_rotation_surprise_deg_s
        measured = estimate.reference_from_current
        if rate is None or measured is None:
            return estimate
        surprise = rotation_angle_deg(prediction[:3, :3].T @ measured[:3, :3])
        allowed = rate * max(span_ns, 1) * 1e-9
        if surprise <= allowed:
            return estimate
        return failed(
            estimate,
            f"implausible rotation: {surprise:.1f} deg from the constant-velocity prediction "
            f"(> {allowed:.1f})",
        )

    def measure_noise(self, estimate: Estimate) -> None:
        """Fold this frame's inlier residuals into the session's noise level."""
        pairs, result, pose = estimate.pairs, estimate.result, estimate.reference_from_current
        if pairs is None or result is None or pose is None:
            return
        if self.config.registration.noise_model == "fixed":
            return
        inliers = result.inliers
        # The estimate's point covariances are at the level the update starts from (the level
        # changes only here, after every estimate of the frame): its check reuses them.
        covariances = None
        if estimate.point_covariances is not None:
            current_cov, reference_cov = estimate.point_covariances
            covariances = (current_cov[inliers], reference_cov[inliers])
        self.noise.update(
            pairs.reference_points[inliers], pairs.current_points[inliers], pose[:3, :3],
            pose[:3, 3], covariances,
        )  # fmt: skip

    def _estimate(
        self,
        correspondences: Correspondences,
        covariances: tuple[np.ndarray, np.ndarray],
        index: int,
    ) -> Estimate:
        """Rigid registration: reference points ~ R current points + t (T_ref_cur)."""
        frontend = self.config.frontend
        needed = frontend.min_matches
        if len(correspondences) < needed:
            return Estimate(None, None, f"{len(correspondences)} temporal matches (< {needed})")
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
            seed=frame_seed(self.config.seed, index),
            **options,
        )
        inliers = int(result.inliers.sum())
        if not result.success:
            return Estimate(None, result, f"registration failed: {result.message}")
        if inliers < needed:
            return Estimate(None, result, f"{inliers} registration inliers (< {needed})")
        if inliers < frontend.min_inlier_ratio * len(correspondences):
            # Matches that passed the ratio and mutual checks are mostly right in a static
            # scene; a pose that explains only a sliver of them is a failed search.
            return Estimate(
                None,
                result,
                f"only {inliers} of {len(correspondences)} matches are inliers "
                f"(< {frontend.min_inlier_ratio:.0%})",
            )
        pose = make_pose(result.rotation, result.translation)
        return Estimate(pose, result, "")

    def _refine(self, estimate: Estimate, correspondences: Correspondences) -> Estimate:
        """Maximum-likelihood pose on the registration inliers, each point weighed by its full
        stereo covariance (uncertain along the ray); the inlier set stays the estimator's.
        When the refinement cannot improve on the registration its pose is kept."""
        if estimate.reference_from_current is None or estimate.result is None:
            return estimate
        assert estimate.point_covariances is not None
        registration = self.config.registration
        inliers = estimate.result.inliers
        current_cov, reference_cov = estimate.point_covariances
        pairs = (
            correspondences.current_points[inliers],
            correspondences.reference_points[inliers],
            current_cov[inliers],
            reference_cov[inliers],
        )
        start = (estimate.reference_from_current[:3, :3], estimate.reference_from_current[:3, 3])
        robust_scale = registration.refine_robust_scale
        if registration.refine_scale_from_residuals:
            # Narrower only: a wider kernel would let in what an estimator without a
            # Mahalanobis support test (msac, svd) left among its inliers.
            robust_scale *= min(_spread(pairs, start), 1.0)
        refined = refine_pose_mahalanobis(
            *pairs,
            *start,
            iterations=registration.refine_iterations,
            robust=registration.refine_robust,
            robust_scale=robust_scale,
            sandwich=registration.refine_covariance != "median",
        )
        if refined.success:
            estimate.reference_from_current = make_pose(refined.rotation, refined.translation)
            estimate.covariance = refined.covariance
            robust = refined.sandwich_covariance  # None with too few pairs: the median one
            if robust is not None and registration.refine_covariance == "sandwich":
                estimate.covariance = robust
            elif robust is not None and registration.refine_covariance == "sandwich-reported":
                estimate.reported_covariance = robust
            if self.sensitivities:
                estimate.pending_sensitivity = functools.partial(
                    self._sensitivities, estimate, correspondences, pairs, refined, robust_scale
                )
        return estimate

    def _sensitivities(
        self,
        estimate: Estimate,
        correspondences: Correspondences,
        pairs: tuple[np.ndarray, ...],
        refined: RefinementResult,
        robust_scale: float,
    ) -> None:
        """How the refined pose moves with the current and the reference inlier points
        (``pairs``: the refinement's inlier points and covariances; ``robust_scale``: its
        kernel's), scaled like its covariance (estimator/odometry/chains.py weighs the chains
        sharing them by it)."""
        assert estimate.result is not None
        registration = self.config.registration
        inliers = estimate.result.inliers
        current_cov, reference_cov = pairs[2], pairs[3]  # already the inliers'
        gains = point_sensitivities(
            *pairs,
            refined.rotation,
            refined.translation,
            robust=registration.refine_robust,
            robust_scale=robust_scale,
        )
        if gains is None:
            return
        scale = np.sqrt(refined.variance_factor)
        estimate.sensitivity = PointSensitivity(
            correspondences.current_index[inliers], gains[0] * scale, current_cov
        )
        estimate.reference_sensitivity = PointSensitivity(
            correspondences.reference_index[inliers], gains[1] * scale, reference_cov
        )


def _spread(pairs: tuple[np.ndarray, ...], pose: tuple[np.ndarray, np.ndarray]) -> float:
    """The inliers' own spread at the registration's pose (refine.residual_spread); 1 where a
    point covariance is singular (the refinement then reports it and keeps the pose)."""
    try:
        return residual_spread(squared_mahalanobis(*pairs, *pose))
    except np.linalg.LinAlgError:
        return 1.0
