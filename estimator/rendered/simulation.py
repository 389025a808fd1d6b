"""Synthetic stereo-odometry registration problems with known ground truth.

A camera sees random 3D points, moves by a random rigid motion and sees them again. Only the
points that project inside a 640x480 pinhole image (``K [I | 0]``) in *both* views are kept,
as a feature tracker would. The second set gets Gaussian noise and a chosen fraction of the
pairs becomes wrong matches (the target of another visible point), which is how outliers
arise in real temporal matching.

Default scene (documented in docs/estimators.md): points at a uniformly random pixel of the
first image and a depth uniform in [2, 10] m (i.e. inside the first camera's view frustum);
motion = rotation by an angle uniform in [0, 30] deg about a uniformly random axis and a
translation of length uniform in [0, 1.5] m in a uniformly random direction. With 400 points
about 275 (mean; 5-95 % range 165-380) stay visible in the second image.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from estimator.geometry import quat_to_matrix, rotation_angle_deg, rotation_vector_to_quat

__all__ = [
    "DEFAULT_SCENE",
    "SimulatedPair",
    "camera_matrix",
    "random_motion",
    "rotation_error_deg",
    "simulate_pair",
    "translation_error",
    "visible",
]

DEFAULT_SCENE: dict[str, float] = {
    "width": 640.0,
    "height": 480.0,
    "focal": 500.0,
    "min_depth_m": 2.0,
    "max_depth_m": 10.0,
    "max_rotation_deg": 30.0,
    "max_translation_m": 1.5,
}


@dataclass
class SimulatedPair:
    """Corresponding points in two camera frames and the motion that relates the inliers."""

    source: np.ndarray  # (M, 3) points in the first camera frame
    target: np.ndarray  # (M, 3) in the second camera frame, noisy, with outliers
    rotation: np.ndarray  # true R (3x3) with target_inlier = R @ source + t
    translation: np.ndarray  # true t (3,)
    inlier_mask: np.ndarray  # (M,) bool, True for correct pairs
    # (M,) per-pair residual std along the viewing rays (``depth_noise`` only), else None
    noise_sigmas: np.ndarray | None = None


def camera_matrix(focal: float, width: float, height: float) -> np.ndarray:
    """Pinhole intrinsics with the principal point at the image centre (paper eq. 17)."""
    return np.array([[focal, 0.0, width / 2.0], [0.0, focal, height / 2.0], [0.0, 0.0, 1.0]])


def visible(points: np.ndarray, intrinsics: np.ndarray, width: float, height: float) -> np.ndarray:
    """Mask of points in front of the camera whose projection K [I|0] X lies in the image."""
    depth = points[:, 2]
    in_front = depth > 1e-6
    pixels = points @ intrinsics.T
    safe_depth = np.where(in_front, depth, 1.0)
    u = pixels[:, 0] / safe_depth
    v = pixels[:, 1] / safe_depth
    return in_front & (u >= 0.0) & (u < width) & (v >= 0.0) & (v < height)


def random_motion(
    rng: np.random.Generator, max_rotation_deg: float, max_translation_m: float
) -> tuple[np.ndarray, np.ndarray]:
    """Rotation of uniform angle about a uniform axis, translation of uniform length/direction."""
    axis = _unit_vector(rng)
    angle = np.radians(rng.uniform(0.0, max_rotation_deg))
    rotation = quat_to_matrix(rotation_vector_to_quat(axis * angle))
    translation = _unit_vector(rng) * rng.uniform(0.0, max_translation_m)
    return rotation, translation


def simulate_pair(
    n_points: int = 400,
    noise_sigma: float = 0.02,
    outlier_ratio: float = 0.0,
    rng: np.random.Generator | int | None = None,
    depth_noise: bool = False,
    **scene: float,
) -> SimulatedPair:
    """One registration problem: ``n_points`` drawn, the mutually visible ones kept.

    ``noise_sigma`` is the per-axis standard deviation (metres) added to the target points;
    ``round(outlier_ratio * M)`` of the M visible pairs (chosen at random) get the target of
    a different visible point. ``scene`` overrides keys of :data:`DEFAULT_SCENE`.

    ``depth_noise=True`` models stereo triangulation instead, whose depth error grows as
    Z^2 sigma_d / (f b): *both* point sets get noise along their own viewing ray with std
    ``noise_sigma * Z^2`` (so ``noise_sigma`` is the std at 1 m), and ``noise_sigmas`` holds
    each pair's residual std sqrt(sigma_source^2 + sigma_target^2).
    """
    _check_options(n_points, noise_sigma, outlier_ratio, scene)
    params = {**DEFAULT_SCENE, **scene}
    rng = np.random.default_rng(rng)
    points, moved, rotation, translation = _mutually_visible_scene(n_points, params, rng)
    source, target, noise_sigmas = _noisy_observations(points, moved, noise_sigma, depth_noise, rng)
    inlier_mask = _swap_in_outliers(target, outlier_ratio, rng)
    return SimulatedPair(source, target, rotation, translation, inlier_mask, noise_sigmas)


def _check_options(
    n_points: int, noise_sigma: float, outlier_ratio: float, scene: dict[str, float]
) -> None:
    """Reject bad arguments with one clear message before any random number is drawn."""
    unknown = set(scene) - set(DEFAULT_SCENE)
    if unknown:
        raise ValueError(f"unknown scene option(s) {sorted(unknown)}; known: {list(DEFAULT_SCENE)}")
    if n_points < 0:
        raise ValueError(f"n_points must be >= 0, got {n_points}")
    if not 0.0 <= outlier_ratio <= 1.0:
        raise ValueError(f"outlier_ratio must be in [0, 1], got {outlier_ratio}")
    if noise_sigma < 0.0:
        raise ValueError(f"noise_sigma must be >= 0, got {noise_sigma}")


def _mutually_visible_scene(
    n_points: int, params: dict[str, float], rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Points in the first view's frustum, a random motion, and the points seen in both views.

    Returns the kept points in the first and the second camera frame (noise-free) and the
    motion; keeping only mutually visible points mimics what a feature tracker can match.
    """
    width, height = params["width"], params["height"]
    intrinsics = camera_matrix(params["focal"], width, height)
    pixels = rng.uniform(0.0, 1.0, size=(n_points, 2)) * [width, height]
    depth = rng.uniform(params["min_depth_m"], params["max_depth_m"], n_points)
    rays = np.column_stack([pixels, np.ones(n_points)]) @ np.linalg.inv(intrinsics).T
    points = rays * depth[:, None]
    rotation, translation = random_motion(
        rng, params["max_rotation_deg"], params["max_translation_m"]
    )
    moved = points @ rotation.T + translation
    keep = visible(points, intrinsics, width, height) & visible(moved, intrinsics, width, height)
    return points[keep], moved[keep], rotation, translation


