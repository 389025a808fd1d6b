"""The pieces the swarm estimators share: pairs with their noise, the rotation objective
and the final least-squares step.

``Pairs`` carries each pair's relative noise scale as the refits use it, ``RotationObjective``
scores rotation-vector particles against anchored pairs through their compressed Horn forms
(``swarm_kernels.pair_forms``), and ``finish`` turns a supporter set into a
``RegistrationResult``. The algorithm that strings them together is ``pso_support``.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from estimator.geometry import kabsch, matrix_to_quat
from estimator.registration.result import (
    RegistrationResult,
    failed_result,
    pose_result,
    residual_norms,
)
from estimator.registration.swarm_kernels import (
    MIN_SUPPORT,
    degenerate_points,
    degenerate_rows,
    fit_pose,
    horn_fit,
    pair_forms,
    swarm_residuals,
    swarm_scores,
)

__all__ = [
    "Fit",
    "Graph",
    "Pairs",
    "Pose",
    "RotationObjective",
    "arun_fit",
    "finish",
    "rows_mask",
    "weighted_horn",
]

# (quaternion, rotation, translation, normalised residuals of all pairs) of a fit.
Pose = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]
# A least-squares pose of the pairs in a mask, with everyone's normalised residual.
Fit = Callable[[np.ndarray, np.ndarray, np.ndarray], Pose]


@dataclass(frozen=True)
class Graph:
    """The rigidity graph: the pair rows it was built on and their (S, S) weights."""

    sample: np.ndarray
    weights: np.ndarray


@dataclass(frozen=True)
class Pairs:
    """The pairs and their per-pair noise, as the refits use it.

    ``inverse`` = 1 / scale normalises residuals, ``weights`` = 1 / scale^2 weighs the
    least squares; both are all ones without ``sigmas``.
    """

    source: np.ndarray
    target: np.ndarray
    inverse: np.ndarray
    weights: np.ndarray

    @classmethod
    def of(cls, source: np.ndarray, target: np.ndarray, scales: np.ndarray | None) -> Pairs:
        if scales is None:
            ones = np.ones(len(source))
            return cls(source, target, ones, ones)
        inverse = 1.0 / scales
        return cls(source, target, inverse, inverse * inverse)

    def fit(self, source: np.ndarray, target: np.ndarray, mask: np.ndarray) -> Pose:
        """Horn's least squares on the pairs in ``mask``, weighted by 1 / scale^2."""
        return fit_pose(source, target, mask, self.weights, self.inverse)

    def pose_of(self, supporters: np.ndarray) -> Pose | None:
        """The fit of the supporters and everyone's normalised residual; None if degenerate."""
        rows = np.flatnonzero(supporters)
        if len(rows) < MIN_SUPPORT or degenerate_points(self.source, rows):
            return None
        return self.fit(self.source, self.target, supporters)


class RotationObjective:
    """Support and cost of rotation-vector particles against centred pairs, all at once.

    The pairs are anchored as R (p - c) and p' - c', with c, c' the centroids of the
    ``anchor`` rows, and divided by their scale (which divides the residual by it); each
    then enters as its Horn form, compressed to the 10 distinct coefficients of the
    symmetric 4x4 matrix (``pair_forms``).
    """

    def __init__(
        self,
        source: np.ndarray,
        target: np.ndarray,
        anchor: np.ndarray,
        rotation: np.ndarray,
        delta: float,
        inverse_scales: np.ndarray | None = None,
    ) -> None:
        if inverse_scales is None:
            inverse_scales = np.ones(len(source))
        self.forms, self.norms = pair_forms(source, target, anchor, rotation, inverse_scales)
        self.delta_squared = float(delta * delta)

    def squared_residuals(self, positions: np.ndarray) -> np.ndarray:
        """(P, M) ||t_j - q_p s_j q_p^-1||^2 via |t|^2 + |s|^2 - 2 q^T N_j q (normalised)."""
        positions = np.ascontiguousarray(positions, dtype=float)
        return swarm_residuals(positions, self.forms, self.norms)

    def sum_of_squares(self, positions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The paper: support (eq. 15) and the plain sum of squared residuals (eq. 13)."""
        return swarm_scores(positions, self.forms, self.norms, self.delta_squared, False)

    def truncated(self, positions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Support and the MSAC cost sum min(r^2, delta^2), which outliers cannot dominate."""
        return swarm_scores(positions, self.forms, self.norms, self.delta_squared, True)

    def supporters(self, position: np.ndarray) -> np.ndarray:
        return self.squared_residuals(position[None, :])[0] < self.delta_squared


def rows_mask(rows: np.ndarray, count: int) -> np.ndarray:
    mask = np.zeros(count, dtype=bool)
    mask[rows] = True
    return mask


def weighted_horn(
    source: np.ndarray, target: np.ndarray, weights: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Horn's closed form for min sum_j w_j ||t_j - (R s_j + t)||^2 (weighted centroids).

    Returns (quaternion with w >= 0, R, t); the compiled fit every refit round uses.
    """
    source = np.ascontiguousarray(source, dtype=float)
    target = np.ascontiguousarray(target, dtype=float)
    weights = np.ascontiguousarray(weights, dtype=float)
    return horn_fit(source, target, weights, np.ones(len(source), dtype=np.bool_))


def arun_fit(source: np.ndarray, target: np.ndarray, mask: np.ndarray) -> Pose:
    """The paper's final step: SVD (Arun, with the det guard), then eq. 8 for t."""
    rotation, translation = kabsch(source[mask], target[mask])
    residual = residual_norms(rotation, translation, source, target)
    return matrix_to_quat(rotation), rotation, translation, residual


def finish(
    source: np.ndarray,
    target: np.ndarray,
    supporters: np.ndarray,
    delta: float,
    iterations: int,
    fit: Fit,
    pose: Pose | None = None,
) -> RegistrationResult:
    """Least-squares pose of the supporters: t = mean(p') - R mean(p) over them (eq. 8).

    ``pose`` is ``fit`` of the supporters when the caller has already computed it. The
    cost sum_j min(u_j^2, delta^2) is over the pose's (normalised) residuals u_j.
    """
    count = len(source)
    rows = np.flatnonzero(supporters)
    if len(rows) < MIN_SUPPORT:
        return failed_result(
            count,
            f"only {len(rows)} pair(s) support the best rotation (need {MIN_SUPPORT}); "
            f"delta={delta:.3g} m may be too small for the noise",
            iterations=iterations,
        )
    if degenerate_rows(source, target, rows):
        return failed_result(count, "the supporting pairs are collinear", iterations=iterations)
    quaternion, rotation, translation, residual = pose or fit(source, target, supporters)
    cost = float(np.minimum(residual * residual, delta * delta).sum())
    return pose_result(
        rotation, translation, supporters, cost=cost, iterations=iterations, quaternion=quaternion
    )
