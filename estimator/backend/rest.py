"""Standstill detection and the gyro bias it yields (static initialisation).

Only vision tells a gyro bias from a real rotation once the platform moves, so the front end's
slow heading drift leaks into the bias estimate. At rest the gyro reads its bias plus white
noise: the mean over a rest window of T seconds estimates the bias to density / sqrt(T).

A window counts as rest when its samples look like sensor noise around a constant, judged
with the sensor sheet's densities only (no per-sequence tuning): per axis, the sample variance
of gyro and accelerometer must stay below its chi-square bound for white noise, the specific
force must be gravity-sized, and a window that extends an earlier rest window must have the
same mean (within the noise of both means plus the bias random walk over the span). Slow,
smooth motion hardly raises the variance, but it changes the mean specific force (any
acceleration) or the mean rate (any turn), which the last test catches.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from estimator.backend.imu import GRAVITY
from estimator.types import ImuNoise

__all__ = ["RestWindow", "at_rest"]

# A bias beyond this is taken as motion (ADIS16448-class gyros: ~0.1 rad/s at most).
_MAX_GYRO_BIAS = 0.2  # rad/s
# Accelerometer bias plus local gravity deviation allowed in the norm of the mean.
_MAX_ACCEL_OFFSET = 0.3  # m/s^2


@dataclass
class RestWindow:
    """Sums over the IMU samples of a rest window (grows while the rest goes on)."""

    count: int
    gyro_sum: np.ndarray  # (3,)
    accel_sum: np.ndarray  # (3,)
    start_ns: int
    end_ns: int

    @classmethod
    def of(cls, stamps_ns: np.ndarray, gyro: np.ndarray, accel: np.ndarray) -> RestWindow:
        return cls(
            len(stamps_ns),
            np.asarray(gyro, dtype=float).sum(axis=0),
            np.asarray(accel, dtype=float).sum(axis=0),
            int(stamps_ns[0]),
            int(stamps_ns[-1]),
        )

    def extend(self, stamps_ns: np.ndarray, gyro: np.ndarray, accel: np.ndarray) -> None:
        self.count += len(stamps_ns)
        self.gyro_sum = self.gyro_sum + np.asarray(gyro, dtype=float).sum(axis=0)
        self.accel_sum = self.accel_sum + np.asarray(accel, dtype=float).sum(axis=0)
        self.end_ns = max(self.end_ns, int(stamps_ns[-1]))

    @property
    def duration_s(self) -> float:
        return (self.end_ns - self.start_ns) * 1e-9

    @property
    def gyro_mean(self) -> np.ndarray:
        """The bias estimate: the mean angular rate over the window."""
        return self.gyro_sum / self.count

    @property
    def accel_mean(self) -> np.ndarray:
        return self.accel_sum / self.count

    def bias_sigma(self, noise: ImuNoise) -> float:
        """Per-axis sigma of ``gyro_mean`` as the bias at the window's end.

        White noise averages to density / sqrt(T) (n samples of sigma density * sqrt(rate));
        the bias also walks, and the end value differs from the window mean by a random walk
        averaged over T: variance random_walk^2 T / 3.
        """
        sample_sigma = noise.gyro_noise_density * np.sqrt(noise.rate_hz)
        span = max(self.duration_s, 1.0 / noise.rate_hz)
        return float(np.sqrt(sample_sigma**2 / self.count + noise.gyro_random_walk**2 * span / 3.0))


def _variance_bound(sigma: float, count: int, z: float) -> float:
    """Upper bound of a white-noise sample variance: (n-1) s^2 / sigma^2 ~ chi2(n-1)."""
    return sigma**2 * (1.0 + z * np.sqrt(2.0 / max(count - 1, 1)))


def at_rest(
    gyro: np.ndarray,
    accel: np.ndarray,
    noise: ImuNoise,
    z: float = 5.0,
    reference: RestWindow | None = None,
) -> bool:
    """Whether IMU samples (M, 3) look like a platform at rest (see module doc).

    ``z`` is the number of standard deviations each test allows (5: a still sensor fails
    a test about once in a million windows). ``reference``: an earlier rest window these
    samples must agree with in mean.
    """
    gyro = np.asarray(gyro, dtype=float).reshape(-1, 3)
    accel = np.asarray(accel, dtype=float).reshape(-1, 3)
    count = len(gyro)
    if count < 2 or len(accel) != count:
        return False
    gyro_sigma = noise.gyro_noise_density * np.sqrt(noise.rate_hz)
    accel_sigma = noise.accel_noise_density * np.sqrt(noise.rate_hz)
    if np.any(gyro.var(axis=0, ddof=1) > _variance_bound(gyro_sigma, count, z)):
        return False
    if np.any(accel.var(axis=0, ddof=1) > _variance_bound(accel_sigma, count, z)):
        return False
    gyro_mean, accel_mean = gyro.mean(axis=0), accel.mean(axis=0)
    if np.any(np.abs(gyro_mean) > _MAX_GYRO_BIAS):
        return False
    if abs(float(np.linalg.norm(accel_mean)) - GRAVITY) > _MAX_ACCEL_OFFSET:
        return False
    if reference is None:
        return True
    # Means of two disjoint windows: noise of both plus the bias walk over the whole span.
    span = reference.duration_s + count / noise.rate_hz
    share = 1.0 / count + 1.0 / reference.count
    gyro_spread = np.sqrt(gyro_sigma**2 * share + noise.gyro_random_walk**2 * span)
    accel_spread = np.sqrt(accel_sigma**2 * share + noise.accel_random_walk**2 * span)
    return bool(
        np.all(np.abs(gyro_mean - reference.gyro_mean) <= z * gyro_spread)
        and np.all(np.abs(accel_mean - reference.accel_mean) <= z * accel_spread)
    )
