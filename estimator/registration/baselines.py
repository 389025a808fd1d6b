"""Reference estimators the swarm is measured against: plain SVD and MSAC.

``svd``  - Arun/Kabsch on all pairs: optimal without outliers, breaks with the first one.
``msac`` - Torr & Zisserman's MSAC: random 3-point hypotheses scored by the truncated
           quadratic cost sum_j min(r_j^2, T^2), adaptive number of hypotheses, Kabsch refit
           on the inliers. Hypotheses are generated and scored in batches (one batched SVD
           and one (B, N) residual matrix per batch) so its timing is a fair comparison.
"""

from __future__ import annotations

import math

import numpy as np

from estimator.geometry import is_degenerate, kabsch, kabsch_batched
from estimator.registration.methods import Estimator, EstimatorSpec, register_method
from estimator.registration.result import (
    RegistrationResult,
    check_positive,
    failed_result,
    pose_result,
    reject_unknown_options,
    relative_scales,
    residual_norms,
)

__all__ = ["msac", "svd"]


@register_method(EstimatorSpec(Estimator.SVD, "least squares on all pairs"))
def svd(
    source: np.ndarray, target: np.ndarray, *, seed: int | None = None, **unknown: object
) -> RegistrationResult:
    """Arun et al. (1987) least squares on all pairs (``seed`` unused: deterministic)."""
    reject_unknown_options(Estimator.SVD, unknown)
    count = len(source)
    if count < 3:
        return failed_result(count, f"svd needs at least 3 pairs, got {count}")
    if is_degenerate(source) or is_degenerate(target):
        return failed_result(count, "points are coincident or collinear: rotation undetermined")
    rotation, translation = kabsch(source, target)
    residual = residual_norms(rotation, translation, source, target)
    return pose_result(
        rotation,
        translation,
        np.ones(count, dtype=bool),
        cost=float(residual @ residual),
        iterations=1,
    )


@register_method(
    EstimatorSpec(
        Estimator.MSAC,
        "random 3-point hypotheses, truncated quadratic cost",
        takes_sigmas=True,
    )
)
def msac(
    source: np.ndarray,
    target: np.ndarray,
    *,
    seed: int | None = None,
    threshold: float = 0.15,
    confidence: float = 0.999,
    max_iterations: int = 20000,
    batch_size: int = 64,
    refits: int = 3,
    sigmas: np.ndarray | None = None,
    **unknown: object,
) -> RegistrationResult:
    """MSAC: minimise sum_j min(r_j^2, T^2) over random 3-point Kabsch hypotheses.

    ``threshold`` T (metres) separates inliers; the number of hypotheses adapts to the best
    inlier ratio w found so far, k = log(1 - confidence) / log(1 - w^3), capped at
    ``max_iterations``. The winner is refitted on its inliers ``refits`` times.
    ``sigmas`` (N,) per-pair residual std: residuals are divided by sigma_j / median(sigma)
    (T then applies to a median pair), as ``pso-robust`` does; the refits stay unweighted.
    """
    reject_unknown_options(Estimator.MSAC, unknown)
    check_positive(threshold=threshold, batch_size=batch_size, max_iterations=max_iterations)
    if not 0.0 < confidence < 1.0:
        raise ValueError(f"confidence must be in (0, 1), got {confidence}")
    count = len(source)
    scales = np.ones(count) if sigmas is None else relative_scales(sigmas, count)
    if count < 4:
        # Three pairs fit any hypothesis exactly: a fourth is needed to check it at all.
        return failed_result(count, f"msac needs at least 4 pairs, got {count}")
    if is_degenerate(source) or is_degenerate(target):
        return failed_result(count, "points are coincident or collinear: rotation undetermined")
    rng = np.random.default_rng(seed)
    rotation, translation, drawn = _best_hypothesis(
        source, target, scales, rng, threshold, confidence, max_iterations, batch_size
    )
    rotation, translation, inliers = _refit_inliers(
        source, target, scales, rotation, translation, threshold, refits
    )
    squared = (residual_norms(rotation, translation, source, target) / scales) ** 2
    cost = float(np.minimum(squared, threshold * threshold).sum())
    if np.count_nonzero(inliers) < 3:
        return failed_result(count, "msac found fewer than 3 inliers", iterations=drawn)
    return pose_result(rotation, translation, inliers, cost=cost, iterations=drawn)


