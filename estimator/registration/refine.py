"""Maximum-likelihood refinement of a rigid pose from 3D-3D pairs with full point covariances.

A stereo point is uncertain mostly along its viewing ray (depth noise grows like Z^2, lateral
noise like Z), so a registration that gives every pair one isotropic sigma lets depth noise leak
into the rotation. Given an initial pose and its inliers, this module minimises

    sum_j rho(r_j^T (R C_src_j R^T + C_tgt_j)^-1 r_j),   r_j = target_j - (R source_j + t),

the negative log-likelihood of independent Gaussian point errors, by Levenberg-Marquardt on
SE(3). The pose is perturbed on the right, T <- T Exp(xi) with xi = (omega, v) in the source
frame (R <- R Exp(omega), t <- t + R v), GTSAM's Pose3 convention, so the returned 6x6
covariance (the inverse Gauss-Newton Hessian) can be used as the covariance of a relative pose
factor as it is. The combined covariance depends on R and is re-evaluated every iteration;
``rho`` is optionally a Cauchy or Huber weight on the Mahalanobis distance for leftover
outliers.

The covariance of the estimate is the inverse Hessian scaled by the robust variance factor
(``covariance``: right when the normalised residuals are Gaussian) and, on request, the robust
sandwich A^-1 (sum_j g_j g_j^T) A^-1 (``sandwich_covariance``, Huber and White) with g_j each
pair's weighted gradient and A the Hessian of the robust cost: stereo residuals have heavy
tails (the 99th percentile of the squared distances at 40-90 where a chi-square with 3 DOF has
11), the pairs in the tail still weigh almost fully under a kernel at 6 sigma, and they move
the pose more than the median of the distances says. The sandwich counts what the observed
residuals actually do to the estimate.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np

from estimator.order_statistics import median
from estimator.registration.refine_kernels import (
    ROBUST_CODES,
    kernel_pairs,
    kernel_pose,
    levenberg_marquardt,
    linearise_pairs,
    scaled_condition,
    score_outer_products,
    squared_distances,
)

__all__ = [
    "CHI2_3_MEDIAN",
    "RefinementResult",
    "refine_pose_mahalanobis",
    "residual_spread",
    "squared_mahalanobis",
]

Robust = Literal["cauchy", "huber", "none"]

# A Jacobi-scaled Hessian with a larger condition number has a direction the data do not fix.
_MAX_CONDITION = 1e10
_MAX_DAMPING_TRIES = 6
_STEP_TOLERANCE = 1e-6  # rad / m: converged, far below any stereo noise
# A rejected step this small is the limit of Gauss-Newton with the covariances frozen in the
# linearisation (they depend on R), not a sign that damping would help: stop there.
_SETTLED_STEP = 1e-5
CHI2_3_MEDIAN = 2.365974  # median of a chi-square variable with 3 degrees of freedom
# The variance factor is a sample estimate: bounded so that a handful of pairs cannot claim an
# absurdly small or large covariance.
_MIN_VARIANCE_FACTOR, _MAX_VARIANCE_FACTOR = 1e-3, 1e3


@dataclass
class RefinementResult:
    """target ~ rotation @ source + translation; the input pose when ``success`` is False."""

    rotation: np.ndarray  # (3, 3)
    translation: np.ndarray  # (3,)
    # (6, 6) of (omega, v), right perturbation, scaled by ``variance_factor``; None on failure
    covariance: np.ndarray | None
    success: bool
    iterations: int
    initial_cost: float
    final_cost: float
    message: str = ""
    # A posteriori variance factor: how much larger (or smaller) the residuals are than the
    # point covariances predict (1 when they are right; robust: from the median distance).
    variance_factor: float = 1.0
    # The robust sandwich covariance (module doc; same frame and order), when it was asked for
    # and the pairs are enough (> 12); else None.
    sandwich_covariance: np.ndarray | None = None


@dataclass
class _Linearisation:
    cost: float
    hessian: np.ndarray  # (6, 6)
    gradient: np.ndarray  # (6,)
    squared: np.ndarray  # (N,) squared Mahalanobis distances of the pairs


def squared_mahalanobis(
    source: np.ndarray,
    target: np.ndarray,
    source_cov: np.ndarray,
    target_cov: np.ndarray,
    rotation: np.ndarray,
    translation: np.ndarray,
) -> np.ndarray:
    """(N,) r^T (R C_src R^T + C_tgt)^-1 r with r = target - (R source + t): the support test
    and the noise model's check use the same distance as the refinement. Raises
    ``LinAlgError`` on a singular point covariance."""
    squared, regular = squared_distances(
        *kernel_pairs(source, target, source_cov, target_cov), *kernel_pose(rotation, translation)
    )
    if not regular:
        raise np.linalg.LinAlgError("singular point covariance")
    return squared


def residual_spread(squared: np.ndarray) -> float:
    """sqrt(median d^2 / chi-square median) of pairs' squared Mahalanobis distances
    (``squared_mahalanobis`` at a pose): 1 when their covariances fit their residuals, below 1
    when the covariances are too generous (a session's first frames, still on the noise
    prior). A robust kernel in standard deviations times this is in units of the residuals' own
    robust spread (a scale-equivariant M-estimator), so a cluster of wrong pairs that generous
    covariances make look consistent is still weighed down. 1 for fewer than 6 pairs (no
    spread to measure)."""
    if len(squared) < 6:
        return 1.0
    middle = median(squared)
    return float(np.sqrt(middle / CHI2_3_MEDIAN)) if middle > 0 and np.isfinite(middle) else 1.0


def _linearise(
    source: np.ndarray,
    target: np.ndarray,
    source_cov: np.ndarray,
    target_cov: np.ndarray,
    rotation: np.ndarray,
    translation: np.ndarray,
    robust: Robust,
    scale: float,
) -> _Linearisation:
    """Cost, J^T W J and J^T W r over all pairs at once (IRLS weights from ``robust``).

    Worked in the source frame, where the residual is r' = R^T r, its covariance
    C_src + R^T C_tgt R and its Jacobian [[s]x, -I] (the right perturbation); one compiled
    pass over the pairs (``refine_kernels.linearise_pairs``).
    """
    cost, hessian, gradient, squared, regular = linearise_pairs(
        source, target, source_cov, target_cov, *kernel_pose(rotation, translation),
        ROBUST_CODES[robust], float(scale),
    )  # fmt: skip
    if not regular:
        raise np.linalg.LinAlgError("singular point covariance")
    return _Linearisation(float(cost), hessian, gradient, squared)


def _condition(hessian: np.ndarray) -> float:
    """Condition number after Jacobi scaling (radians and metres are not comparable units)."""
    return float(scaled_condition(np.ascontiguousarray(hessian, dtype=float)))


def _checked(array: np.ndarray, shape: tuple[int, ...], name: str) -> np.ndarray:
    array = np.asarray(array, dtype=float)
    if array.shape != shape:
        raise ValueError(f"{name} must have shape {shape}, got {array.shape}")
    return array


def _levenberg_marquardt(
    data: tuple[np.ndarray, ...],
    rotation: np.ndarray,
    translation: np.ndarray,
    current: _Linearisation,
    iterations: int,
    robust: Robust,
    robust_scale: float,
) -> tuple[np.ndarray, np.ndarray, _Linearisation, int]:
    """Accept only steps that do not raise the cost; damp harder after each rejection.

    One compiled loop (``refine_kernels.levenberg_marquardt``): a frame runs it a few times
    over about a hundred pairs, where a step's dozen small array calls cost more than its
    arithmetic. Returns the estimate, its linearisation and the number of accepted steps.
    """
    estimate_r, estimate_t, cost, hessian, gradient, squared, steps = levenberg_marquardt(
        *data, *kernel_pose(rotation, translation), current.cost, current.hessian,
        current.gradient, current.squared, int(iterations), ROBUST_CODES[robust],
        float(robust_scale), _MAX_DAMPING_TRIES, _STEP_TOLERANCE, _SETTLED_STEP,
    )  # fmt: skip
    return estimate_r, estimate_t, _Linearisation(float(cost), hessian, gradient, squared), steps


def _scaled_covariance(linearisation: _Linearisation) -> tuple[np.ndarray, float]:
    """The inverse Hessian scaled by the a posteriori variance factor.

    The point covariances come from nominal pixel and disparity sigmas; the residuals say how
    large the noise really was. Scaling by the robust variance factor (median squared
    distance over the median of chi-square with 3 degrees of freedom) makes the covariance
    match this frame's data, so a consumer weighs it neither too much nor too little.
    """
    variance_factor = median(linearisation.squared) / CHI2_3_MEDIAN
    variance_factor = min(max(variance_factor, _MIN_VARIANCE_FACTOR), _MAX_VARIANCE_FACTOR)
    covariance = variance_factor * np.linalg.inv(linearisation.hessian)
    return 0.5 * (covariance + covariance.T), variance_factor


def _sandwich_covariance(
    data: tuple[np.ndarray, ...],
    rotation: np.ndarray,
    translation: np.ndarray,
    linearisation: _Linearisation,
    robust: Robust,
    robust_scale: float,
) -> np.ndarray | None:
    """A^-1 B A^-1 times n / (n - 6) (the small-sample correction for six fitted parameters):
    B the sum of the pairs' outer gradient products, A the Hessian of the robust cost (the
    Gauss-Newton one less the kernel's own curvature, ``score_outer_products``; where that is
    not positive definite, the Gauss-Newton one). None when it cannot be formed."""
    count = len(data[0])
    if count <= 2 * 6:
        return None  # too few pairs to measure a 6x6 spread
    meat, curvature, regular = score_outer_products(
        *data, *kernel_pose(rotation, translation), ROBUST_CODES[robust], float(robust_scale)
    )
    if not regular or not np.isfinite(meat).all():
        return None
    bread = linearisation.hessian - curvature
    try:
        np.linalg.cholesky(bread)
    except np.linalg.LinAlgError:
        bread = linearisation.hessian
    inverse = np.linalg.inv(bread)
    covariance = inverse @ meat @ inverse * (count / (count - 6))
    covariance = 0.5 * (covariance + covariance.T)
    try:
        np.linalg.cholesky(covariance)
    except np.linalg.LinAlgError:
        return None  # the pairs' gradients span fewer than six directions
    return covariance


def refine_pose_mahalanobis(
    source: np.ndarray,
    target: np.ndarray,
    source_cov: np.ndarray,
    target_cov: np.ndarray,
    rotation: np.ndarray,
    translation: np.ndarray,
    iterations: int = 5,
    robust: Robust = "cauchy",
    robust_scale: float = 3.0,
    with_covariance: bool = True,
    sandwich: bool = False,
) -> RefinementResult:
    """Refine target ~ R source + t on inlier pairs weighed by their 3x3 covariances.

    Returns the input pose with ``success=False`` (never raises on data) when the pairs are
    too few, not finite, or leave a direction unconstrained; the cost never rises (steps that
    raise it are damped, Levenberg-Marquardt). ``robust_scale`` is in standard deviations.
    Without ``with_covariance`` the result's covariance is None and its variance factor 1:
    a caller that wants the pose alone (the support test's refits) skips the median and the
    inverse. With ``sandwich`` the result also carries the robust sandwich covariance
    (module doc), None when the pairs are too few (<= 12) to measure their spread.
    """
    n = len(np.asarray(source))
    source = _checked(source, (n, 3), "source")
    target = _checked(target, (n, 3), "target")
    source_cov = _checked(source_cov, (n, 3, 3), "source_cov")
    target_cov = _checked(target_cov, (n, 3, 3), "target_cov")
    rotation = _checked(rotation, (3, 3), "rotation")
    translation = _checked(translation, (3,), "translation")

    def unchanged(message: str, cost: float = np.nan) -> RefinementResult:
        return RefinementResult(
            rotation.copy(), translation.copy(), None, False, 0, cost, cost, message
        )

    if n < 3:
        return unchanged(f"{n} pairs (< 3)")
    arrays = (source, target, source_cov, target_cov, rotation, translation)
    if not all(np.isfinite(a).all() for a in arrays):
        return unchanged("non-finite input")
    data = kernel_pairs(source, target, source_cov, target_cov)
    try:
        current = _linearise(*data, rotation, translation, robust, robust_scale)
    except np.linalg.LinAlgError:
        return unchanged("a point covariance is singular")
    initial_cost = current.cost
    if not np.isfinite(initial_cost):
        return unchanged("non-finite cost", initial_cost)

    estimate_r, estimate_t, current, steps = _levenberg_marquardt(
        data, rotation, translation, current, iterations, robust, robust_scale
    )
    if not current.cost <= initial_cost:  # also catches NaN
        return unchanged("the cost rose", initial_cost)
    if _condition(current.hessian) > _MAX_CONDITION:
        return unchanged("ill-conditioned: the pairs do not fix all six degrees", initial_cost)
    covariance, variance_factor = _scaled_covariance(current) if with_covariance else (None, 1.0)
    robust_covariance = None
    if covariance is not None and sandwich:
        robust_covariance = _sandwich_covariance(
            data, estimate_r, estimate_t, current, robust, robust_scale
        )
    return RefinementResult(
        estimate_r, estimate_t, covariance, True, steps, initial_cost, current.cost,
        variance_factor=variance_factor, sandwich_covariance=robust_covariance,
    )  # fmt: skip
