"""The scale ladder of pso-robust (step 5 of ``pso_support``): widen a threshold fitted to
the quietest pairs until it covers the noise of the rest.

A threshold estimated from a few pairs fits *their* noise; with heteroscedastic noise (stereo
depth error grows with depth squared) the core may be the quiet pairs and the refit loop
converges on them alone. The ladder doubles the threshold while that adds markedly more
supporters than one Gaussian scale allows, refitting each time with IRLS weights.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from estimator.registration.support_pairs import Pairs, Pose, rows_mask
from estimator.registration.swarm_kernels import MIN_SUPPORT

__all__ = ["LADDER_GAIN", "Refine", "climb_ladder"]

# Double the threshold while support grows by at least this fraction.
LADDER_GAIN = 0.05

# The estimator's refit loop: (pairs, supporters, threshold, adapt, residual, floor) ->
# (supporters, threshold, pose or None).
Refine = Callable[
    [Pairs, np.ndarray, float, bool, np.ndarray | None, float | None],
    tuple[np.ndarray, float, Pose | None],
]


def climb_ladder(
    pairs: Pairs,
    supporters: np.ndarray,
    delta: float,
    pose: Pose | None,
    core: np.ndarray,
    refine: Refine,
    delta_max: float,
) -> tuple[np.ndarray, float, Pose | None]:
    """Double the adaptive threshold while that adds markedly more supporters.

    At the converged pose one Gaussian scale puts ~0.1 % of the inliers between 4 and 8
    sigma, and wrong matches rarely land that close to the model; a gain of
    ``LADDER_GAIN`` (and at least ``MIN_SUPPORT`` pairs) therefore means that the
    threshold fitted only the quietest pairs (heteroscedastic noise). (Homoscedastic
    noise along one axis, e.g. stereo rays, settles the RMS rule at ~2.1 sigma with
    ~96 % of the inliers; doubling gains ~4 %, below the bar, so it is left alone.)
    Each accepted step refits (``refine``) with the doubled threshold held fixed
    (re-estimating it from the RMS of mixed scales would shrink it again), weighing each
    pair by 1 / max(u, delta_0)^2 of its previous normalised residual u.

    The threshold from the core can be so tight that fewer than ``MIN_SUPPORT`` pairs
    pass it (a core of the quietest pairs, e.g. the nearest points of a scene that
    reaches 200 m): there is then no supporters' pose to judge, and the ladder starts
    from the fit of the ``core`` (row indices) itself.
    """
    base = delta
    while True:
        wider = min(2.0 * delta, delta_max)
        if pose is None:  # the loop did not settle: judge the pose of its last set
            pose = pairs.pose_of(supporters)
        if pose is None:  # too few to fit: the core's own pose
            pose = pairs.pose_of(rows_mask(core, len(supporters)))
        if pose is None or wider <= delta:
            return supporters, delta, pose
        residual = pose[3]
        support = int(np.count_nonzero(supporters))
        widened = residual < wider
        gained = int(np.count_nonzero(widened)) - support
        if gained < max(MIN_SUPPORT, LADDER_GAIN * support):
            return supporters, delta, pose
        supporters, delta, pose = refine(pairs, widened, wider, False, residual, base)
