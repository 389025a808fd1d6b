"""The stereo noise level of a session, measured on its own inlier residuals.

A stereo point is measured as (u, v, d): its column and row in the rectified left image and its
disparity. How noisy those three numbers are depends on the camera, the optics, the blur, the
texture and the sub-pixel method; a constant chosen on rendered images is wrong for real ones.
So the level is estimated from the data, per session and online:

* after each frame, the inlier pairs (reference point p, current point q, relative pose R, t)
  are projected into the reference camera: e = proj(p) - proj(R q + t) in pixels, per axis.
  Both points carry noise, so Var(e_k) ~ 2 sigma_k^2 (small inter-frame motion);
* a robust scale of each axis (1.4826 x the median absolute residual, immune to the leftover
  outliers) gives the shape (sigma_u : sigma_v : sigma_d) of this frame's level, and one common
  factor scales it so that the median squared Mahalanobis residual of the frame's pairs is the
  chi-square median (heavy tails make the per-axis rule alone overestimate the 3D spread);
* frames are pooled as a weighted running variance that forgets old frames (``memory``), starting
  from a prior (the configured constants) worth ``prior_pairs`` residuals, so the first frames
  are not at the mercy of a handful of pairs.

Real residuals are not Gaussian: blur and edges (the aperture problem) give a minority of
features errors many times the typical one (on EuRoC MH_01 the 99th percentile of the
normalised residuals lies at 7-11 sigma, where a Gaussian has 2.6). A support test at the
Gaussian 99.9 % quantile would reject those good pairs by the dozen. So the model also
measures the tail, ``tail`` = 99.9th percentile of |e| / sigma over 3.29 (1 for Gaussian
noise), pooled like the variance from a generous prior, and the support gate is the
chi-square 99.9 % quantile scaled by tail^2 (``gate_chi2``), with the prior's tail as its
floor (the measured tail is truncated by the gate itself).

The noise of a temporal match also grows with how far the scene moved in the image between the
two frames: the patch changes shape, blur and viewpoint shift the corner (on EuRoC MH_01 the
robust sigma of the residuals rises about linearly from 0.06 px at a flow of 5 px to 0.26 px
at 60 px, at 20 Hz and at 10 Hz alike). The pooled level is the level at the recent frames'
flow, so a frame that moves more than they did (a faster turn, a dropped frame, a lower frame
rate) would meet too tight a support gate and lose good pairs by the dozen. So the model fits
that growth, sigma ~ a (1 + gain x flow), as a least-squares line through the residual sizes
and flows of the recent frames' pairs (``gain_memory``; the flow varies more from frame to
frame than within one), and widens a frame's gate (``gate_for``) by the ratio
(1 + gain x its median flow) / (1 + gain x the recent frames' median flow), when that is > 1.
By the ratio, not by its square as Gaussian sigmas would have it: the measured tail already
widens the gate for the spread of flows in the recent frames, and on MH_01 the square lets
enough poor pairs of the fastest frames in to cost 0.8 mm of ATE on the clean clip.

The disparity noise also grows with the disparity itself: a near point's two views differ
more (perspective, occlusion edges), so its sub-pixel disparity is less certain (on EuRoC MH_01
the disparity residuals of points at 40-200 px are 2-3x those at 3-20 px, at every flow). The
model fits sigma_d ~ a (1 + g x d) as a line through the recent frames' disparity residuals
against the disparity (``disparity_gain``), and the level holds sigma_d at the recent frames'
median disparity (``typical_disparity``): a point's disparity sigma is
sigma_d (1 + g d) / (1 + g typical), so a floor or prior on the level applies where the points are.

The level gives every point its full 3x3 covariance (``stereo.point_covariances``: lateral noise
growing with depth, depth noise with depth squared, along the viewing ray). With the right
level, the squared Mahalanobis residuals of the inliers follow a chi-square law with 3 degrees
of freedom (median 2.366): ``median_squared_mahalanobis`` reports how close the session is.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from estimator.compiled import kernel
from estimator.formats.calibration import Rectification
from estimator.frontend.stereo import point_covariances
from estimator.order_statistics import column_medians, median, quantile
from estimator.registration.refine import CHI2_3_MEDIAN, squared_mahalanobis

__all__ = ["CHI2_3_MEDIAN", "NoiseLevel", "StereoNoiseModel", "flow", "squared_mahalanobis"]

_MAD_TO_SIGMA = 1.482602  # sigma of a Gaussian from its median absolute deviation
_MIN_SIGMA_PX = 0.01  # floor: quantised or synthetic data must not claim zero noise
_MIN_PAIRS = 8  # fewer inliers say nothing reliable about the scale
_GAUSSIAN_Q999 = 3.2905  # 99.9th percentile of |N(0, 1)|
_CHI2_3_Q999 = 16.266  # the Gaussian support gate: chi-square 99.9 % quantile, 3 DOF
_MAX_GAIN_PER_PX = 0.5  # the flow gain is clipped to [0, this]
_MIN_FLOW_SPREAD_PX = 2.0  # flows spread less than this (std) say nothing about the gain
_SIZE_CLIP = 8.0  # residual sizes beyond this many frame medians are clipped in the line fit
_MAX_DISPARITY_GAIN_PER_PX = 0.2  # the disparity gain is clipped to [0, this]
_MIN_DISPARITY_SPREAD_PX = 2.0  # disparities spread less than this (std) say nothing of it


@dataclass(frozen=True)
class NoiseLevel:
    """Standard deviations (pixels) of a stereo point's column, row and disparity."""

    sigma_u_px: float
    sigma_v_px: float
    sigma_d_px: float

    def as_tuple(self) -> tuple[float, float, float]:
        return (self.sigma_u_px, self.sigma_v_px, self.sigma_d_px)