def _noisy_observations(
    source: np.ndarray,
    target: np.ndarray,
    noise_sigma: float,
    depth_noise: bool,
    rng: np.random.Generator,
) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """Isotropic noise on the target only, or stereo-like noise along the rays of both sets.

    Returns (source, target, per-pair residual std or None); the std is only known per pair
    when it depends on depth.
    """
    if not depth_noise:
        return source, target + rng.normal(0.0, noise_sigma, size=(len(target), 3)), None
    source, source_sigma = _along_rays(source, noise_sigma, rng)
    target, target_sigma = _along_rays(target, noise_sigma, rng)
    return source, target, np.hypot(source_sigma, target_sigma)


def _swap_in_outliers(
    target: np.ndarray, outlier_ratio: float, rng: np.random.Generator
) -> np.ndarray:
    """Give ``round(outlier_ratio * M)`` pairs another point's target (in place); inlier mask.

    A wrong match in temporal tracking lands on another real point, so outliers are drawn
    from the visible targets rather than from thin air.
    """
    count = len(target)
    n_outliers = round(outlier_ratio * count) if count > 1 else 0
    inlier_mask = np.ones(count, dtype=bool)
    if n_outliers:
        wrong = rng.choice(count, size=n_outliers, replace=False)
        # A shift in [1, count-1] never maps a pair onto itself: always a different point.
        partner = (wrong + rng.integers(1, count, size=n_outliers)) % count
        target[wrong] = target[partner].copy()
        inlier_mask[wrong] = False
    return inlier_mask


def _along_rays(
    points: np.ndarray, sigma_at_1m: float, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:
    """Stereo-like noise: each point slides along its viewing ray by N(0, (sigma Z^2)^2).

    Triangulation error is dominated by the disparity error, which moves the point along
    the ray through the camera centre; the lateral (pixel) error is negligible beside it.
    """
    depth = points[:, 2]
    sigma = sigma_at_1m * depth**2
    rays = points / np.linalg.norm(points, axis=1, keepdims=True)
    return points + rays * rng.normal(0.0, 1.0, len(points))[:, None] * sigma[:, None], sigma


def rotation_error_deg(rotation_estimate: np.ndarray, rotation_true: np.ndarray) -> float:
    """Geodesic angle (degrees) between the estimated and the true rotation."""
    return float(rotation_angle_deg(np.asarray(rotation_estimate).T @ np.asarray(rotation_true)))


def translation_error(translation_estimate: np.ndarray, translation_true: np.ndarray) -> float:
    """Euclidean distance (metres) between the estimated and the true translation."""
    difference = np.asarray(translation_estimate, float) - np.asarray(translation_true, float)
    return float(np.linalg.norm(difference))


def _unit_vector(rng: np.random.Generator) -> np.ndarray:
    vector = rng.normal(size=3)
    return vector / np.linalg.norm(vector)
