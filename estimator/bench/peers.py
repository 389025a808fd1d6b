"""Peer estimators the registration benchmark compares swarmvo against.

Each peer wraps one library's robust estimator behind the same contract as
``estimator.register``: corresponding points in, :class:`RegistrationResult` out. To compare
like with like, every peer is finished the same way: the pairs its model explains within the
common inlier threshold ``tau`` are refitted with Kabsch (``estimator.geometry.kabsch``), and
the reported inliers are the pairs within ``tau`` of that refit. The oracle is Kabsch on the
*true* inliers: the accuracy floor set by the noise alone.

The libraries belong to the optional ``bench`` extra; a missing one is reported, not fatal.
"""

from __future__ import annotations

import importlib.util
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy.stats import chi2

from estimator.baselines import failed_result, pose_result, residual_norms
from estimator.geometry import kabsch
from estimator.registration import RegistrationResult

__all__ = [
    "INLIER_QUANTILE",
    "PEERS",
    "Peer",
    "inlier_threshold",
    "oracle",
    "peer_missing_package",
    "run_peer",
]

# Residual |target - (R source + t)| of an inlier is sigma * chi(3) when the target carries
# isotropic noise of per-axis sigma; its 99 % quantile keeps 99 % of the true inliers.
INLIER_QUANTILE = 0.99
_CHI3_FACTOR = float(np.sqrt(chi2.ppf(INLIER_QUANTILE, df=3)))  # ~3.37
MIN_PAIRS = 3


def inlier_threshold(noise_sigma: float) -> float:
    """Common inlier threshold tau (metres) for a per-axis noise sigma: ~3.37 sigma."""
    if not noise_sigma > 0.0:
        raise ValueError(f"noise sigma must be > 0 to set an inlier threshold, got {noise_sigma}")
    return _CHI3_FACTOR * noise_sigma


def _fit(
    source: np.ndarray, target: np.ndarray, chosen: np.ndarray, threshold: float, iterations: int
) -> RegistrationResult:
    """Kabsch on ``chosen`` pairs; inliers and MSAC cost measured against ``threshold``."""
    if chosen.sum() < MIN_PAIRS:
        return failed_result(len(source), f"fewer than {MIN_PAIRS} pairs to refit", iterations)
    rotation, translation = kabsch(source[chosen], target[chosen])
    residuals = residual_norms(rotation, translation, source, target)
    inliers = residuals < threshold
    return pose_result(
        rotation,
        translation,
        inliers,
        cost=float(np.minimum(residuals**2, threshold**2).sum()),
        iterations=iterations,
        success=bool(inliers.sum() >= MIN_PAIRS),
    )


def _refit_model(
    source: np.ndarray,
    target: np.ndarray,
    linear: np.ndarray,
    offset: np.ndarray,
    threshold: float,
) -> RegistrationResult:
    """The peer's model (any 3x3 ``linear`` + ``offset``) -> its tau-inliers -> Kabsch."""
    chosen = residual_norms(linear, offset, source, target) < threshold
    return _fit(source, target, chosen, threshold, iterations=0)


# ----------------------------------------------------------------------------- the peers


def _magsac(
    source: np.ndarray, target: np.ndarray, threshold: float, seed: int, max_iterations: int
) -> RegistrationResult:
    """MAGSAC++ (Barath et al. 2020) from ``pymagsac.findRigidTransformation``.

    ``sigma_th`` is MAGSAC's upper bound on the noise scale; it gets tau. The uniform sampler
    is used because the benchmark gives no match-quality prior (the default AR-sampler needs
    one). pymagsac exposes no seed, so its rows are not bit-reproducible.
    """
    import pymagsac

    del seed  # not exposed by pymagsac
    correspondences = np.ascontiguousarray(np.hstack([source, target]), dtype=np.float64)
    pose, _ = pymagsac.findRigidTransformation(
        correspondences,
        np.ones(len(source)),
        sampler=0,
        use_magsac_plus_plus=True,
        sigma_th=threshold,
        conf=0.999,
        min_iters=50,
        max_iters=max_iterations,
    )
    if pose is None:
        return failed_result(len(source), "pymagsac returned no model")
    # pymagsac returns the 4x4 transform transposed (row-vector convention).
    matrix = np.asarray(pose, dtype=float).T
    return _refit_model(source, target, matrix[:3, :3], matrix[:3, 3], threshold)