def project(points: np.ndarray, rectification: Rectification) -> np.ndarray:
    """(N, 3) rectified-camera points -> (N, 3) (u, v, d) in pixels."""
    f, b = rectification.fx, rectification.baseline
    inverse_depth = 1.0 / points[:, 2]
    projected = np.empty((len(points), 3))
    projected[:, 0] = f * points[:, 0] * inverse_depth + rectification.cx
    projected[:, 1] = f * points[:, 1] * inverse_depth + rectification.cy
    projected[:, 2] = f * b * inverse_depth
    return projected


@dataclass
class StereoNoiseModel:
    """Online, robust estimate of the session's pixel and disparity noise (see module doc)."""

    rectification: Rectification
    prior: NoiseLevel
    prior_pairs: float = 200.0  # how many residuals the prior is worth
    memory: float = 0.5  # weight kept by the past at each update
    prior_tail: float = 3.0  # generous: a tight first gate would cut the tail it measures
    gain_memory: float = 0.9  # weight kept by the past of the flow-gain line at each update
    # Fit the disparity noise's growth with the disparity (module doc); False: the same
    # disparity noise at every depth.
    disparity_growth: bool = True
    _variance_sums: np.ndarray = field(init=False, repr=False)
    _tail_sum: float = field(init=False, repr=False)
    _flow_sum: float = field(default=0.0, init=False, repr=False)  # pooled like the level
    _disparity_sum: float = field(default=0.0, init=False, repr=False)  # the same
    _line_sums: np.ndarray = field(init=False, repr=False)  # n, sum f, f^2, y, f y
    _disparity_sums: np.ndarray = field(init=False, repr=False)  # n, sum d, d^2, y, d y
    _weight: float = field(init=False, repr=False)
    _medians: list[float] = field(default_factory=list, init=False, repr=False)
    _q90: list[float] = field(default_factory=list, init=False, repr=False)
    _updates: int = field(default=0, init=False, repr=False)

    def __post_init__(self) -> None:
        for name in ("memory", "gain_memory"):
            if not 0.0 <= getattr(self, name) < 1.0:
                raise ValueError(f"{name} must be in [0, 1), got {getattr(self, name)}")
        if not self.prior_pairs > 0:
            raise ValueError(f"prior_pairs must be > 0, got {self.prior_pairs}")
        self._variance_sums = self.prior_pairs * np.square(self.prior.as_tuple())
        self._tail_sum = self.prior_pairs * self.prior_tail
        self._weight = self.prior_pairs
        self._line_sums = np.zeros(5)
        self._disparity_sums = np.zeros(5)

    @property
    def level(self) -> NoiseLevel:
        sigmas = np.sqrt(self._variance_sums / self._weight)
        return NoiseLevel(*(float(s) for s in sigmas))

    @property
    def tail(self) -> float:
        """Heavy-tail factor of the residuals (1 for Gaussian noise)."""
        return float(self._tail_sum / self._weight)

    @property
    def gate_chi2(self) -> float:
        """Support gate on the squared Mahalanobis residual at the measured tail, never
        narrower than the prior's: the tail is measured on the pairs this gate let through,
        so it cannot see beyond the gate and would only ever ratchet it tighter (on MH_01 it
        settled near 1.5-2.5 while the untruncated tail is at 3-4; the refinement's robust
        kernel, not the gate, then weighs the moderate outliers it admits)."""
        return _CHI2_3_Q999 * max(self.tail, self.prior_tail, 1.0) ** 2

    @property
    def gain(self) -> float:
        """Relative growth of the residuals per pixel of flow between the frames (>= 0)."""
        return _line_gain(
            self._line_sums, self.prior_pairs, _MIN_FLOW_SPREAD_PX, _MAX_GAIN_PER_PX
        )

    @property
    def disparity_gain(self) -> float:
        """Relative growth of the disparity noise per pixel of disparity (>= 0): a point's
        disparity sigma is ``level.sigma_d_px`` x (1 + g d) / (1 + g ``typical_disparity``)."""
        return _line_gain(
            self._disparity_sums, self.prior_pairs, _MIN_DISPARITY_SPREAD_PX,
            _MAX_DISPARITY_GAIN_PER_PX,
        )  # fmt: skip

    @property
    def typical_disparity(self) -> float:
        """Median disparity (pixels) of the recent frames' inliers, weighted like the level:
        where ``level.sigma_d_px`` holds."""
        return float(self._disparity_sum / self._weight)

    @property
    def typical_flow(self) -> float:
        """Median flow (pixels) of the recent frames, weighted like the level."""
        return float(self._flow_sum / self._weight)

    def gate_for(self, current: np.ndarray, reference: np.ndarray) -> float:
        """The support gate of one frame's matched points: ``gate_chi2`` widened for a frame
        that moved more in the image than the recent ones (see module doc)."""
        if len(current) == 0:
            return self.gate_chi2
        moved = median(flow(current, reference, self.rectification))
        gain = self.gain
        ratio = (1.0 + gain * moved) / (1.0 + gain * self.typical_flow)
        return self.gate_chi2 * max(ratio, 1.0)

    def covariances(self, points: np.ndarray) -> np.ndarray:
        """(N, 3, 3) covariances of rectified-camera points at the current level."""
        return self._covariances(points, self.level)

    def _covariances(self, points: np.ndarray, level: NoiseLevel) -> np.ndarray:
        rectification = self.rectification
        points = np.ascontiguousarray(points, dtype=float)
        if points.ndim != 2 or points.shape[1] != 3:
            return point_covariances(points, rectification, *level.as_tuple())  # its error
        return _point_covariances(
            points, rectification.fx, rectification.fx * rectification.baseline,
            level.sigma_u_px**2, level.sigma_v_px**2, level.sigma_d_px, self.disparity_gain,
            self.typical_disparity,
        )  # fmt: skip

    def update(
        self,
        reference: np.ndarray,
        current: np.ndarray,
        rotation: np.ndarray,
        translation: np.ndarray,
        covariances: tuple[np.ndarray, np.ndarray] | None = None,
    ) -> float | None:
        """Fold in one frame's inlier pairs (reference ~ R current + t); returns the median
        squared Mahalanobis residual under the level *before* the update (None: too few).
        ``covariances`` (current, reference) are ``covariances`` of the points at the present
        level when the caller already has them (the estimate's), else they are computed."""
        if len(reference) < _MIN_PAIRS:
            return None
        if covariances is None:
            covariances = (self.covariances(current), self.covariances(reference))
        # The check first: residuals against the level predicted before this frame.
        predicted_squared = squared_mahalanobis(
            current, reference, *covariances, rotation, translation
        )
        predicted_median = median(predicted_squared)
        self._q90.append(quantile(predicted_squared, 0.9))
        predicted = current @ rotation.T + translation
        seen = project(reference, self.rectification)
        errors = seen - project(predicted, self.rectification)
        # Disparity residuals brought to the typical disparity, where the level holds, by the
        # growth known before this frame; the growth's own fit takes the raw residuals.
        growth = self._disparity_growth(seen[:, 2])
        self._fold_disparity_line(seen[:, 2], errors[:, 2])
        errors[:, 2] /= growth
        # Both points are noisy: the difference has twice the variance of one measurement.
        sigma = _MAD_TO_SIGMA * column_medians(np.abs(errors)) / np.sqrt(2.0)
        sigma = np.maximum(sigma, _MIN_SIGMA_PX)
        frame_level = NoiseLevel(*(float(value) for value in sigma))
        squared = squared_mahalanobis(
            current, reference, self._covariances(current, frame_level),
            self._covariances(reference, frame_level), rotation, translation,
        )  # fmt: skip
        sigma = np.maximum(sigma * np.sqrt(median(squared) / CHI2_3_MEDIAN), _MIN_SIGMA_PX)
        normalised = np.abs(errors) / (np.sqrt(2.0) * sigma)
        tail = float(quantile(normalised, 0.999).max()) / _GAUSSIAN_Q999
        pairs = float(len(reference))
        moved = _flow(project(current, self.rectification), seen)
        self._fold_line(errors, moved)
        self._flow_sum = self.memory * self._flow_sum + pairs * median(moved)
        self._disparity_sum = self.memory * self._disparity_sum + pairs * median(seen[:, 2])
        self._variance_sums = self.memory * self._variance_sums + pairs * sigma**2
        self._tail_sum = self.memory * self._tail_sum + pairs * tail
        self._weight = self.memory * self._weight + pairs
        self._medians.append(predicted_median)
        self._updates += 1
        return predicted_median

    def _disparity_growth(self, disparity: np.ndarray) -> np.ndarray:
        """(1 + g d) / (1 + g typical): each disparity's noise against the level's."""
        gain = self.disparity_gain
        return (1.0 + gain * disparity) / (1.0 + gain * self.typical_disparity)

    def _fold_disparity_line(self, disparity: np.ndarray, residual: np.ndarray) -> None:
        """Add this frame's (disparity, |disparity residual|) pairs to the running line fit
        of the growth (nothing when the growth is off: its gain stays 0)."""
        if self.disparity_growth:
            terms = _line_terms(disparity, np.abs(residual))
            self._disparity_sums = self.gain_memory * self._disparity_sums + terms

    def _fold_line(self, errors: np.ndarray, moved: np.ndarray) -> None:
        """Add this frame's (flow, residual size) pairs to the running line fit."""
        size = np.sqrt(np.square(errors).sum(axis=1) / errors.shape[1])  # np.mean's operations
        self._line_sums = self.gain_memory * self._line_sums + _line_terms(moved, size)

    def summary(self) -> dict[str, float | int | None]:
        """The level now and the median (over frames) of the inliers' median squared
        Mahalanobis residual, ignoring the first frames in which the prior still weighs."""
        settled = self._medians[5:] or self._medians
        settled_q90 = self._q90[5:] or self._q90
        return {
            **{key: value for key, value in zip(
                ("sigma_u_px", "sigma_v_px", "sigma_d_px"), self.level.as_tuple(), strict=True
            )},
            "tail": self.tail,
            "gain_per_px": self.gain,
            "disparity_gain_per_px": self.disparity_gain,
            "typical_disparity_px": self.typical_disparity,
            "typical_flow_px": self.typical_flow,
            "gate_chi2": self.gate_chi2,
            "median_squared_mahalanobis": float(np.median(settled)) if settled else None,
            # Chi-square (3 DOF) 90 % quantile: 6.251; larger here means heavier tails.
            "q90_squared_mahalanobis": float(np.median(settled_q90)) if settled_q90 else None,
            "frames": self._updates,
        }  # fmt: skip


