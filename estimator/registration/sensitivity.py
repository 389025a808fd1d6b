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

from estimator.geometry import skew
from estimator.registration.refine import Robust

__all__ = ["point_sensitivities"]


def _robust_weights(squared: np.ndarray, robust: Robust, scale: float) -> np.ndarray:
    """The IRLS weights the refinement used (``refine_kernels.linearise_pairs``)."""
    if robust == "cauchy":
        return 1.0 / (1.0 + squared / (scale * scale))
    if robust == "huber":
        distance = np.sqrt(squared)
        return np.where(distance > scale, scale / np.maximum(distance, 1e-300), 1.0)
    return np.ones_like(squared)


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
    the source points' share of it is sum_j K_j C_src_j K_j^T.
    """
    source = np.asarray(source, dtype=float)
    residual = (np.asarray(target, dtype=float) - translation) @ rotation - source
    combined = source_cov + np.einsum("ki,nkl,lj->nij", rotation, target_cov, rotation)
    try:
        information = np.linalg.inv(combined)
    except np.linalg.LinAlgError:
        return None
    squared = np.einsum("ni,nij,nj->n", residual, information, residual)
    weighted = information * _robust_weights(squared, robust, robust_scale)[:, None, None]
    jacobian = np.zeros((len(source), 3, 6))
    jacobian[:, :, :3] = skew(source)
    jacobian[:, :, 3:] = -np.eye(3)
    transposed = np.einsum("nki,nkj->nij", jacobian, weighted)  # (N, 6, 3) J^T W
    hessian = np.einsum("nik,nkj->ij", transposed, jacobian)
    target_side = -transposed @ rotation.T
    # J_j depends on source_j too: d(J_j^T W_j r_j')/d source_j = -J_j^T W_j + [[W_j r_j']x; 0]
    # (first order: a single pair's residual is not small, only their weighted sum vanishes).
    pulled = np.einsum("nij,nj->ni", weighted, residual)
    transposed[:, :3, :] -= skew(pulled)
    try:
        inverse = np.linalg.inv(hessian)
    except np.linalg.LinAlgError:
        return None
    if not np.isfinite(inverse).all():
        return None
    return (
        np.einsum("ij,njk->nik", inverse, transposed),
        np.einsum("ij,njk->nik", inverse, target_side),
    )
