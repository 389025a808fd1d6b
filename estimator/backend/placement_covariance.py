"""The pose covariance a placement prior drops, carried into the reported covariance.

When a measurement's keyframe has left the window, ``old_reference = "prior"`` (and
``"prior-after-gap"`` after frames without vision) places the frame in the world from the
keyframe's last estimate, ``X_ref T``, with the measurement's covariance. The factor is right
for the estimate (it keeps the tie to the keyframe), but the smoother then holds the frame's
absolute pose as known to within one measurement: the keyframe's own uncertainty, and all the
drift before it, are no longer in the graph. The marginals it reports stop growing, while the
errors keep growing like a random walk from keyframe to keyframe, so a filter trusting the
pose covariance sees the relative motion over a window as far more certain than it is (MH_01
fused pose NEES 15.5 per DOF).

The dropped part is put back at report time, not into the factors (weighing the priors less
costs drift): each frame's reported covariance is its marginal plus a carried covariance
``D``. The n-th frame placed from keyframe K gets ``D`` = K's reported covariance moved along
the measured motion (its marginal and its own ``D`` when it was last reported) plus (n - 1)
times the measurement's covariance; any other frame inherits the previous frame's ``D`` moved
along the estimated motion, since its absolute pose in the graph hangs on the placed frames.
Before the first placement ``D`` is zero and the reported covariance is the marginal.

The (n - 1) term: measurements against one keyframe share its points (lag-1 correlation of
their errors 0.87 on MH_01), so the placed frames' errors do not stay one measurement's apart;
reported as a random walk along the keyframe's measurements they grow the way the pose reading
of ``bench consistency`` (and a filter differencing two poses) assumes. With the keyframe's
covariance alone, MH_01 fused ("prior") had pose NEES 4.7 per DOF (27 in the first second, one
keyframe measured against for a second) and the V1_01 standstill 1170; with the term 0.68 and
2.2 (``docs/backend.md``).
"""

from __future__ import annotations

import numpy as np

from estimator.geometry import invert_pose, transport_covariance

__all__ = ["PlacementCovariance"]


class PlacementCovariance:
    """Carried covariance ``D`` of the newest frame and the reported covariance of the frames
    that may still be referenced (module doc)."""

    def __init__(self) -> None:
        self._carried = np.zeros((6, 6))
        self._pose: np.ndarray | None = None  # body pose the carried covariance is held at
        self._reported: dict[int, np.ndarray] = {}  # frame index -> reported covariance
        self._placement: np.ndarray | None = None  # the pending frame's D, when placed
        self._counts: dict[int, int] = {}  # keyframe index -> frames placed from it so far

    def place(self, reference: int, measured: np.ndarray, covariance: np.ndarray) -> None:
        """The next reported frame was placed from ``reference`` by the body motion
        ``measured`` (T_ref_cur) with ``covariance`` (body frame, as weighed)."""
        reported = self._reported.get(reference)
        if reported is None:
            return
        count = self._counts.get(reference, 0) + 1
        self._counts[reference] = count
        self._placement = transport_covariance(reported, measured) + (count - 1) * covariance

    def report(
        self, index: int, body_pose: np.ndarray, marginal: np.ndarray | None
    ) -> np.ndarray | None:
        """The covariance to report for frame ``index`` whose smoother marginal is
        ``marginal`` (None stays None: nothing to add to)."""
        if self._placement is not None:
            self._carried, self._placement = self._placement, None
        elif self._pose is not None:
            self._carried = transport_covariance(self._carried, invert_pose(self._pose) @ body_pose)
        self._pose = body_pose.copy()
        if marginal is None:
            return None
        reported = marginal + self._carried
        reported = 0.5 * (reported + reported.T)
        self._reported[index] = reported
        return reported

    def anchor(self) -> None:
        """The smoother restarts pinned at the newest estimate: all of the newest frame's
        reported covariance is carried from here."""
        self._placement = None
        if self._reported:
            self._carried = self._reported[max(self._reported)].copy()

    def forget_before(self, oldest: int, kept: set[int] = frozenset()) -> None:
        """Drop the frames older than ``oldest`` but the ``kept`` keyframes (a revisit measures
        against them again)."""
        for index in [i for i in self._reported if i < oldest and i not in kept]:
            del self._reported[index]
            self._counts.pop(index, None)