def flow(current: np.ndarray, reference: np.ndarray, rectification: Rectification) -> np.ndarray:
    """(N,) pixel displacement of matched points between the two frames' left images."""
    return _flow(project(current, rectification), project(reference, rectification))


def _line_terms(x: np.ndarray, size: np.ndarray) -> np.ndarray:
    """One frame's sums (n, x, x^2, y, x y) of a line through residual sizes y against x, the
    sizes clipped at ``_SIZE_CLIP`` frame medians (a few wild pairs must not set a slope)."""
    size = np.minimum(size, _SIZE_CLIP * median(size))
    return np.array([len(size), x.sum(), np.square(x).sum(), size.sum(), (x * size).sum()])


def _line_gain(sums: np.ndarray, min_count: float, min_spread: float, max_gain: float) -> float:
    """Relative slope (slope / intercept) of the pooled line, clipped to [0, ``max_gain``];
    0 while there are fewer than ``min_count`` pairs or x spreads less than ``min_spread``."""
    count, sum_x, sum_xx, sum_y, sum_xy = sums
    spread = count * sum_xx - sum_x**2  # count^2 x the variance of x
    if count < min_count or spread < (count * min_spread) ** 2:
        return 0.0  # too little data: the level holds everywhere
    slope = (count * sum_xy - sum_x * sum_y) / spread
    intercept = (sum_y - slope * sum_x) / count
    if intercept <= 0.0:  # residuals as good as proportional to x
        return max_gain
    return float(np.clip(slope / intercept, 0.0, max_gain))


