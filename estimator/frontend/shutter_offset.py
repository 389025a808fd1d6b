"""The right shutter's time against the left's: measured from the stereo matches' rows, undone
in their disparities.

Two cameras without a shared trigger (two USB cameras, a rig whose sync cable is loose) expose
their images a few milliseconds apart. While the rig turns, the right image then sees the scene
where the left one will see it ``offset`` seconds later: every right pixel has moved by the
point's image velocity times the offset. Across the rows this shows as a vertical offset of the
stereo matches that grows with the vertical image velocity (rectified rows should agree);
along the rows it is the same kind of shift added to every disparity, which no stereo noise
model can average out (at 60 deg/s and 5 ms on a 435 px lens: 2.3 px, 14 % of the depth of a
point 3 m away with an 11 cm baseline).

The offset is the slope of the matches' row offsets against their vertical image velocity
(least squares with an intercept, which takes a constant row error of the calibration), summed
over the session. It counts as measured once at least ``_MIN_MEASURE_S2`` of velocity spread
was seen and it is further from zero than ``_SIGNIFICANCE`` standard errors and at least
``_MIN_OFFSET_S``: then the run reports it (a rig whose cameras are triggered together measures
nothing). It is undone only when configured (``frontend.stereo_time_offset_ms``), from the
first frame: a correction switched on halfway would give the keyframe and the frame different
geometry, and the measured slope is diluted by the rows' truncation at the stereo row
tolerance and the velocity's errors (docs/frontend.md, "A late right shutter").
"""

from __future__ import annotations

import math

import numpy as np

from estimator.formats.calibration import Rectification
from estimator.frontend.stereo import StereoPoints, shift_disparities

__all__ = ["ShutterOffset", "StereoTiming", "image_velocity", "undo_offset"]

Velocity = tuple[np.ndarray, np.ndarray]  # a camera's (angular rad/s, linear m/s), own frame

# Reported once the standard error of the slope is this many times below it ...
_SIGNIFICANCE = 5.0
# ... it is at least this long (shorter offsets move a disparity by well under a tenth of a
# pixel at a hand-held rig's rates) ...
_MIN_OFFSET_S = 5e-4
# ... and the sum of the squared vertical velocities about their mean has reached this
# ((px/s)^2; 10^6: e.g. 100 matches of 10 frames turning at ~6 deg/s on a 435 px lens).
_MIN_MEASURE_S2 = 1e6


def image_velocity(
    points: np.ndarray, angular: np.ndarray, linear: np.ndarray, rectification: Rectification
) -> np.ndarray:
    """(N, 2) image velocity (px/s) of static ``points`` (rectified left camera) seen from a
    camera turning at ``angular`` (rad/s) and moving at ``linear`` (m/s), both in its own
    frame: the points move at -angular x P - linear relative to it."""
    points = np.asarray(points, dtype=float).reshape(-1, 3)
    moving = -np.cross(angular, points) - linear
    x, y, z = points.T
    f = rectification.fx
    du = f * (moving[:, 0] * z - x * moving[:, 2]) / (z * z)
    dv = f * (moving[:, 1] * z - y * moving[:, 2]) / (z * z)
    return np.column_stack([du, dv])


class ShutterOffset:
    """The session's right-minus-left shutter time (seconds), measured or configured."""

    def __init__(self, configured_s: float | None = None) -> None:
        self.configured_s = configured_s
        # Sums over the matches of 1, g, g^2, r, g r, r^2 (g: vertical velocity, r: row offset).
        self._sums = np.zeros(6)

    @property
    def measuring(self) -> bool:
        return self.configured_s is None

    def observe(self, vertical_velocity: np.ndarray, row_offset: np.ndarray) -> None:
        """Fold in one frame's matches: predicted vertical velocity (px/s) and right row
        minus left row (px)."""
        if not self.measuring or len(row_offset) == 0:
            return
        g = np.asarray(vertical_velocity, dtype=float)
        r = np.asarray(row_offset, dtype=float)
        self._sums += (len(g), g.sum(), g @ g, r.sum(), g @ r, r @ r)

    def fit(self) -> tuple[float, float] | None:
        """(slope s, its standard error) of row offset = c + s x velocity; None: too little
        velocity spread seen yet."""
        count, sum_g, sum_gg, sum_r, sum_gr, sum_rr = self._sums
        if count < 3:
            return None
        spread = sum_gg - sum_g * sum_g / count
        if spread < _MIN_MEASURE_S2:
            return None
        slope = (sum_gr - sum_g * sum_r / count) / spread
        intercept = (sum_r - slope * sum_g) / count
        residual = (
            sum_rr - 2 * intercept * sum_r - 2 * slope * sum_gr + count * intercept**2
            + 2 * intercept * slope * sum_g + slope**2 * sum_gg
        )  # fmt: skip
        variance = max(residual, 0.0) / (count - 2)
        return float(slope), math.sqrt(variance / spread)

    @property
    def measured_s(self) -> float | None:
        """The measured offset once it is clearly measured (None: not, or configured)."""
        fitted = self.fit()
        if self.configured_s is not None or fitted is None:
            return None
        slope, error = fitted
        if abs(slope) < _MIN_OFFSET_S or abs(slope) < _SIGNIFICANCE * error:
            return None
        return slope

    @property
    def offset_s(self) -> float:
        """The offset the frames are corrected by: the configured one (0: none)."""
        return self.configured_s or 0.0


