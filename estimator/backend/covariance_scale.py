"""Per-session scale of the reported covariances, measured online against the gyro.

The front end's measurement covariance comes from a fixed noise model (stereo pixel noise
through the rigid fit, plus floors). It fits one world and misses the other: on rendered
flights the actual errors are about half the reported sigmas, on real images about twice
(``swarmvo bench consistency``). The errors that the model misses are common to the points of
a frame (calibration, timing, blur), so the fit's residuals cannot reveal them; an independent
sensor can. With an IMU, each keyframe-to-frame measurement's rotation is compared with the
gyro integrated over the same interval (bias removed with the back end's estimate):

    e = Log(R_gyro^T R_vision),   q(s) = e^T (s V + G)^-1 e

with V the measurement's reported rotation covariance and G the gyro's own (white noise plus
an allowance for the bias error). ``s`` is the variance factor that makes the median of q over
the recent measurements equal the median of chi-square with 3 DOF: median-based, so that a
wrong measurement or a start-up bias cannot carry it, and bounded. The translation shares the
factor: the missing error affects both blocks alike in the benchmark (rendered 0.27 / 0.26,
MH_01 4.7 / 4.0 per DOF, rotation / translation), and the IMU cannot measure translation that
finely. Without an IMU, or before ``covariance_scale_min_samples`` comparisons, the factor is 1.

The session median does not follow episodes of a second or so in which the errors of
consecutive measurements add up (they share a keyframe, and the back end's gyro bias follows
them): on MH_01 a few windows had rotation errors 10-35 times their covariance. A time-local
factor (:class:`ChainDisagreement`) compares the chained vision rotation over the last second
with the gyro; the pose covariance's growth is scaled by the larger of the two.
Both are kept in the back end's resume state, so a resumed session continues with them.

The factor scales the covariances the pipeline reports (odometry messages); the back end's
factor noise is left as it is, so the trajectory does not change.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable
from typing import Any

import gtsam
import numpy as np

from estimator.backend.imu import GyroPreintegration
from estimator.backend.scale_kernels import spectra_statistic
from estimator.config import BackendConfig
from estimator.geometry import invert_pose

__all__ = ["ChainDisagreement", "CovarianceScale", "GyroCalibration", "GyroChain"]

# Median of chi-square with 3 DOF, chi2.ppf(0.5, 3), to the last bit: importing scipy.stats
# for it cost every back-end process 34 MB and half a second.
_CHI2_3_MEDIAN = 2.3659738843753377
_CHI2_3_MEAN = 3.0
_BISECTION_STEPS = 40


Spectra = tuple[np.ndarray, np.ndarray]  # (N, 3) eigenvalues lambda, (N, 3) weights f^2


def solve_factor(
    statistic: Callable[[np.ndarray], float],
    target: float,
    errors: np.ndarray,
    vision: np.ndarray,
    gyro: np.ndarray,
    bounds: tuple[float, float],
) -> float:
    """The factor s whose ``statistic`` of q(s) = e^T (s V + G)^-1 e over the samples equals
    ``target``; q falls as s grows, so bisection on log s finds it (or a bound)."""
    errors = np.asarray(errors, dtype=float)
    spectra = disagreement_spectra(errors, vision, gyro)
    if spectra is not None:
        return solve_factor_spectra(statistic, target, spectra, bounds)

    def solved(log_scale: float) -> float:
        covariance = np.exp(log_scale) * vision + gyro
        solution = np.linalg.solve(covariance, errors[..., None])[..., 0]
        return float(statistic(np.einsum("ni,ni->n", errors, solution)))

    return _bisect(solved, target, bounds)


def solve_factor_spectra(
    statistic: Callable[[np.ndarray], float],
    target: float,
    spectra: Spectra,
    bounds: tuple[float, float],
) -> float:
    """``solve_factor`` of samples decomposed by ``disagreement_spectra`` (kept per sample
    by a caller that adds one sample a frame to a window of hundreds).

    The median and the mean run compiled (``scale_kernels.py``, the same numbers); any other
    statistic in NumPy.
    """
    eigenvalues, weights = spectra
    median = _COMPILED.get(statistic)
    if median is not None:
        eigenvalues = np.ascontiguousarray(eigenvalues, dtype=float)
        weights = np.ascontiguousarray(weights, dtype=float)

        def compiled(log_scale: float) -> float:
            return spectra_statistic(eigenvalues, weights, float(np.exp(log_scale)), median)

        return _bisect(compiled, target, bounds)

    def decomposed(log_scale: float) -> float:
        return float(statistic((weights / (np.exp(log_scale) * eigenvalues + 1.0)).sum(axis=1)))

    return _bisect(decomposed, target, bounds)


def _bisect(value: Callable[[float], float], target: float, bounds: tuple[float, float]) -> float:
    # Python floats: the same IEEE arithmetic as NumPy scalars at a fraction of the overhead.
    low, high = float(np.log(bounds[0])), float(np.log(bounds[1]))
    if value(high) >= target:
        return bounds[1]
    if value(low) <= target:
        return bounds[0]
    for _ in range(_BISECTION_STEPS):
        middle = 0.5 * (low + high)
        if value(middle) > target:
            low = middle
        else:
            high = middle
    return float(np.exp(0.5 * (low + high)))


def disagreement_spectra(
    errors: np.ndarray, vision: np.ndarray, gyro: np.ndarray
) -> Spectra | None:
    """The samples (N, 3), (N, 3, 3), (N, 3, 3) decomposed so that q(s) is elementwise.

    With G = L L^T and L^-1 V L^-T = U diag(lambda) U^T, s V + G = L U (s diag(lambda) + I)
    U^T L^T, so q(s) = sum_k f_k^2 / (s lambda_k + 1) with f = U^T L^-1 e: three divisions
    per sample instead of a 3x3 solve at each of the bisection's ~40 evaluations. None when a
    gyro covariance is not positive definite (no bias allowance): the caller solves instead.
    """
    try:
        inverse_root = np.linalg.inv(np.linalg.cholesky(gyro))
    except np.linalg.LinAlgError:
        return None
    whitened = inverse_root @ vision @ np.swapaxes(inverse_root, -1, -2)
    eigenvalues, eigenvectors = np.linalg.eigh(0.5 * (whitened + np.swapaxes(whitened, -1, -2)))
    weights = np.einsum("nji,njk,nk->ni", eigenvectors, inverse_root, errors) ** 2
    return np.maximum(eigenvalues, 0.0), weights  # V is positive semi-definite: rounding only


def _median(values: np.ndarray) -> float:
    """``np.median`` of a 1-D array (the same number, NaN when one is NaN) without its
    generic machinery: the bisection takes about 40 medians per frame."""
    count = len(values)
    if count == 0 or np.isnan(values).any():
        return float("nan")
    half = count // 2
    if count % 2:
        return float(np.partition(values, half)[half])
    part = np.partition(values, (half - 1, half))
    return float((part[half - 1] + part[half]) / 2.0)


# Statistics with a compiled bisection step: True for the median, False for the mean.
_COMPILED: dict[Callable[[np.ndarray], float], bool] = {
    _median: True,
    np.median: True,
    np.mean: False,
}


class GyroChain:
    """The gyro intervals of the recent frames, composed between any two of them.

    Each interval keeps its first-order bias Jacobian, so the composition removes the bias
    estimated now rather than the one of the moment it was integrated (the estimate moves
    most during the first seconds). Intervals are independent in their white noise: the
    covariance of a composition is the sum of theirs, each carried to the last frame.
    """

    def __init__(self) -> None:
        self._intervals: dict[int, tuple[int, GyroPreintegration]] = {}  # end -> (start, gyro)
        self._last_ns: int | None = None

    def extend(self, timestamp_ns: int, interval: GyroPreintegration | None) -> None:
        """Append the interval ending at ``timestamp_ns`` (None: a gap, the chain restarts)."""
        if interval is None:
            self._intervals.clear()
        elif self._last_ns is not None:
            self._intervals[int(timestamp_ns)] = (self._last_ns, interval)
        self._last_ns = int(timestamp_ns)

    def between(
        self, first_ns: int, last_ns: int, bias: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray] | None:
        """(R_first^T R_last, its covariance) with ``bias`` removed; None when a piece is
        missing."""
        rotation, covariance = np.eye(3), np.zeros((3, 3))
        stamp = int(last_ns)
        pieces = []
        while stamp > first_ns:
            if stamp not in self._intervals:
                return None
            start, interval = self._intervals[stamp]
            pieces.append(interval)
            stamp = start
        if stamp != first_ns or not pieces:
            return None
        for interval in reversed(pieces):
            correction = interval.bias_jacobian @ (bias - interval.bias_hat)
            step = interval.delta_rotation @ gtsam.Rot3.Expmap(correction).matrix()
            rotation = rotation @ step
            covariance = step.T @ covariance @ step + interval.covariance
        return rotation, covariance

    def forget_before(self, timestamp_ns: int) -> None:
        """Drop intervals that end by ``timestamp_ns`` (no later measurement needs them)."""
        for stamp in [s for s in self._intervals if s <= timestamp_ns]:
            del self._intervals[stamp]


class CovarianceScale:
    """Online variance factor of the measurement covariance (module doc)."""

    def __init__(
        self,
        window: int = 400,
        min_samples: int = 20,
        bounds: tuple[float, float] = (1 / 16, 16.0),
        bias_sigma: float = 2e-4,
    ) -> None:
        """``window`` recent comparisons are kept; ``bias_sigma`` (rad/s) is the gyro bias error
        allowed for; the factor stays within ``bounds``."""
        if not 0 < bounds[0] <= 1 <= bounds[1]:
            raise ValueError(f"covariance scale bounds must enclose 1, got {bounds}")
        self.bounds = bounds
        self.min_samples = int(min_samples)
        self.bias_sigma = float(bias_sigma)
        self._errors: deque[np.ndarray] = deque(maxlen=window)
        self._vision: deque[np.ndarray] = deque(maxlen=window)
        self._gyro: deque[np.ndarray] = deque(maxlen=window)
        # Each sample decomposed once, when it arrives (None: its gyro covariance is singular).
        self._spectra: deque[Spectra | None] = deque(maxlen=window)
        # The same spectra in a ring (slot i: the sample appended i, i + window, ... th), so
        # that a solve reads them without joining 400 small arrays; the median ignores order.
        self._ring = np.full((2, window, 3), np.nan)  # eigenvalues, weights
        self._slot = 0
        self._value = 1.0

    @property
    def value(self) -> float:
        return self._value

    @property
    def samples(self) -> int:
        return len(self._errors)

    def observe(
        self,
        vision_rotation: np.ndarray,
        vision_covariance: np.ndarray,
        gyro_rotation: np.ndarray,
        gyro_covariance: np.ndarray,
        duration_s: float,
    ) -> float:
        """Add one comparison over the same interval (body frame, right perturbations) and
        return the updated factor."""
        error = np.asarray(gtsam.Rot3.Logmap(gtsam.Rot3(gyro_rotation.T @ vision_rotation)))
        bias = (self.bias_sigma * duration_s) ** 2 * np.eye(3)
        if not (np.isfinite(error).all() and np.isfinite(vision_covariance).all()):
            return self._value
        self._errors.append(error)
        self._vision.append(np.asarray(vision_covariance, dtype=float))
        self._gyro.append(np.asarray(gyro_covariance, dtype=float) + bias)
        spectrum = disagreement_spectra(error[None], self._vision[-1][None], self._gyro[-1][None])
        self._spectra.append(spectrum)
        if spectrum is not None:
            self._ring[0, self._slot], self._ring[1, self._slot] = spectrum[0][0], spectrum[1][0]
        self._slot = (self._slot + 1) % self._ring.shape[1]
        if len(self._errors) >= self.min_samples:
            self._value = self._solve()
        return self._value

    def _solve(self) -> float:
        """The factor whose median normalised disagreement is chi-square(3)'s median."""
        if None not in self._spectra:  # every sample decomposed (identity test per item)
            count = len(self._spectra)  # the ring's first ``count`` slots until it is full
            spectra = (self._ring[0, :count], self._ring[1, :count])
            return solve_factor_spectra(_median, _CHI2_3_MEDIAN, spectra, self.bounds)
        errors, vision, gyro = np.array(self._errors), np.array(self._vision), np.array(self._gyro)
        return solve_factor(_median, _CHI2_3_MEDIAN, errors, vision, gyro, self.bounds)

    def state(self) -> dict[str, float]:
        return {"value": self._value}

    def restore(self, state: dict[str, float]) -> None:
        """Continue from a stored factor; it holds until ``min_samples`` new comparisons."""
        self._value = float(np.clip(state["value"], *self.bounds))


