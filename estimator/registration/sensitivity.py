"""How a refined pose moves with its points: the linear sensitivity of the estimate.

The Mahalanobis refinement (``refine.py``) solves the weighted least squares
sum_j w_j r_j'^T S_j^-1 r_j' with r_j' = R^T (target_j - t) - source_j and the Jacobian
J_j = [[source_j]x, -I] of the right perturbation xi = (omega, v). At its minimum the step
xi = -H^-1 sum_j J_j^T W_j r_j' vanishes (W_j = w_j S_j^-1, H = sum_j J_j^T W_j J_j); moving
source point j by e_j changes r_j' by -e_j and J_j by [[e_j]x, 0], so the estimate by K_j e_j,
K_j = H^-1 (J_j^T W_j - [[W_j r_j']x; 0]) (the robust weights and the rotation inside S_j held).

Two poses estimated from the same source points (one frame measured against two references)
therefore have correlated errors, cov = sum over the shared points of K_j C_j K'_j^T; this is
what a combination of the two needs in order not to count those points twice.
"""

from __future__ import annotations

import numpy as np

from estimator.registration.refine import Robust
from estimator.registration.refine_kernels import (
    ROBUST_CODES,
    kernel_pairs,
    kernel_pose,
    sensitivity_terms,
)

__all__ = ["point_sensitivities"]


def point_sensitivities(
    source: np.ndarray,
    target: np.ndarray,
    source_cov: np.ndarray,
    target_cov: np.ndarray,
    rotation: np.ndarray,
    translation: np.ndarray,
    robust: Robust = "cauchy",
    robust_scale: float = 3.0,
) -> tuple[np.ndarray, np.ndarray] | None:
    """(N, 6, 3) d xi / d source_j and d xi / d target_j at the refined pose (right
    perturbation, source frame); None when the pairs do not fix all six degrees or a
    covariance is singular. A target point enters only through r_j' (by R^T), so its gain is
    -H^-1 J_j^T W_j R^T.

    Sum_j K_j S_j K_j^T is the unscaled refinement covariance H^-1 without robust weights;
    the source points' share of it is sum_j K_j C_src_j K_j^T. The per-pair terms come from
    one compiled pass (``refine_kernels.sensitivity_terms``).
    """
    own, other, hessian, regular = sensitivity_terms(
        *kernel_pairs(source, target, source_cov, target_cov),
        *kernel_pose(rotation, translation), ROBUST_CODES[robust], float(robust_scale),
    )  # fmt: skip
    if not regular:
        return None
    try:
        inverse = np.linalg.inv(hessian)
    except np.linalg.LinAlgError:
        return None
    if not np.isfinite(inverse).all():
        return None
    return inverse @ own, inverse @ other
