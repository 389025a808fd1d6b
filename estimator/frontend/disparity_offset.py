"""A constant offset in every disparity: measured from the registrations, taken out of them.

A stereo calibration that is slightly off (the right camera's principal point, or a yaw of a
few hundredths of a degree between the cameras) adds one constant to every disparity. Near
points barely notice it, but depth is f b / d: on a car's 0.54 m baseline a point 40 m away
has 9.7 px of disparity, and 0.2 px more or less moves it by 2 %. Driving forward, the far
points then say the car moved less (or more) than the near ones do, and the translation and
the rotation that fit both drift (a rendered 520 m drive: 0.01 % final drift with the exact
calibration, 0.5 / 1.1 / 1.8 / 3.0 % with 0.1 / 0.2 / 0.3 / 0.5 px; docs/frontend.md, "A
disparity offset"). Real rigs' calibrations are off by that much.

The offset is observable from the motion itself: only the right one makes the near and the far
points agree on one rigid motion. For each keyframe measurement the inliers are refitted with
the offset moved by +-``_STEP_PX`` around the one in use (the Mahalanobis refinement from the
measured pose), and the three costs give a Newton step and its curvature; the session's
estimate is the curvature-weighted mean of the steps (a frame that hardly moved against its
keyframe, or only turned, has no curvature and no say). Once the estimate's standard error is
below ``_MAX_STANDARD_ERROR_PX`` and it is ``_SIGNIFICANCE`` standard errors from zero it is
taken out of every later frame's disparities; a frame measured against an older reference
gets that reference's points shifted to its own offset (``aligned``). From then on it is
measured afresh around the offset in use and replaced when it has clearly moved.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from estimator.config import MAX_DISPARITY_OFFSET_PX, FrontendConfig
from estimator.formats.calibration import Rectification
from estimator.frontend.stereo import StereoPoints, shift_disparities, triangulate
from estimator.frontend.stereo_noise import StereoNoiseModel
from estimator.registration.refine import refine_pose_mahalanobis

__all__ = ["DisparityOffset", "aligned", "configured_offset"]

# The profile's half step (pixels): the cost is sampled at -step, 0 and +step of the offset.
_STEP_PX = 0.1
# Measurements with fewer inliers, or whose disparities change less between the frames (the
# median absolute change, pixels), say nothing about the offset.
_MIN_INLIERS = 30
_MIN_DISPARITY_CHANGE_PX = 0.5
# At most this many inlier pairs per measurement (evenly spread over them): the refits are the
# cost, and a few hundred pairs pin the offset as well as all of them.
_MAX_PAIRS = 200
# Once the estimate's standard error is below this (pixels), one frame in
# ``_SETTLED_EVERY`` is measured: it only confirms a constant.
_SETTLED_STANDARD_ERROR_PX = 0.01
_SETTLED_EVERY = 5
# Applied once the estimate is this sure and this far from zero (standard errors) ...
_MAX_STANDARD_ERROR_PX = 0.03
_SIGNIFICANCE = 5.0
_MIN_MEASUREMENTS = 20
# ... and changed again only when it has moved by more than this from the one in use, and
# by this many standard errors.
_MIN_CHANGE_PX = 0.02
_CHANGE_SIGNIFICANCE = 3.0
# A disparity the offset would make non-positive becomes this one (a point at infinity, almost).
_FAR_DISPARITY_PX = 0.05


def aligned(points: StereoPoints, offset_px: float, rectification: Rectification) -> StereoPoints:
    """``points`` with ``offset_px`` taken out of their disparities instead of theirs; every
    point is kept (a disparity that would not stay positive is held at a far one), so that
    indices into them stay valid."""
    if points.disparity_offset_px == offset_px or len(points) == 0:
        return points
    shift = points.disparity_offset_px - offset_px
    shifted = shift_disparities(points, shift, rectification, floor_px=_FAR_DISPARITY_PX)
    return replace(shifted, disparity_offset_px=float(offset_px))


def configured_offset(frontend: FrontendConfig) -> float | None:
    """``frontend.disparity_offset_px``; unset, None (measured) in detect mode and 0 in track
    mode, whose tracks carry their own disparities."""
    configured = frontend.disparity_offset_px
    if configured is None and frontend.mode == "track":
        return 0.0
    return configured


def _believable(offset_px: float) -> float:
    """``offset_px`` held within the largest offset believed; a non-finite one is none."""
    if not math.isfinite(offset_px):
        return 0.0
    return float(np.clip(offset_px, -MAX_DISPARITY_OFFSET_PX, MAX_DISPARITY_OFFSET_PX))


class DisparityOffset:
    """The session's disparity offset: configured, or measured and then taken out."""

    def __init__(self, rectification: Rectification, configured_px: float | None) -> None:
        self.rectification = rectification
        self.measuring = configured_px is None
        self.applied = 0.0 if configured_px is None else float(configured_px)
        self._offered = 0  # measurements offered (for the settled estimate's sampling)
        self._total = 0  # measurements folded in, over the whole session
        self._restart()

    def _restart(self) -> None:
        """Measure afresh around the offset in use: a step measured far from the optimum (a
        robust cost's curvature is not a quadratic's there) should not weigh on the next."""
        self._information = 0.0  # sum of the profiles' curvatures
        self._weighted = 0.0  # sum of curvature x offset
        self._weighted_squares = 0.0  # sum of curvature x offset^2
        self._curvature_squares = 0.0  # for the effective number of measurements
        self._count = 0

    def resume(self, applied_px: float) -> None:
        """Continue a session: the offset another process had taken out (a configured one
        stays as configured); it is measured afresh around that value."""
        if self.measuring:
            self.applied = _believable(applied_px)
            self._restart()

    def corrected(self, points: StereoPoints) -> StereoPoints:
        """A new frame's ``points`` (as matched) with the offset in use taken out."""
        return aligned(points, self.applied, self.rectification)

    @property
    def estimate(self) -> tuple[float, float] | None:
        """(offset, standard error) in pixels measured around the offset in use, None before
        two informative measurements since it was set."""
        if self._count < 2 or self._information <= 0.0:
            return None
        mean = self._weighted / self._information
        spread = max(self._weighted_squares / self._information - mean * mean, 0.0)
        # The measurements' own scatter, over the effective number of them.
        effective = self._information**2 / max(self._curvature_squares, 1e-300)
        return mean, math.sqrt(spread / max(effective - 1.0, 1.0))

    def observe(
        self,
        reference: StereoPoints,
        current: StereoPoints,
        pairs_reference: np.ndarray,
        pairs_current: np.ndarray,
        reference_from_current: np.ndarray,
        noise: StereoNoiseModel,
    ) -> None:
        """Fold one measurement in: the inlier pairs (indices into ``reference`` and
        ``current``) and the measured pose (rectified, reference from current)."""
        if not self.measuring or len(pairs_current) < _MIN_INLIERS:
            return
        self._offered += 1
        if self._resting():
            return
        if len(pairs_current) > _MAX_PAIRS:
            chosen = np.linspace(0, len(pairs_current) - 1, _MAX_PAIRS).astype(np.intp)
            pairs_reference, pairs_current = pairs_reference[chosen], pairs_current[chosen]
        matched_reference = reference.disparity[pairs_reference] + reference.disparity_offset_px
        matched_current = current.disparity[pairs_current] + current.disparity_offset_px
        if np.median(np.abs(matched_current - matched_reference)) < _MIN_DISPARITY_CHANGE_PX:
            return
        reference_pixels = reference.pixels[pairs_reference]
        current_pixels = current.pixels[pairs_current]
        costs = [
            self._refit_cost(
                (reference_pixels, matched_reference), (current_pixels, matched_current),
                self.applied + step, reference_from_current, noise,
            )
            for step in (-_STEP_PX, 0.0, _STEP_PX)
        ]
        if not all(math.isfinite(cost) for cost in costs):
            return
        curvature = (costs[0] - 2.0 * costs[1] + costs[2]) / _STEP_PX**2
        if curvature <= 0.0:
            return
        slope = (costs[2] - costs[0]) / (2.0 * _STEP_PX)
        offset = _believable(self.applied - slope / curvature)
        self._information += curvature
        self._curvature_squares += curvature * curvature
        self._weighted += curvature * offset
        self._weighted_squares += curvature * offset * offset
        self._count += 1
        self._total += 1
        self._update_applied()

    def _resting(self) -> bool:
        """Whether this frame is skipped: the estimate has settled and it is not the turn of
        one in ``_SETTLED_EVERY``."""
        estimate = self.estimate
        settled = (
            estimate is not None
            and self._count >= _MIN_MEASUREMENTS
            and estimate[1] <= _SETTLED_STANDARD_ERROR_PX
        )
        return settled and self._offered % _SETTLED_EVERY != 0

    def _update_applied(self) -> None:
        estimate = self.estimate
        if estimate is None or self._count < _MIN_MEASUREMENTS:
            return
        offset, standard_error = estimate
        if standard_error > _MAX_STANDARD_ERROR_PX:
            return
        # Zero until the offset stands out from its error; from then on, refined when the
        # measurements around the one in use say it is off (not for their scatter alone).
        if self.applied == 0.0 and abs(offset) < _SIGNIFICANCE * standard_error:
            return
        change = abs(offset - self.applied)
        if change > _MIN_CHANGE_PX and change >= _CHANGE_SIGNIFICANCE * standard_error:
            self.applied = offset
            self._restart()

    def _refit_cost(
        self,
        reference: tuple[np.ndarray, np.ndarray],
        current: tuple[np.ndarray, np.ndarray],
        offset: float,
        reference_from_current: np.ndarray,
        noise: StereoNoiseModel,
    ) -> float:
        """The refined registration's cost with ``offset`` taken out of both frames' matched
        disparities (pixels and disparities of the inliers; NaN when a disparity would not
        stay positive or the refit fails)."""
        reference_disparity = reference[1] - offset
        current_disparity = current[1] - offset
        if min(reference_disparity.min(), current_disparity.min()) <= 0.0:
            return math.nan
        target = triangulate(reference[0], reference_disparity, self.rectification)
        source = triangulate(current[0], current_disparity, self.rectification)
        result = refine_pose_mahalanobis(
            source, target, noise.covariances(source), noise.covariances(target),
            reference_from_current[:3, :3], reference_from_current[:3, 3],
            iterations=3, with_covariance=False,
        )  # fmt: skip
        return result.final_cost if result.success else math.nan

    def summary(self) -> dict[str, float | int | bool | None]:
        """For metrics.json: the estimate, its standard error, the offset in use (pixels)."""
        estimate = self.estimate
        return {
            "measured": self.measuring,
            "estimate_px": None if estimate is None else estimate[0],
            "standard_error_px": None if estimate is None else estimate[1],
            "applied_px": self.applied,
            "measurements": self._total,
        }
