"""A rectified estimate as the back end and the frame reports take it: in the original left
camera frame, with its inlier points, residuals and covariance."""

from __future__ import annotations

from dataclasses import dataclass, fields
from typing import TYPE_CHECKING, Any

import numpy as np

from estimator.config import BackendConfig
from estimator.formats.calibration import Rectification
from estimator.geometry import invert_pose, make_pose, transform_points
from estimator.odometry.frames import Estimate

if TYPE_CHECKING:
    from estimator.backend.observations import StereoObservations
    from estimator.frontend.stereo_noise import StereoNoiseModel

__all__ = ["CameraFrames", "Measurement"]


@dataclass
class Measurement:
    """What the back end's ``add_frame`` takes of one frame's vision (nothing: no estimate)."""

    relative_pose: np.ndarray | None = None
    inlier_residuals: np.ndarray | None = None
    inlier_count: int = 0
    reference_ns: int | None = None
    inlier_points: np.ndarray | None = None
    covariance: np.ndarray | None = None
    stereo: StereoObservations | None = None  # the inliers' pixels, for stereo landmarks

    def keywords(self) -> dict[str, Any]:
        """The fields by name: ``FusionBackend.add_frame`` takes them as keywords."""
        return {field.name: getattr(self, field.name) for field in fields(self)}


class CameraFrames:
    """Between the rectified left camera (where geometry runs) and the original one (poses)."""

    def __init__(
        self, rectifying_rotation: np.ndarray, rectification: Rectification | None = None
    ) -> None:
        self.rect_from_camera = make_pose(rectifying_rotation, np.zeros(3))
        self.camera_from_rect = invert_pose(self.rect_from_camera)
        self.rectification = rectification

    def in_camera(self, rectified_motion: np.ndarray) -> np.ndarray:
        """A relative pose of rectified frames as one of the original left camera."""
        return self.camera_from_rect @ rectified_motion @ self.rect_from_camera

    def in_rectified(self, camera_motion: np.ndarray) -> np.ndarray:
        """A relative pose of the original left camera as one of rectified frames."""
        return self.rect_from_camera @ camera_motion @ self.camera_from_rect

    def measurement(self, estimate: Estimate, noise: StereoNoiseModel | None = None) -> Measurement:
        """The estimate for the back end: T_ref_cur against the frame it was made from (the back
        end ties the two frames directly instead of through the poses in between). With the
        session's ``noise`` model, also the inliers' stereo pixels (landmarks)."""
        assert estimate.result is not None and estimate.reference is not None
        stereo = None if noise is None else self.stereo_observations(estimate, noise)
        return Measurement(
            relative_pose=self.reference_from_current(estimate),
            inlier_residuals=self.inlier_residuals(estimate),
            inlier_count=int(estimate.result.inliers.sum()),
            reference_ns=estimate.reference.timestamp_ns,
            inlier_points=self.inlier_points(estimate),
            covariance=self.measurement_covariance(estimate),
            stereo=stereo,
        )

    def stereo_observations(
        self, estimate: Estimate, noise: StereoNoiseModel
    ) -> StereoObservations | None:
        """The inliers as rectified stereo pixels of both frames, named by their point indices
        (None without the rectification)."""
        from estimator.backend.observations import (
            StereoCamera,
            StereoObservations,
            project_stereo,
            stereo_pixels,
        )

        pairs, result, reference = estimate.pairs, estimate.result, estimate.reference
        rect = self.rectification
        if pairs is None or result is None or reference is None or rect is None:
            return None
        mask = result.inliers
        reference_ids, current_ids = pairs.reference_index[mask], pairs.current_index[mask]
        previous = reference.points
        camera = StereoCamera(rect.fx, rect.cx, rect.cy, rect.baseline, self.camera_from_rect)
        return StereoObservations(
            reference_ns=int(reference.timestamp_ns),
            reference_ids=np.asarray(reference_ids, dtype=np.int64),
            current_ids=np.asarray(current_ids, dtype=np.int64),
            reference_pixels=stereo_pixels(
                previous.pixels[reference_ids], previous.disparity[reference_ids]
            ),
            # From the matched points, not the detections: the temporal match refines the
            # current pixels to sub-pixel precision against the reference image.
            current_pixels=project_stereo(pairs.current_points[mask], camera),
            reference_points=previous.points[reference_ids],
            camera=camera,
            sigmas_px=noise.level.as_tuple(),
            flow_gain=noise.gain,
            typical_flow_px=noise.typical_flow,
        )

    def measurement_covariance(
        self, estimate: Estimate, reported: bool = False
    ) -> np.ndarray | None:
        """The refinement's 6x6 covariance, rotated from the rectified into the camera frame
        (``reported``: the one the frame report carries, ``Estimate.reported_covariance``).

        The rectifying transform is a pure rotation, whose adjoint rotates both the rotation and
        the translation block of the (right-perturbation) tangent.
        """
        covariance = estimate.covariance
        if reported and estimate.reported_covariance is not None:
            covariance = estimate.reported_covariance
        if covariance is None:
            return None
        rotation = self.camera_from_rect[:3, :3]
        adjoint = np.zeros((6, 6))
        adjoint[:3, :3] = adjoint[3:, 3:] = rotation
        return adjoint @ covariance @ adjoint.T

    def report_covariance(self, estimate: Estimate, backend: BackendConfig) -> np.ndarray:
        """Covariance of the measured T_ref_cur as the back end weighs it (with
        ``registration.refine_covariance`` "sandwich-reported": the robust one instead): the
        refinement's, else the rigid fit's from the inlier points, scaled and floored by
        ``backend``."""
        from estimator.backend.noise import fit_covariance, measured_covariance

        covariance = self.measurement_covariance(estimate, reported=True)
        if covariance is not None:
            return measured_covariance(covariance, backend)
        points, residuals = self.inlier_points(estimate), self.inlier_residuals(estimate)
        return fit_covariance(points, residuals, backend)

    def reference_from_current(self, estimate: Estimate) -> np.ndarray:
        """T_ref_cur of the original left camera (the estimate is in rectified frames)."""
        assert estimate.reference_from_current is not None
        return self.in_camera(estimate.reference_from_current)

    def inlier_points(self, estimate: Estimate) -> np.ndarray:
        """The registration inliers of the current frame in its (original) left camera frame:
        their spread and lever arm give the back end the full covariance of the fit."""
        pairs, result = estimate.pairs, estimate.result
        assert pairs is not None and result is not None
        return transform_points(self.camera_from_rect, pairs.current_points[result.inliers])

    @staticmethod
    def inlier_residuals(estimate: Estimate) -> np.ndarray:
        """||p - (R q + t)|| of the registration inliers (metres), for the back-end covariance."""
        pairs, result = estimate.pairs, estimate.result
        assert pairs is not None and result is not None
        assert estimate.reference_from_current is not None
        mask = result.inliers
        moved = transform_points(estimate.reference_from_current, pairs.current_points[mask])
        return np.linalg.norm(pairs.reference_points[mask] - moved, axis=1)