def _best_hypothesis(
    source: np.ndarray,
    target: np.ndarray,
    scales: np.ndarray,
    rng: np.random.Generator,
    threshold: float,
    confidence: float,
    max_iterations: int,
    batch_size: int,
) -> tuple[np.ndarray, np.ndarray, int]:
    """The 3-point hypothesis of least truncated cost, drawn in batches until the stopping
    rule (``msac``) is met: (R, t, hypotheses drawn)."""
    squared_cap = threshold * threshold
    best_cost, best_pose = math.inf, (np.eye(3), np.zeros(3))
    needed, drawn = max_iterations, 0
    while drawn < min(needed, max_iterations):
        batch = min(batch_size, max_iterations - drawn)
        rotations, translations = _hypotheses(rng, source, target, batch)
        squared = _scaled_squared_residuals(rotations, translations, source, target, scales)
        costs = np.minimum(squared, squared_cap).sum(axis=1)
        drawn += batch
        winner = int(np.argmin(costs))
        if costs[winner] < best_cost:
            best_cost = float(costs[winner])
            best_pose = (rotations[winner], translations[winner])
            ratio = np.count_nonzero(squared[winner] < squared_cap) / len(source)
            needed = _hypotheses_needed(ratio, confidence, max_iterations)
    return *best_pose, drawn


def _hypotheses(
    rng: np.random.Generator, source: np.ndarray, target: np.ndarray, batch: int
) -> tuple[np.ndarray, np.ndarray]:
    """``batch`` Kabsch fits of random triplets: rotations (B, 3, 3), translations (B, 3)."""
    samples = _triplets(rng, len(source), batch)
    return kabsch_batched(source[samples], target[samples])


def _scaled_squared_residuals(
    rotations: np.ndarray,
    translations: np.ndarray,
    source: np.ndarray,
    target: np.ndarray,
    scales: np.ndarray,
) -> np.ndarray:
    """(B, N) squared residual of every pair under every hypothesis, over its relative scale."""
    predicted = source @ rotations.transpose(0, 2, 1) + translations[:, None, :]
    return np.sum((target - predicted) ** 2, axis=2) / scales**2


def _refit_inliers(
    source: np.ndarray,
    target: np.ndarray,
    scales: np.ndarray,
    rotation: np.ndarray,
    translation: np.ndarray,
    threshold: float,
    refits: int,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Kabsch on the inliers, at most ``refits`` times or until the inlier set repeats:
    (R, t, inlier mask)."""
    inliers = residual_norms(rotation, translation, source, target) / scales < threshold
    for _ in range(refits):
        if np.count_nonzero(inliers) < 3 or is_degenerate(source[inliers]):
            break
        rotation, translation = kabsch(source[inliers], target[inliers])
        residual = residual_norms(rotation, translation, source, target) / scales
        refitted = residual < threshold
        if np.array_equal(refitted, inliers):
            break
        inliers = refitted
    return rotation, translation, inliers


def _triplets(rng: np.random.Generator, count: int, batch: int) -> np.ndarray:
    """(batch, 3) indices of three distinct pairs each, drawn without a Python loop."""
    first = rng.integers(0, count, batch)
    second = (first + rng.integers(1, count, batch)) % count
    third = rng.integers(0, count - 2, batch)
    # Skip over the two taken indices in increasing order so the third is distinct.
    low, high = np.minimum(first, second), np.maximum(first, second)
    third = third + (third >= low)
    third = third + (third >= high)
    return np.stack([first, second, third], axis=1)


def _hypotheses_needed(ratio: float, confidence: float, cap: int) -> int:
    """Standard RANSAC stopping rule for 3-point samples."""
    good = ratio**3
    if good <= 0.0:
        return cap
    if good >= 1.0:
        return 1
    return min(cap, math.ceil(math.log(1.0 - confidence) / math.log(1.0 - good)))