class ChainDisagreement:
    """Time-local factor: the vision chain against the gyro chain over the last ``window_s``.

    The session factor is a median over many short keyframe-to-frame comparisons; it does not
    follow episodes in which the vision errors of consecutive measurements add up (they share
    their keyframe, and the back end's gyro bias follows them), which is what makes a pose
    over-confident over a second. Here the chained vision rotation from the keyframe about
    ``window_s`` back to the current frame is compared with the gyro over the same time,
    against the chained covariance of that stretch (keyframe-to-keyframe measurements are
    independent, so it is the difference of the two chained covariances) plus the gyro's,
    with a bias error allowance growing with the duration. ``count`` recent stretches give the
    factor whose mean q is chi-square(3)'s mean: the mean, so that one bad second counts.
    """

    def __init__(
        self,
        window_s: float = 1.0,
        count: int = 10,
        bounds: tuple[float, float] = (1 / 16, 16.0),
        bias_sigma: float = 2e-4,
    ) -> None:
        self.window_ns = round(window_s * 1e9)
        self.bounds = bounds
        self.bias_sigma = float(bias_sigma)
        # timestamp -> chained (vision rotation, its covariance, gyro rotation, its covariance)
        self._chain: dict[int, tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]] = {}
        self._keyframes: list[int] = []  # stamps used as references, oldest first
        self._samples: deque[tuple[np.ndarray, np.ndarray, np.ndarray]] = deque(maxlen=count)
        self._spectra: deque[Spectra | None] = deque(maxlen=count)  # each sample's, once
        self._value = bounds[0]  # no stretch yet: no inflation

    @property
    def value(self) -> float:
        return self._value

    @property
    def samples(self) -> tuple[tuple[np.ndarray, np.ndarray, np.ndarray], ...]:
        """The recent stretches (error, vision covariance, gyro covariance) the factor is
        solved from, oldest first: what a check of the factor needs."""
        return tuple(self._samples)

    def add(
        self,
        timestamp_ns: int,
        reference_ns: int,
        vision_rotation: np.ndarray,
        vision_covariance: np.ndarray,
        gyro_rotation: np.ndarray,
        gyro_covariance: np.ndarray,
    ) -> float:
        """Chain one keyframe-to-frame comparison (body frame) and return the local factor."""
        if reference_ns not in self._chain:  # a restart: the chain begins at the reference
            self._chain = {reference_ns: (np.eye(3), np.zeros((3, 3)), np.eye(3), np.zeros((3, 3)))}
            self._keyframes = []
        if not self._keyframes or self._keyframes[-1] != reference_ns:
            self._keyframes.append(reference_ns)
        base_v, cov_v, base_g, cov_g = self._chain[reference_ns]
        self._chain[timestamp_ns] = (
            base_v @ vision_rotation,
            vision_rotation.T @ cov_v @ vision_rotation + vision_covariance,
            base_g @ gyro_rotation,
            gyro_rotation.T @ cov_g @ gyro_rotation + gyro_covariance,
        )
        anchors = [k for k in self._keyframes if timestamp_ns - k <= self.window_ns]
        if anchors and timestamp_ns - anchors[0] >= self.window_ns // 2:
            sample = self._stretch(anchors[0], timestamp_ns)
            self._samples.append(sample)
            self._spectra.append(disagreement_spectra(*(part[None] for part in sample)))
            self._value = self._solve()
        self._forget(timestamp_ns, reference_ns)
        return self._value

    def _solve(self) -> float:
        """The factor whose mean normalised disagreement is chi-square(3)'s mean."""
        if None not in self._spectra:
            eigenvalues = np.concatenate([spectrum[0] for spectrum in self._spectra])  # type: ignore[index]
            weights = np.concatenate([spectrum[1] for spectrum in self._spectra])  # type: ignore[index]
            return solve_factor_spectra(np.mean, _CHI2_3_MEAN, (eigenvalues, weights), self.bounds)
        errors, vision, gyro = (np.array(part) for part in zip(*self._samples, strict=True))
        return solve_factor(np.mean, _CHI2_3_MEAN, errors, vision, gyro, self.bounds)

    def _stretch(self, first_ns: int, last_ns: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(error, vision covariance, gyro covariance) of the chained motion first -> last."""
        first_v, first_cov_v, first_g, first_cov_g = self._chain[first_ns]
        last_v, last_cov_v, last_g, last_cov_g = self._chain[last_ns]
        vision = first_v.T @ last_v
        gyro = first_g.T @ last_g
        error = np.asarray(gtsam.Rot3.Logmap(gtsam.Rot3(gyro.T @ vision)))
        duration = (last_ns - first_ns) * 1e-9
        bias = (self.bias_sigma * duration) ** 2 * np.eye(3)
        return (
            error,
            _positive(last_cov_v - vision.T @ first_cov_v @ vision),
            _positive(last_cov_g - gyro.T @ first_cov_g @ gyro) + bias,
        )

    def _forget(self, timestamp_ns: int, reference_ns: int) -> None:
        """Keep the frames a later stretch or measurement may start from."""
        horizon = timestamp_ns - 2 * self.window_ns
        self._keyframes = [k for k in self._keyframes if k >= horizon or k == reference_ns]
        keep = set(self._keyframes) | {timestamp_ns, reference_ns}
        for stamp in [s for s in self._chain if s < horizon and s not in keep]:
            del self._chain[stamp]

    def state(self) -> dict[str, float]:
        return {"value": self._value}

    def restore(self, state: dict[str, float]) -> None:
        """Continue from a stored factor; it holds until the first new stretch."""
        self._value = float(np.clip(state["value"], *self.bounds))


def _positive(covariance: np.ndarray) -> np.ndarray:
    """Symmetric with eigenvalues clipped at zero (a difference of chained covariances)."""
    values, vectors = np.linalg.eigh(0.5 * (covariance + covariance.T))
    return (vectors * np.clip(values, 0.0, None)) @ vectors.T


class GyroCalibration:
    """The back end's side: the gyro chain of the frames and the factors measured along it.

    ``value`` (the session's factor) scales the frame-to-frame covariances (twist,
    measurements); ``pose_value``, the larger of it and the time-local one
    (:class:`ChainDisagreement`), scales the growth of the pose covariance through episodes
    the session median does not follow (errors adding up over a second do not make a single
    frame's twist worse than the session factor says: rendered flights, ``bench consistency``).
    """

    def __init__(self, config: BackendConfig, body_from_camera: np.ndarray) -> None:
        self.body_from_camera = np.asarray(body_from_camera, dtype=float)
        self.enabled = config.covariance_scale == "gyro"
        bounds = (1.0 / config.covariance_scale_max, config.covariance_scale_max)
        self.scale = CovarianceScale(
            window=config.covariance_scale_window,
            bounds=bounds,
            bias_sigma=config.covariance_scale_gyro_bias_sigma,
        )
        self.local = (
            ChainDisagreement(
                config.covariance_scale_local_window_s,
                config.covariance_scale_local_count,
                bounds,
                config.covariance_scale_gyro_bias_sigma,
            )
            if config.covariance_scale_local_count > 0
            else None
        )
        self.chain = GyroChain()

    @property
    def value(self) -> float:
        return self.scale.value if self.enabled else 1.0

    @property
    def pose_value(self) -> float:
        if self.local is None:
            return self.value
        return max(self.value, self.local.value) if self.enabled else 1.0

    def state(self) -> dict[str, Any]:
        """The factors, for a continuation in another process (JSON-ready)."""
        return {
            "session": self.scale.state(),
            "local": self.local.state() if self.local is not None else None,
        }

    def restore(self, state: dict[str, Any]) -> None:
        """Continue with the stored factors until new comparisons replace them."""
        self.scale.restore(state["session"])
        if self.local is not None and state.get("local"):
            self.local.restore(state["local"])

    def add_frame(
        self,
        timestamp_ns: int,
        interval: GyroPreintegration | None,
        reference_ns: int | None,
        relative_pose: np.ndarray | None,
        covariance: np.ndarray | None,
        bias: np.ndarray,
    ) -> float:
        """Extend the chain by the interval ending at this frame and compare its measurement
        T_ref_cur (left camera; ``covariance`` in the body frame, as the factor uses it),
        the gyro bias removed as estimated now."""
        if not self.enabled:
            return 1.0
        self.chain.extend(timestamp_ns, interval)
        if relative_pose is None or covariance is None or reference_ns is None:
            return self.value
        gyro = self.chain.between(reference_ns, timestamp_ns, bias)
        if gyro is not None:
            camera_from_body = invert_pose(self.body_from_camera)
            measured = self.body_from_camera @ relative_pose @ camera_from_body
            duration = (timestamp_ns - reference_ns) * 1e-9
            self.scale.observe(measured[:3, :3], covariance[:3, :3], gyro[0], gyro[1], duration)
            if self.local is not None:
                self.local.add(
                    timestamp_ns, reference_ns, measured[:3, :3], covariance[:3, :3], *gyro
                )
        self.chain.forget_before(reference_ns)
        return self.value
