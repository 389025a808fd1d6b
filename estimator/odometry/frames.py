"""Input images and seeds, and the records one frame leaves: a reference and an estimate."""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass

import cv2
import numpy as np

from estimator.formats.calibration import Rectification
from estimator.frontend.stereo import StereoPoints
from estimator.frontend.stereo_noise import flow
from estimator.frontend.temporal import Correspondences
from estimator.odometry.chains import PointSensitivity
from estimator.registration.registry import RegistrationResult
from estimator.types import StereoFrame

__all__ = [
    "CurrentFrame",
    "Estimate",
    "Reference",
    "checked_pose",
    "failed",
    "frame_seed",
    "grey_pair",
    "inlier_flow",
    "stage",
    "to_grey8",
]


def frame_seed(seed: int, index: int) -> int:
    """Estimator seed of frame ``index``: reproducible in any process, distinct per frame."""
    return int(np.random.SeedSequence([seed, index]).generate_state(1)[0])


def to_grey8(image: np.ndarray, name: str = "image") -> np.ndarray:
    """8-bit grey from grey / BGR / BGRA images of 8 or 16 bits (16-bit scaled by 1/257)."""
    image = np.asarray(image)
    if image.dtype not in (np.uint8, np.uint16):
        raise ValueError(f"{name} must be uint8 or uint16, got {image.dtype}")
    if image.ndim == 3 and image.shape[2] == 1:
        image = image[:, :, 0]
    if image.ndim == 3 and image.shape[2] in (3, 4):
        code = cv2.COLOR_BGR2GRAY if image.shape[2] == 3 else cv2.COLOR_BGRA2GRAY
        image = cv2.cvtColor(image, code)
    if image.ndim != 2:
        raise ValueError(f"{name} must be (H, W) grey or (H, W, 3|4) colour, got {image.shape}")
    if image.dtype == np.uint16:
        image = (image.astype(np.uint32) * 255 + 32767) // 65535  # full range onto 0..255
    return np.ascontiguousarray(image, dtype=np.uint8)


def grey_pair(frame: StereoFrame, shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """The frame's left and right images as 8-bit grey; a clear error when one is not of the
    calibration's ``shape`` (height, width)."""
    left = to_grey8(frame.left, "left image")
    right = to_grey8(frame.right, "right image")
    for name, image in (("left", left), ("right", right)):
        if image.shape != shape:
            raise ValueError(
                f"{name} image is {image.shape[1]}x{image.shape[0]}, the calibration "
                f"expects {shape[1]}x{shape[0]}"
            )
    return left, right


def checked_pose(pose: np.ndarray) -> np.ndarray:
    matrix = np.asarray(pose, dtype=float)
    if matrix.shape != (4, 4) or not np.isfinite(matrix).all():
        raise ValueError(f"initial_pose must be a finite 4x4 matrix, got shape {matrix.shape}")
    rotation = matrix[:3, :3]
    if (
        np.abs(rotation.T @ rotation - np.eye(3)).max() > 1e-6
        or np.linalg.det(rotation) < 0
        or not np.allclose(matrix[3], [0, 0, 0, 1])
    ):
        raise ValueError("initial_pose must be a rigid transform (rotation block orthonormal)")
    return matrix


@dataclass
class Reference:
    """The frame the current one is matched against, with its front-end pose."""

    index: int
    timestamp_ns: int
    points: StereoPoints
    image: np.ndarray  # rectified left image
    pose: np.ndarray  # left camera in world (original camera frame)


@dataclass
class CurrentFrame:
    """The frame being measured: what every measurement of it against a reference takes."""

    index: int
    timestamp_ns: int
    points: StereoPoints
    image: np.ndarray  # rectified left image
    timings: dict[str, float]  # the frame report's stage timings, added to as it goes


@dataclass
class Estimate:
    """A relative pose of the current frame w.r.t. the reference, or why there is none."""

    reference_from_current: np.ndarray | None  # rectified frames; None when the estimate failed
    result: RegistrationResult | None
    message: str
    pairs: Correspondences | None = None
    reference: Reference | None = None  # the frame it was measured against
    # 6x6 of (rotation, translation), right perturbation, when the pose was refined.
    covariance: np.ndarray | None = None
    # The covariance the frame report carries when it is not ``covariance`` (the one the back
    # end weighs; ``registration.refine_covariance``); None: ``covariance``.
    reported_covariance: np.ndarray | None = None
    # The covariance the next frame's chain link takes when it is not ``covariance``: the
    # combination's own, without this frame's common error, which ``covariance`` counts once
    # (odometry/combination.py, ``ChainCombination``); None: ``covariance``.
    chain_covariance: np.ndarray | None = None
    # (N, 3, 3) covariances of the current and reference points of ``pairs``.
    point_covariances: tuple[np.ndarray, np.ndarray] | None = None
    # How the refined pose moves with the current and with the reference points (only when
    # a chain is combined).
    sensitivity: PointSensitivity | None = None
    reference_sensitivity: PointSensitivity | None = None
    # Fills in the two above when called: they cost a solve per point and only a chain uses
    # them, so they are formed when one does (``sensitivities_of``).
    pending_sensitivity: Callable[[], None] | None = None


def sensitivities_of(
    estimate: Estimate,
) -> tuple[PointSensitivity | None, PointSensitivity | None]:
    """The estimate's current and reference point sensitivities, formed now if still pending."""
    pending, estimate.pending_sensitivity = estimate.pending_sensitivity, None
    if pending is not None:
        pending()
    return estimate.sensitivity, estimate.reference_sensitivity


def inlier_flow(estimate: Estimate, rectification: Rectification) -> np.ndarray:
    """(N,) image motion (px) of the estimate's inliers; empty when it has none."""
    if estimate.pairs is None or estimate.result is None:
        return np.zeros(0)
    inliers = estimate.result.inliers
    pairs = estimate.pairs
    return flow(pairs.current_points[inliers], pairs.reference_points[inliers], rectification)


def failed(estimate: Estimate, reason: str) -> Estimate:
    """The estimate turned into a failed one (no pose), keeping its matches for the report."""
    message = f"{estimate.message}; {reason}" if estimate.message else reason
    return Estimate(None, estimate.result, message, estimate.pairs, estimate.reference)


@contextmanager
def stage(timings: dict[str, float], name: str) -> Iterator[None]:
    """Adds the wall time of the block to ``timings[name]`` (the frame report's timings)."""
    start = time.perf_counter()
    try:
        yield
    finally:
        timings[name] = timings.get(name, 0.0) + time.perf_counter() - start
