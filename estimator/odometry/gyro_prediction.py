"""The gyro's rotation between frames, for centring and sizing the temporal search windows.

A constant-velocity prediction misses a turn as it begins: its rotation error is the angular
acceleration times T^2, and the per-point windows must be as wide as the largest one expected
(or the search falls back to the wide window once the matches show the miss). The gyro measures
the rotation itself; what is left is its bias and noise, a few hundredths of a degree per
frame. Both are learned against vision, as the constant-velocity level is: the bias from the
mean difference between the gyro's and the measured rotation, the error level from the
decaying peak of what the bias-corrected gyro still missed.
"""

from __future__ import annotations

import numpy as np

from estimator.config import FrontendConfig
from estimator.formats.calibration import StereoRig
from estimator.geometry import (
    quat_multiply,
    quat_to_matrix,
    rotation_angle_deg,
    rotation_vector,
    rotation_vector_to_quat,
)
from estimator.imu_sampling import sample_segments, samples_cover
from estimator.types import ImuBatch

__all__ = ["GyroPrediction", "gyro_prediction_for", "integrate_gyro"]

# Learning rate of the bias from each frame's difference between the gyro and vision: vision's
# rotation noise on one frame (a few 1e-5 rad) over 0.05-0.1 s is ~1e-3 rad/s, averaged over
# about 1 / gain frames.
_BIAS_GAIN = 0.1
_LEVEL_DECAY = 0.9  # per frame, as the constant-velocity level (references.py)
# The samples must cover the interval but for this much at each end (one missing sample).
_COVERAGE_SLACK_NS = 15_000_000


def integrate_gyro(
    timestamps_ns: np.ndarray, rates: np.ndarray, start_ns: int, end_ns: int
) -> np.ndarray | None:
    """Body rotation body(start) <- body(end) from rates (rad/s, bias removed), read between
    the samples as the back end's preintegration reads them (``sample_segments``); None when
    the samples do not cover [start_ns, end_ns] (but for one missing sample at either end)."""
    if not samples_cover(timestamps_ns, start_ns, end_ns, _COVERAGE_SLACK_NS):
        return None
    pieces, durations = sample_segments(timestamps_ns, rates, start_ns, end_ns)
    rotation = np.array([1.0, 0.0, 0.0, 0.0])
    for rate, duration in zip(pieces, durations, strict=True):
        rotation = quat_multiply(rotation, rotation_vector_to_quat(rate * duration))
    return quat_to_matrix(rotation)


class GyroPrediction:
    """The rectified camera's rotation since the last good frame, from the gyro.

    ``rect_from_body`` rotates body (IMU) vectors into the rectified left camera. ``advance``
    takes each frame's samples (those since the previous frame); ``rotation_since_good`` is
    then the rectified rotation good(previous frame with an estimate) <- now, or None.
    """

    def __init__(self, rect_from_body: np.ndarray, prior_error_rad_s: float) -> None:
        self.rect_from_body = np.asarray(rect_from_body, dtype=float)
        self.bias = np.zeros(3)  # rad/s, body frame
        self.error_rad_s = float(prior_error_rad_s)  # one sigma of the rate error left
        self._good_ns: int | None = None  # the last good frame's stamp
        self._last_ns: int | None = None  # the last frame's stamp
        self._since_good: np.ndarray | None = np.eye(3)  # body(good) <- body(last)
        self._now: np.ndarray | None = None  # body(good) <- body(now), this frame's
        self._now_ns: int | None = None

    def advance(self, imu: ImuBatch | None, now_ns: int) -> None:
        """Integrate the samples from the last frame to ``now_ns``."""
        self._now, self._now_ns = None, int(now_ns)
        if imu is None or self._last_ns is None or self._since_good is None:
            return
        step = integrate_gyro(imu.timestamps_ns, imu.gyro - self.bias, self._last_ns, now_ns)
        if step is not None:
            self._now = self._since_good @ step

    def rotation_since_good(self, span_ns: int) -> np.ndarray | None:
        """Rectified good <- now when ``span_ns`` is the time since the last good frame."""
        if self._now is None or self._good_ns is None or self._now_ns is None:
            return None
        if abs(self._now_ns - self._good_ns - span_ns) > 1000:
            return None
        return self.rect_from_body @ self._now @ self.rect_from_body.T

    def sigma_rad(self, span_ns: int) -> float:
        """One sigma of :meth:`rotation_since_good`'s angle error over ``span_ns``."""
        return self.error_rad_s * max(span_ns, 0) * 1e-9

    def frame_done(self, good: bool, measured: np.ndarray | None) -> None:
        """End of a frame: learn from ``measured``, vision's rectified rotation good <- now
        (None when it was not measured against the last good frame), and restart from this
        frame when it is ``good``."""
        if self._good_ns is not None and self._now_ns is not None:
            span_ns = self._now_ns - self._good_ns
            gyro = self.rotation_since_good(span_ns)
            if good and measured is not None and gyro is not None and span_ns > 0:
                self._learn(gyro, measured, span_ns)
        if good or self._good_ns is None:
            self._good_ns, self._since_good = self._now_ns, np.eye(3)
        else:
            self._since_good = self._now
        self._last_ns = self._now_ns

    def _learn(self, gyro: np.ndarray, measured: np.ndarray, span_ns: int) -> None:
        """Bias from the mean of (gyro - vision) / T, level from the decaying peak of the miss.

        For small angles log(measured^T gyro) is the integrated rate error, in the camera.
        """
        span_s = span_ns * 1e-9
        miss = rotation_vector(measured.T @ gyro)
        rate_error = self.rect_from_body.T @ miss / span_s  # body frame
        self.bias = self.bias + _BIAS_GAIN * rate_error
        angle = np.radians(rotation_angle_deg(measured.T @ gyro))
        self.error_rad_s = max(float(angle) / span_s, _LEVEL_DECAY * self.error_rad_s)


def gyro_prediction_for(rig: StereoRig, frontend: FrontendConfig) -> GyroPrediction | None:
    """The gyro's rotation for the per-point search windows (``frontend.gyro_prediction``).

    Only where the windows are per point (``min_search_radius_px`` set; derived for every rig
    with a frame rate since 2026-12-04): with one wide window for every point the
    constant-velocity centre is what the window was sized for, and the gyro's centre moved
    the noisy rendered flight's fused trajectory by a few per cent either way
    (docs/performance.md, "Driving rig").
    """
    if not frontend.gyro_prediction or frontend.min_search_radius_px is None:
        return None
    rect_from_body = rig.rectification.R_left @ rig.left.T_BS[:3, :3].T
    return GyroPrediction(rect_from_body, np.radians(frontend.prediction_gyro_error_deg_s))