@kernel("float64[:, ::1], float64, float64, float64, float64, float64, float64, float64")
def _point_covariances(
    points, focal, focal_baseline, variance_u, variance_v, sigma_d, disparity_gain,
    typical_disparity,
):
    """``stereo.point_covariances`` in one compiled pass, the same operations in the same
    order (bit for bit, tested): the array version's temporaries cost more than its
    arithmetic at a few hundred points, four times a frame."""
    covariance = np.empty((points.shape[0], 3, 3))
    growth = disparity_gain * focal_baseline
    sigma_d = sigma_d / (1.0 + disparity_gain * typical_disparity)
    for n in range(points.shape[0]):
        ray = sigma_d * (points[n, 2] + growth) / focal_baseline
        along = ray * ray  # (sigma_d (1 + g d) / (1 + g typical) / d)^2
        for i in range(3):
            for j in range(3):
                covariance[n, i, j] = points[n, i] * (points[n, j] * along)
        lateral = points[n, 2] / focal
        across = lateral * lateral
        covariance[n, 0, 0] += across * variance_u
        covariance[n, 1, 1] += across * variance_v
    return covariance


def _flow(current: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """``flow`` of points already projected to (u, v, d)."""
    shift = current[:, :2] - reference[:, :2]
    return np.hypot(shift[:, 0], shift[:, 1])
