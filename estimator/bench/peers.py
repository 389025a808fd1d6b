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

import cv2
import numpy as np
from scipy.stats import chi2

from estimator.geometry import kabsch
from estimator.registration.registry import RegistrationResult
from estimator.registration.result import failed_result, pose_result, residual_norms

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


# ----------------------------------------------------------------------------- whole-pipeline peer


@dataclass
class StereoVoPeerOptions:
    """Plain OpenCV stereo VO, as a user would first write it (every number a common default)."""

    features: int = 2000
    row_tolerance_px: float = 1.5
    min_disparity_px: float = 1.0
    max_disparity_px: float = 160.0
    max_hamming: int = 64
    ransac_reprojection_px: float = 2.0
    ransac_iterations: int = 200
    min_points: int = 12


def _stereo_features(
    orb: cv2.ORB, left: np.ndarray, right: np.ndarray, fx: float, cx: float, cy: float,
    baseline: float, options: StereoVoPeerOptions,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:  # fmt: skip
    """Left keypoints (N, 2), their descriptors and 3D points from row-constrained matching."""
    left_kp, left_desc = orb.detectAndCompute(left, None)
    right_kp, right_desc = orb.detectAndCompute(right, None)
    if left_desc is None or right_desc is None:
        return np.empty((0, 2)), np.empty((0, 32), np.uint8), np.empty((0, 3))
    left_xy = np.array([k.pt for k in left_kp])
    right_xy = np.array([k.pt for k in right_kp])
    distances = _hamming(left_desc, right_desc)
    disparity = left_xy[:, None, 0] - right_xy[None, :, 0]
    allowed = (np.abs(left_xy[:, None, 1] - right_xy[None, :, 1]) <= options.row_tolerance_px) & (
        (disparity >= options.min_disparity_px) & (disparity <= options.max_disparity_px)
    )
    distances = np.where(allowed, distances, 1 << 20)
    best = distances.argmin(axis=1)
    rows = np.arange(len(left_xy))
    keep = distances[rows, best] <= options.max_hamming
    rows, best = rows[keep], best[keep]
    d = disparity[rows, best]
    depth = fx * baseline / d
    points = np.column_stack(
        [(left_xy[rows, 0] - cx) * depth / fx, (left_xy[rows, 1] - cy) * depth / fx, depth]
    )
    return left_xy[rows], left_desc[rows], points


def _hamming(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(len(a), len(b)) Hamming distances of binary descriptors."""
    bits = np.unpackbits(a, axis=1).astype(np.int32)
    other = np.unpackbits(b, axis=1).astype(np.int32)
    return bits.sum(1)[:, None] + other.sum(1)[None, :] - 2 * bits @ other.T


def opencv_stereo_vo(
    sequence, limit: int | None = None, options: StereoVoPeerOptions | None = None
) -> tuple[np.ndarray, np.ndarray, int]:
    """Left-camera poses of plain OpenCV stereo VO: ORB, row-constrained stereo matching, then
    ``cv2.solvePnPRansac`` of the current keypoints against the previous frame's 3D points.

    Returns (timestamps_ns, (N, 4, 4) poses of the original left camera, frames failed); a
    failed frame keeps the previous pose.
    """
    options = options or StereoVoPeerOptions()
    rect = sequence.rig.rectification
    camera = np.array([[rect.fx, 0, rect.cx], [0, rect.fx, rect.cy], [0, 0, 1.0]])
    rect_from_camera = np.eye(4)
    rect_from_camera[:3, :3] = rect.R_left
    orb = cv2.ORB_create(options.features)
    matcher = cv2.BFMatcher(cv2.NORM_HAMMING, crossCheck=True)
    count = len(sequence) if limit is None else min(limit, len(sequence))
    pose = np.eye(4)  # rectified left camera of frame k in that of frame 0
    poses, stamps, failed, previous = [], [], 0, None
    for index in range(count):
        frame = sequence.load(index)
        left, right = rect.rectify(_grey(frame.left), _grey(frame.right))
        xy, descriptors, points = _stereo_features(
            orb, left, right, rect.fx, rect.cx, rect.cy, rect.baseline, options
        )
        if previous is not None:
            motion = _pnp_motion(matcher, previous, xy, descriptors, camera, options)
            if motion is None:
                failed += 1
            else:
                pose = pose @ motion
        poses.append(np.linalg.inv(rect_from_camera) @ pose @ rect_from_camera)
        stamps.append(frame.timestamp_ns)
        previous = (descriptors, points)
    return np.array(stamps, dtype=np.int64), np.array(poses), failed


def _pnp_motion(
    matcher: cv2.BFMatcher,
    previous: tuple[np.ndarray, np.ndarray],
    xy: np.ndarray,
    descriptors: np.ndarray,
    camera: np.ndarray,
    options: StereoVoPeerOptions,
) -> np.ndarray | None:
    """T_prev_cur (rectified) from PnP of the current keypoints on the previous 3D points."""
    previous_descriptors, previous_points = previous
    if len(previous_points) < options.min_points or len(xy) < options.min_points:
        return None
    matches = matcher.match(previous_descriptors, descriptors)
    matches = [m for m in matches if m.distance <= options.max_hamming]
    if len(matches) < options.min_points:
        return None
    object_points = previous_points[[m.queryIdx for m in matches]]
    image_points = xy[[m.trainIdx for m in matches]]
    found, rvec, tvec, inliers = cv2.solvePnPRansac(
        object_points, image_points, camera, None,
        iterationsCount=options.ransac_iterations,
        reprojectionError=options.ransac_reprojection_px,
        confidence=0.999, flags=cv2.SOLVEPNP_ITERATIVE,
    )  # fmt: skip
    if not found or inliers is None or len(inliers) < options.min_points:
        return None
    current_from_previous = np.eye(4)
    current_from_previous[:3, :3] = cv2.Rodrigues(rvec)[0]
    current_from_previous[:3, 3] = tvec.ravel()
    return np.linalg.inv(current_from_previous)


def _grey(image: np.ndarray) -> np.ndarray:
    image = np.asarray(image)
    if image.ndim == 3:
        image = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    if image.dtype == np.uint16:
        image = (image // 257).astype(np.uint8)
    return image
