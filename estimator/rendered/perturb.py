"""What real cameras do to a clean stereo sequence, reproducibly.

Real stereo cameras change exposure on their own (left and right not in step), run at lower
frame rates or drop frames, deliver black or motion-blurred frames and get noisy in dim light;
their left and right shutters may not fire together. :func:`perturb_sequence` wraps a recorded
:class:`~estimator.formats.datasets.Sequence` so that every loaded frame carries those effects,
seeded per (frame, camera): the same sequence, perturbation and seed always give the same pixels, in
any order of loading. Ground truth, calibration and IMU are left as they are.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from estimator.formats.datasets import Sequence
from estimator.types import StereoFrame

__all__ = ["PERTURBATIONS", "Perturbation", "PerturbedSequence", "perturb_sequence"]

_LEFT, _RIGHT = 0, 1


@dataclass(frozen=True)
class Perturbation:
    """Camera effects applied to every frame of a sequence (all off by default)."""

    # Gain drawn uniformly from [low, high] independently per frame and camera (auto exposure
    # out of step); pixels are multiplied, rounded and clipped to the 8-bit range.
    gain: tuple[float, float] | None = None
    keep_every: int = 1  # frame-rate reduction: keep every n-th frame (2: 20 Hz -> 10 Hz)
    drop_probability: float = 0.0  # frames lost at random (after the rate reduction)
    black_every: int = 0  # every n-th frame is all black (frames n-1, 2n-1, ...)
    blur_every: int = 0  # every n-th frame is motion blurred (frames n-1, 2n-1, ...)
    blur_length_px: int = 25  # length of the motion-blur streak
    noise_sigma: float = 0.0  # additive Gaussian pixel noise (grey levels)
    # Right shutter this many milliseconds late: the right image is warped by the rotation of
    # the right camera over that time (ground truth; parallax of the translation neglected).
    right_delay_ms: float = 0.0
    seed: int = 0

    def __post_init__(self) -> None:
        if self.gain is not None and not 0 < self.gain[0] <= self.gain[1]:
            raise ValueError(f"gain range must satisfy 0 < low <= high, got {self.gain}")
        if self.keep_every < 1:
            raise ValueError(f"keep_every must be >= 1, got {self.keep_every}")
        if not 0 <= self.drop_probability < 1:
            raise ValueError(f"drop_probability must be in [0, 1), got {self.drop_probability}")
        for name in ("black_every", "blur_every", "blur_length_px", "right_delay_ms"):
            if getattr(self, name) < 0:
                raise ValueError(f"{name} must be >= 0, got {getattr(self, name)}")
        if self.noise_sigma < 0:
            raise ValueError(f"noise_sigma must be >= 0, got {self.noise_sigma}")


# The suite the perturbation benchmark and the tests run (names are the table's rows).
PERTURBATIONS: dict[str, Perturbation] = {
    "none": Perturbation(),
    "gain flicker 0.6-1.4": Perturbation(gain=(0.6, 1.4)),
    "10 Hz": Perturbation(keep_every=2),
    "black every 10th": Perturbation(black_every=10),
    "blurred every 10th": Perturbation(blur_every=10),
    "10 % frames dropped": Perturbation(drop_probability=0.1),
    "noise sigma 6": Perturbation(noise_sigma=6.0),
    "right shutter 5 ms late": Perturbation(right_delay_ms=5.0),
}


def _rng(seed: int, index: int, camera: int, effect: int) -> np.random.Generator:
    """One generator per (frame, camera, effect): independent of the order of loading."""
    return np.random.default_rng([seed, index, camera, effect])


def _kept_frames(count: int, perturbation: Perturbation) -> list[int]:
    """Source indices of the frames that reach the odometry (rate reduction, then drops)."""
    kept = list(range(0, count, perturbation.keep_every))
    if perturbation.drop_probability > 0:
        draws = np.random.default_rng([perturbation.seed, 1 << 20]).random(len(kept))
        draws[0] = 1.0  # the first frame always arrives: it defines the world
        kept = [index for index, draw in zip(kept, draws, strict=True)
                if draw >= perturbation.drop_probability]  # fmt: skip
    return kept


def _motion_blur(image: np.ndarray, length: int, rng: np.random.Generator) -> np.ndarray:
    """A straight streak of ``length`` pixels in a random direction (a shaken camera)."""
    if length < 2:
        return image
    kernel = np.zeros((length, length), np.float32)
    kernel[length // 2, :] = 1.0
    angle = float(rng.uniform(0.0, 180.0))
    rotation = cv2.getRotationMatrix2D(((length - 1) / 2, (length - 1) / 2), angle, 1.0)
    kernel = cv2.warpAffine(kernel, rotation, (length, length))
    kernel /= kernel.sum()
    return cv2.filter2D(image, -1, kernel, borderType=cv2.BORDER_REFLECT)


@dataclass
class PerturbedSequence(Sequence):
    """A sequence whose frames are loaded with :class:`Perturbation` effects applied."""

    perturbation: Perturbation = field(default_factory=Perturbation)
    source_index: list[int] = field(default_factory=list)  # perturbed -> source frame

    def load(self, index: int) -> StereoFrame:
        frame = super().load(index)
        right = frame.right
        if self.perturbation.right_delay_ms > 0:
            right = self._delayed_right(right, frame.timestamp_ns)
        left = self._apply(frame.left, index, _LEFT)
        right = self._apply(right, index, _RIGHT)
        return StereoFrame(frame.timestamp_ns, left, right)

    def _delayed_right(self, image: np.ndarray, timestamp_ns: int) -> np.ndarray:
        """The right image as a shutter ``right_delay_ms`` later would see it (rotation only)."""
        if self.ground_truth is None:
            raise ValueError("a right-shutter delay needs the sequence's ground truth")
        delay_ns = round(self.perturbation.right_delay_ms * 1e6)
        end = min(timestamp_ns + delay_ns, int(self.ground_truth.timestamps_ns[-1]))
        body = self.ground_truth.interpolate(np.array([timestamp_ns, end]))
        camera = body @ self.rig.right.T_BS
        rotation = camera[0, :3, :3].T @ camera[1, :3, :3]  # later camera in the earlier one
        K = self.rig.right.K
        homography = K @ rotation.T @ np.linalg.inv(K)
        height, width = image.shape[:2]
        return cv2.warpPerspective(image, homography, (width, height), flags=cv2.INTER_LINEAR,
                                   borderMode=cv2.BORDER_REPLICATE)  # fmt: skip

    def _apply(self, image: np.ndarray, index: int, camera: int) -> np.ndarray:
        p = self.perturbation
        if image.dtype != np.uint8:
            raise ValueError(f"perturbations need 8-bit images, got {image.dtype}")
        if p.black_every and index % p.black_every == p.black_every - 1:
            return np.zeros_like(image)
        if p.blur_every and index % p.blur_every == p.blur_every - 1:
            # Both cameras shake together: one direction per frame.
            image = _motion_blur(image, p.blur_length_px, _rng(p.seed, index, _LEFT, 0))
        values = image.astype(np.float32)
        if p.gain is not None:
            values *= float(_rng(p.seed, index, camera, 1).uniform(*p.gain))
        if p.noise_sigma > 0:
            values += _rng(p.seed, index, camera, 2).normal(0.0, p.noise_sigma, image.shape)
        return np.clip(np.rint(values), 0, 255).astype(np.uint8)


def perturb_sequence(sequence: Sequence, perturbation: Perturbation) -> PerturbedSequence:
    """``sequence`` as a camera with ``perturbation`` would have recorded it."""
    kept = _kept_frames(len(sequence), perturbation)
    return PerturbedSequence(
        name=sequence.name,
        format=sequence.format,
        root=sequence.root,
        rig=sequence.rig,
        frames=[sequence.frames[index] for index in kept],
        imu=sequence.imu,
        imu_noise=sequence.imu_noise,
        ground_truth=sequence.ground_truth,
        perturbation=perturbation,
        source_index=kept,
    )