def undo_offset(
    points: StereoPoints, horizontal_velocity: np.ndarray, offset_s: float,
    rectification: Rectification,
) -> StereoPoints:
    """``points`` as a right image taken with the left one would have given them: each right
    pixel moved back by its horizontal velocity times ``offset_s`` (disparity + velocity x
    offset), re-triangulated; points whose disparity would not stay positive are dropped."""
    return shift_disparities(points, horizontal_velocity * offset_s, rectification)


class StereoTiming:
    """Measures the shutter offset on the frames' stereo points and undoes it in them.

    A frame's rows are measured against the camera's velocity at the frame: the mean of the
    motions measured into it and out of it (known one frame later), which the row offsets
    follow far more closely than the constant-velocity prediction the correction has to use
    (with the prediction the slope came out at 2 of 5 ms on the real MH_01 clip delayed by
    5 ms: its errors dilute the slope).
    """

    def __init__(self, rectification: Rectification, configured_ms: float | None) -> None:
        self.rectification = rectification
        self.offset = ShutterOffset(None if configured_ms is None else configured_ms * 1e-3)
        self._current: StereoPoints | None = None  # this frame's points, as matched
        self._waiting: tuple[StereoPoints, Velocity] | None = None  # last frame's, velocity in

    @property
    def correcting(self) -> bool:
        """Whether the frames' disparities are corrected (an offset is configured)."""
        return self.offset.offset_s != 0.0

    def corrected(self, points: StereoPoints, velocity: Velocity | None) -> StereoPoints:
        """``points`` with the offset undone; ``velocity``: the camera's predicted velocity at
        the frame, None when there is no prediction yet (the points are kept as they are)."""
        self._current = points
        offset_s = self.offset.offset_s
        if velocity is None or len(points) == 0 or not self.correcting:
            return points
        flow = image_velocity(points.points, *velocity, self.rectification)
        return undo_offset(points, flow[:, 0], offset_s, self.rectification)

    def summary(self) -> dict[str, float | None]:
        """For metrics.json: the configured offset, the fit and whether it counts (ms)."""
        fitted = self.offset.fit()
        measured = self.offset.measured_s
        return {
            "configured_ms": None if self.offset.measuring else self.offset.offset_s * 1e3,
            "fitted_ms": None if fitted is None else fitted[0] * 1e3,
            "standard_error_ms": None if fitted is None else fitted[1] * 1e3,
            "measured_ms": None if measured is None else measured * 1e3,
        }

    def learn(self, velocity_in: Velocity | None) -> None:
        """After the frame: ``velocity_in`` is that of the motion measured into it (None:
        none). Measures the previous frame's rows at the mean of its motions in and out."""
        waiting, current = self._waiting, self._current
        self._waiting = None
        self._current = None
        if not self.offset.measuring or velocity_in is None:
            return
        if waiting is not None and waiting[0].row_offset is not None:
            points, before = waiting
            angular = 0.5 * (before[0] + velocity_in[0])
            linear = 0.5 * (before[1] + velocity_in[1])
            flow = image_velocity(points.points, angular, linear, self.rectification)
            self.offset.observe(flow[:, 1], points.row_offset)
        if current is not None and len(current) > 0:
            self._waiting = (current, velocity_in)