def _open3d(
    source: np.ndarray, target: np.ndarray, threshold: float, seed: int, max_iterations: int
) -> RegistrationResult:
    """Open3D ``registration_ransac_based_on_correspondence`` with the tutorial's checkers.

    The edge-length (0.9) and distance (tau) checkers reject most outlier samples before
    Open3D's expensive scoring, which is by nearest neighbour in the target cloud.
    """
    import open3d as o3d

    registration = o3d.pipelines.registration
    o3d.utility.random.seed(int(seed) % (2**31))
    indices = np.repeat(np.arange(len(source), dtype=np.int32)[:, None], 2, axis=1)
    result = registration.registration_ransac_based_on_correspondence(
        o3d.geometry.PointCloud(o3d.utility.Vector3dVector(source)),
        o3d.geometry.PointCloud(o3d.utility.Vector3dVector(target)),
        o3d.utility.Vector2iVector(indices),
        threshold,
        registration.TransformationEstimationPointToPoint(False),
        3,
        [
            registration.CorrespondenceCheckerBasedOnEdgeLength(0.9),
            registration.CorrespondenceCheckerBasedOnDistance(threshold),
        ],
        registration.RANSACConvergenceCriteria(max_iterations, 0.999),
    )
    matrix = np.asarray(result.transformation, dtype=float)
    if len(result.correspondence_set) == 0:
        return failed_result(len(source), "open3d found no consensus")
    return _refit_model(source, target, matrix[:3, :3], matrix[:3, 3], threshold)


def _opencv_affine(
    source: np.ndarray, target: np.ndarray, threshold: float, seed: int, max_iterations: int
) -> RegistrationResult:
    """OpenCV ``estimateAffine3D``: RANSAC over 4-point *affine* samples, then rigid refit.

    OpenCV fixes its iteration cap (1000 in OpenCV 5); ``max_iterations`` cannot reach it.
    """
    import cv2

    del max_iterations  # not configurable in cv2.estimateAffine3D
    cv2.setRNGSeed(int(seed) % (2**31))
    found, affine, _ = cv2.estimateAffine3D(
        source, target, ransacThreshold=threshold, confidence=0.999
    )
    if not found or affine is None:
        return failed_result(len(source), "cv2.estimateAffine3D found no model")
    affine = np.asarray(affine, dtype=float)
    return _refit_model(source, target, affine[:, :3], affine[:, 3], threshold)


PeerFn = Callable[[np.ndarray, np.ndarray, float, int, int], RegistrationResult]


@dataclass(frozen=True)
class Peer:
    """A third-party estimator: its import name and how it is configured (for the docs)."""

    package: str
    function: PeerFn
    summary: str


PEERS: dict[str, Peer] = {
    "magsac++": Peer(
        "pymagsac",
        _magsac,
        "pymagsac.findRigidTransformation, MAGSAC++, uniform sampler, sigma_th=tau, "
        "confidence 0.999, iteration cap --peer-max-iterations; + Kabsch refit",
    ),
    "open3d-ransac": Peer(
        "open3d",
        _open3d,
        "open3d registration_ransac_based_on_correspondence, point-to-point, 3-point samples, "
        "edge-length 0.9 + distance checkers, confidence 0.999, cap --peer-max-iterations; "
        "+ Kabsch refit",
    ),
    "opencv-affine3d": Peer(
        "cv2",
        _opencv_affine,
        "cv2.estimateAffine3D, RANSAC over affine 4-point samples, threshold tau, "
        "confidence 0.999, OpenCV's fixed 1000-iteration cap; + rigid Kabsch refit",
    ),
}


def peer_missing_package(name: str) -> str | None:
    """The peer's package name if it is not installed, else None."""
    package = PEERS[name].package
    return package if importlib.util.find_spec(package) is None else None


def run_peer(
    name: str,
    source: np.ndarray,
    target: np.ndarray,
    *,
    noise_sigma: float,
    seed: int,
    max_iterations: int = 100_000,
) -> RegistrationResult:
    """Run peer ``name``; ``elapsed_s`` covers the library call and the Kabsch refit."""
    if name not in PEERS:
        raise ValueError(f"unknown peer {name!r}; peers: {', '.join(PEERS)}")
    if max_iterations < 1:
        raise ValueError(f"max_iterations must be >= 1, got {max_iterations}")
    source = np.ascontiguousarray(source, dtype=np.float64)
    target = np.ascontiguousarray(target, dtype=np.float64)
    threshold = inlier_threshold(noise_sigma)
    start = time.perf_counter()
    if len(source) < MIN_PAIRS:
        result = failed_result(len(source), f"fewer than {MIN_PAIRS} pairs")
    else:
        result = PEERS[name].function(source, target, threshold, seed, max_iterations)
    result.elapsed_s = time.perf_counter() - start
    result.method = name
    return result


def oracle(source: np.ndarray, target: np.ndarray, true_inliers: np.ndarray) -> RegistrationResult:
    """Kabsch on the true inliers only: the error no estimator can beat on average."""
    true_inliers = np.asarray(true_inliers, dtype=bool)
    start = time.perf_counter()
    if true_inliers.sum() < MIN_PAIRS:
        result = failed_result(len(source), f"fewer than {MIN_PAIRS} true inliers")
    else:
        rotation, translation = kabsch(source[true_inliers], target[true_inliers])
        result = pose_result(rotation, translation, true_inliers.copy(), cost=0.0, iterations=0)
    result.elapsed_s = time.perf_counter() - start
    result.method = "oracle"
    return result
