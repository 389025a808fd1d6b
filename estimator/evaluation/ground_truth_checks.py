"""How far a ground truth can be trusted: its clock and its lever arm, seen through the data.

Diagnostics, not metrics. The headline ATE (``metrics.evaluate_trajectory``) compares the
estimate with the ground truth at the frames' own timestamps through the calibrated ``T_BS``;
these checks ask what that comparison takes for granted:

* whether the ground truth's orientation runs on the IMU's clock (its body rate against the
  gyro, over a scan of time shifts);
* whether the camera's stamps run on the IMU's clock, without any ground truth (vision's
  frame-to-frame rotations against the gyro integrated over the same intervals, shifted);
* whether the ground truth's positions run on the IMU's clock, without any camera (their
  second difference against the accelerometer);
* how much of an estimate's ATE goes away when the ground-truth positions are read a little
  later or earlier, when the camera sits at a slightly different place in the ground truth's
  body frame (a lever arm), or both. Any free parameter fitted to one run lowers its ATE
  somewhat; whether a correction fitted on one half of a run also lowers the other half's
  (``held_out_check``) is what says it belongs to the reference.

Sign convention, everywhere: a shift ``s`` reads the *other* series (the ground truth, or the
gyro in the camera check) at ``t + s`` for a sample stamped ``t``; a minimum at ``s > 0`` says
the other series' stamps run ``s`` late.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import StrEnum

import numpy as np

from estimator.evaluation.metrics import camera_ground_truth
from estimator.formats.datasets import GroundTruth
from estimator.geometry import (
    kabsch,
    quat_multiply,
    quat_to_matrix,
    rotation_vector,
    rotation_vector_to_quat,
    skew,
)
from estimator.imu_sampling import sample_segments
from estimator.types import ImuBatch

__all__ = [
    "Correction",
    "CorrectionKind",
    "HeldOutCheck",
    "RunPositions",
    "ShiftScan",
    "accelerometer_ground_truth_offset",
    "aligned_ate",
    "ate_versus_shift",
    "camera_gyro_offset",
    "corrected_ate",
    "fit_correction",
    "fit_lever_arm",
    "fit_shift_and_lever_arm",
    "gyro_ground_truth_offset",
    "gyro_orientation",
    "held_out_check",
    "parabolic_minimum",
]

_MAX_GAUSS_NEWTON_STEPS = 30
_STEP_TOLERANCE = 1e-10  # norm of a Gauss-Newton update (rad and m) that counts as converged


@dataclass(frozen=True)
class ShiftScan:
    """A residual as a function of a time shift, and its minimum refined between grid points."""

    shifts_s: np.ndarray  # (K,) increasing, uniform
    values: np.ndarray  # (K,) the residual at each shift (units: the function's)
    best_shift_s: float  # vertex of the parabola through the grid minimum and its neighbours
    best_value: float  # the parabola's value there (the grid minimum when at an edge)
    at_edge: bool  # the grid minimum is the first or last shift: widen the scan

    def value_at(self, shift_s: float) -> float:
        """The residual at the scanned shift nearest ``shift_s``."""
        return float(self.values[int(np.argmin(np.abs(self.shifts_s - shift_s)))])


class CorrectionKind(StrEnum):
    """What is fitted to the ground truth's positions on top of the rigid alignment."""

    SHIFT = "shift"  # a time shift of the ground truth
    LEVER_ARM = "lever-arm"  # the camera's offset in the ground truth's body frame
    BOTH = "shift+lever-arm"


@dataclass(frozen=True)
class Correction:
    """A ground-truth correction and the ATE with it (the alignment refitted)."""

    kind: CorrectionKind
    shift_s: float  # the ground truth read at t + shift_s
    lever_arm_m: np.ndarray  # (3,) added to T_BS's translation (body frame)
    ate_m: float
    iterations: int = 0  # Gauss-Newton steps of the lever-arm fit (0: none fitted)


def parabolic_minimum(shifts_s: np.ndarray, values: np.ndarray) -> ShiftScan:
    """The grid minimum of a scan, refined by the parabola through it and its two neighbours."""
    shifts_s = np.asarray(shifts_s, dtype=float)
    values = np.asarray(values, dtype=float)
    if len(shifts_s) < 3 or shifts_s.shape != values.shape:
        raise ValueError(f"need at least 3 shifts with one value each, got {values.shape}")
    steps = np.diff(shifts_s)
    if not np.allclose(steps, steps[0]) or steps[0] <= 0:
        raise ValueError("the shifts must be increasing and evenly spaced")
    index = int(np.argmin(values))
    if index in (0, len(values) - 1):
        return ShiftScan(shifts_s, values, float(shifts_s[index]), float(values[index]), True)
    left, middle, right = values[index - 1 : index + 2]
    curvature = left - 2.0 * middle + right
    offset = 0.5 * (left - right) / curvature if curvature > 0 else 0.0
    best_value = middle - 0.25 * (left - right) * offset
    best_shift = shifts_s[index] + offset * steps[0]
    return ShiftScan(shifts_s, values, float(best_shift), float(best_value), False)


def _shift_ns(shift_s: float) -> int:
    return round(shift_s * 1e9)


def _relative_rotations(first: np.ndarray, second: np.ndarray) -> np.ndarray:
    """first^T second for stacks of rotations (N, 3, 3)."""
    return np.swapaxes(first, -1, -2) @ second


def _log(rotations: np.ndarray) -> np.ndarray:
    """Rotation vectors (N, 3) of rotation matrices (N, 3, 3)."""
    return np.atleast_2d(rotation_vector(rotations))


def _rms_norm(residuals: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.sum(np.square(residuals), axis=-1))))


# ----------------------------------------------------------------------------- rotation clocks


def _ground_truth_rates(
    ground_truth: GroundTruth, timestamps_ns: np.ndarray, half_step_ns: int
) -> np.ndarray:
    """Body angular rate (rad/s, body frame) of the ground truth by a central difference."""
    before = ground_truth.interpolate(timestamps_ns - half_step_ns)[:, :3, :3]
    after = ground_truth.interpolate(timestamps_ns + half_step_ns)[:, :3, :3]
    return _log(_relative_rotations(before, after)) / (2.0 * half_step_ns * 1e-9)


def gyro_ground_truth_offset(
    imu: ImuBatch,
    ground_truth: GroundTruth,
    shifts_s: np.ndarray,
    half_step_s: float = 2.5e-3,
) -> ShiftScan:
    """RMS of gyro minus the ground truth's body rate read at ``t + shift`` (rad/s).

    The mean difference (the gyro bias) is removed at every shift. Only samples whose shifted
    difference window lies inside the ground truth at every shift are used, so all shifts see
    the same samples.
    """
    half_step_ns = _shift_ns(half_step_s)
    reach = max(abs(_shift_ns(s)) for s in shifts_s) + half_step_ns
    stamps = np.asarray(imu.timestamps_ns, dtype=np.int64)
    usable = ground_truth.covers(stamps - reach) & ground_truth.covers(stamps + reach)
    if usable.sum() < 3:
        raise ValueError("fewer than 3 IMU samples inside the ground truth for this scan")
    stamps, gyro = stamps[usable], np.asarray(imu.gyro, dtype=float)[usable]
    values = []
    for shift in shifts_s:
        difference = gyro - _ground_truth_rates(
            ground_truth, stamps + _shift_ns(shift), half_step_ns
        )
        values.append(_rms_norm(difference - difference.mean(axis=0)))
    return parabolic_minimum(np.asarray(shifts_s, dtype=float), np.array(values))


def gyro_orientation(
    imu: ImuBatch, bias: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """The gyro integrated over the whole stream: body(first sample) <- body(t) at each sample.

    The rates between samples are read as the estimator's preintegration reads them
    (``imu_sampling.sample_segments``); rotations between any two times then follow from two
    slerped lookups (see ``camera_gyro_offset``).
    """
    stamps = np.asarray(imu.timestamps_ns, dtype=np.int64)
    if len(stamps) < 2:
        raise ValueError("need at least 2 IMU samples to integrate the gyro")
    rates = np.asarray(imu.gyro, dtype=float) - (np.zeros(3) if bias is None else bias)
    pieces, durations = sample_segments(stamps, rates, int(stamps[0]), int(stamps[-1]))
    steps = rotation_vector_to_quat(pieces * durations[:, None])
    orientation = np.empty((len(stamps), 4))
    orientation[0] = (1.0, 0.0, 0.0, 0.0)
    for index, step in enumerate(steps):
        orientation[index + 1] = quat_multiply(orientation[index], step)
    return stamps, quat_to_matrix(orientation)


def _gyro_between(
    orientation: tuple[np.ndarray, np.ndarray], starts_ns: np.ndarray, ends_ns: np.ndarray
) -> np.ndarray:
    """body(start) <- body(end) from the integrated gyro, slerped between its samples."""
    from scipy.spatial.transform import Rotation, Slerp

    stamps, rotations = orientation
    seconds = (stamps - stamps[0]) * 1e-9
    slerp = Slerp(seconds, Rotation.from_matrix(rotations))
    start = slerp((np.asarray(starts_ns) - stamps[0]) * 1e-9).as_matrix()
    end = slerp((np.asarray(ends_ns) - stamps[0]) * 1e-9).as_matrix()
    return _relative_rotations(start, end)


def camera_gyro_offset(
    timestamps_ns: np.ndarray,
    camera_rotations: np.ndarray,
    imu: ImuBatch,
    R_BS: np.ndarray,
    shifts_s: np.ndarray,
) -> ShiftScan:
    """RMS (rad per frame) of vision's frame-to-frame body rotation against the gyro's over
    the same interval read at ``+ shift``; no ground truth involved.

    ``camera_rotations`` (N, 3, 3) are camera-to-world rotations of consecutive frames (any
    world frame); ``R_BS`` turns camera vectors into body ones. The gyro bias is estimated
    from the mean disagreement at shift 0 and removed before integrating; the mean residual
    left is removed at every shift, so a bias error does not pass for a time offset.
    """
    stamps = np.asarray(timestamps_ns, dtype=np.int64)
    rotations = np.asarray(camera_rotations, dtype=float)
    if len(stamps) < 4 or rotations.shape != (len(stamps), 3, 3):
        raise ValueError(f"need (N >= 4, 3, 3) rotations for N stamps, got {rotations.shape}")
    vision = R_BS @ _relative_rotations(rotations[:-1], rotations[1:]) @ R_BS.T
    reach = max(abs(_shift_ns(s)) for s in shifts_s)
    imu_stamps = np.asarray(imu.timestamps_ns, dtype=np.int64)
    if (
        len(imu_stamps) < 2
        or imu_stamps[0] > stamps[0] - reach
        or imu_stamps[-1] < stamps[-1] + reach
    ):
        raise ValueError("the IMU does not cover the frames over the whole shift scan")
    durations = np.diff(stamps) * 1e-9
    bias = np.zeros(3)
    for _ in range(2):  # the second pass linearises at the first pass's bias
        gyro = _gyro_between(gyro_orientation(imu, bias), stamps[:-1], stamps[1:])
        residual = _log(_relative_rotations(gyro, vision))
        bias = bias - (residual / durations[:, None]).mean(axis=0)
    orientation = gyro_orientation(imu, bias)
    values = []
    for shift in shifts_s:
        gyro = _gyro_between(
            orientation, stamps[:-1] + _shift_ns(shift), stamps[1:] + _shift_ns(shift)
        )
        residual = _log(_relative_rotations(gyro, vision))
        values.append(_rms_norm(residual - residual.mean(axis=0)))
    return parabolic_minimum(np.asarray(shifts_s, dtype=float), np.array(values))


def _triangle_smoothed(values: np.ndarray, half_width: int) -> np.ndarray:
    """values (N, ...) averaged with triangular weights over +-half_width samples: what a
    second difference over +-half_width samples does to the second derivative."""
    weights = (half_width - np.abs(np.arange(1 - half_width, half_width))).astype(float)
    weights /= weights.sum()
    flat = values.reshape(len(values), -1)
    smoothed = np.stack([np.convolve(column, weights, "same") for column in flat.T], axis=1)
    return smoothed.reshape(values.shape)


def accelerometer_ground_truth_offset(
    imu: ImuBatch,
    ground_truth: GroundTruth,
    shifts_s: np.ndarray,
    half_window_s: float = 0.1,
) -> ShiftScan:
    """RMS (m/s^2) of the ground-truth positions' second difference (over +-half_window_s,
    read at ``t + shift``) against the accelerometer turned into the world by the ground
    truth's orientation at ``t`` and smoothed alike; no camera involved.

    An accelerometer bias (body frame) and a constant world term (gravity, whatever its
    value) are fitted at every shift. The IMU must be uniformly sampled. Scan shifts that are
    multiples of the ground truth's row spacing: reading between its rows interpolates, which
    smooths the positions' noise and lowers the residual for a reason other than timing.
    """
    stamps = np.asarray(imu.timestamps_ns, dtype=np.int64)
    steps = np.diff(stamps)
    if len(stamps) < 3 or np.ptp(steps) > 0.01 * np.median(steps):
        raise ValueError("the accelerometer check needs uniformly sampled IMU data")
    half_width = round(float(half_window_s * 1e9 / np.median(steps)))
    half_window_ns = int(half_width * np.median(steps))
    reach = max(abs(_shift_ns(s)) for s in shifts_s) + half_window_ns
    usable = ground_truth.covers(stamps - reach) & ground_truth.covers(stamps + reach)
    if usable.sum() < 2 * half_width + 3:
        raise ValueError("too few IMU samples inside the ground truth for this scan")
    stamps = stamps[usable]
    rotations = ground_truth.interpolate(stamps)[:, :3, :3]
    force = _triangle_smoothed(
        rotations @ np.asarray(imu.accel, float)[usable][:, :, None], half_width
    )[..., 0]
    design = np.concatenate(
        [_triangle_smoothed(rotations, half_width), np.broadcast_to(np.eye(3), rotations.shape)],
        axis=2,
    )
    inner = slice(half_width, len(stamps) - half_width)  # where the smoothing saw a full window
    values = []
    for shift in shifts_s:
        query = stamps + _shift_ns(shift)
        position = [
            ground_truth.interpolate(query + k)[:, :3, 3]
            for k in (-half_window_ns, 0, half_window_ns)
        ]
        second = (position[0] - 2.0 * position[1] + position[2]) / (half_window_ns * 1e-9) ** 2
        target = (second - force)[inner].reshape(-1)
        columns = design[inner].reshape(-1, 6)
        residual = target - columns @ np.linalg.lstsq(columns, target, rcond=None)[0]
        values.append(_rms_norm(residual.reshape(-1, 3)))
    return parabolic_minimum(np.asarray(shifts_s, dtype=float), np.array(values))


# ----------------------------------------------------------------------------- positions


def aligned_ate(estimate_positions: np.ndarray, reference_positions: np.ndarray) -> float:
    """ATE RMSE (m) after the least-squares rigid alignment (no scale) of estimate onto
    reference: the minimiser evo's Umeyama fit finds for the headline metric."""
    rotation, translation = kabsch(estimate_positions, reference_positions)
    aligned = estimate_positions @ rotation.T + translation
    return _rms_norm(aligned - reference_positions)


def _covered_at_all_shifts(
    timestamps_ns: np.ndarray, ground_truth: GroundTruth, shifts_s: np.ndarray
) -> np.ndarray:
    stamps = np.asarray(timestamps_ns, dtype=np.int64)
    low, high = min(_shift_ns(s) for s in shifts_s), max(_shift_ns(s) for s in shifts_s)
    covered = ground_truth.covers(stamps + low) & ground_truth.covers(stamps + high)
    if covered.sum() < 3:
        raise ValueError("fewer than 3 frames inside the ground truth at every shift")
    return covered


def _camera_positions(
    ground_truth: GroundTruth, timestamps_ns: np.ndarray, T_BS: np.ndarray, lever_arm_m: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Ground-truth camera positions with the camera moved by ``lever_arm_m`` (body frame),
    and the body rotations (which the lever arm's Jacobian needs)."""
    moved = np.array(T_BS, dtype=float)
    moved[:3, 3] += lever_arm_m
    camera = camera_ground_truth(ground_truth, timestamps_ns, moved)
    return camera[:, :3, 3], camera[:, :3, :3] @ moved[:3, :3].T


def ate_versus_shift(
    timestamps_ns: np.ndarray,
    estimate_positions: np.ndarray,
    ground_truth: GroundTruth,
    T_BS: np.ndarray,
    shifts_s: np.ndarray,
) -> ShiftScan:
    """ATE (m) with the ground truth read at ``t + shift``, over the frames covered at every
    shift (at shift 0 over all frames that is the headline ATE)."""
    shifts = np.asarray(shifts_s, dtype=float)
    covered = _covered_at_all_shifts(timestamps_ns, ground_truth, shifts)
    stamps = np.asarray(timestamps_ns, dtype=np.int64)[covered]
    positions = np.asarray(estimate_positions, dtype=float)[covered]
    values = [
        aligned_ate(positions, _camera_positions(ground_truth, stamps + _shift_ns(s), T_BS, 0.0)[0])
        for s in shifts
    ]
    return parabolic_minimum(shifts, np.array(values))


def fit_lever_arm(
    timestamps_ns: np.ndarray,
    estimate_positions: np.ndarray,
    ground_truth: GroundTruth,
    T_BS: np.ndarray,
    shift_s: float = 0.0,
) -> Correction:
    """The body-frame lever arm and rigid alignment that minimise the ATE jointly.

    Residual per frame: R p_est + t - (p_body + R_body (t_BS + l)), in (rotation of the
    alignment, t, l), solved by Gauss-Newton from the plain alignment (l = 0). The lever arm
    is observable only when the body turns: a pure translation moves every frame alike, which
    the alignment's t absorbs.
    """
    stamps = np.asarray(timestamps_ns, dtype=np.int64)
    positions = np.asarray(estimate_positions, dtype=float)
    stamps_gt = stamps + _shift_ns(shift_s)
    reference, body_rotations = _camera_positions(ground_truth, stamps_gt, T_BS, np.zeros(3))
    rotation, translation = kabsch(positions, reference)
    lever = np.zeros(3)
    iterations = 0
    while iterations < _MAX_GAUSS_NEWTON_STEPS:
        iterations += 1
        target = reference + body_rotations @ lever
        residual = positions @ rotation.T + translation - target
        jacobian = np.concatenate(
            [
                -rotation @ skew(positions),
                np.broadcast_to(np.eye(3), body_rotations.shape),
                -body_rotations,
            ],
            axis=2,
        ).reshape(-1, 9)
        step = np.linalg.lstsq(jacobian, -residual.reshape(-1), rcond=None)[0]
        rotation = rotation @ quat_to_matrix(rotation_vector_to_quat(step[:3]))
        translation, lever = translation + step[3:6], lever + step[6:]
        if np.linalg.norm(step) < _STEP_TOLERANCE:
            break
    ate = aligned_ate(positions, reference + body_rotations @ lever)
    kind = CorrectionKind.BOTH if shift_s else CorrectionKind.LEVER_ARM
    return Correction(kind, float(shift_s), lever, ate, iterations)


def fit_shift_and_lever_arm(
    timestamps_ns: np.ndarray,
    estimate_positions: np.ndarray,
    ground_truth: GroundTruth,
    T_BS: np.ndarray,
    shifts_s: np.ndarray,
) -> tuple[ShiftScan, Correction]:
    """The ground-truth time shift and lever arm together: the lever arm is fitted at every
    scanned shift, and once more at the refined best shift (frames covered at every shift)."""
    shifts = np.asarray(shifts_s, dtype=float)
    covered = _covered_at_all_shifts(timestamps_ns, ground_truth, shifts)
    stamps = np.asarray(timestamps_ns, dtype=np.int64)[covered]
    positions = np.asarray(estimate_positions, dtype=float)[covered]
    values = [fit_lever_arm(stamps, positions, ground_truth, T_BS, s).ate_m for s in shifts]
    scan = parabolic_minimum(shifts, np.array(values))
    fit = fit_lever_arm(stamps, positions, ground_truth, T_BS, scan.best_shift_s)
    return scan, Correction(
        CorrectionKind.BOTH, fit.shift_s, fit.lever_arm_m, fit.ate_m, fit.iterations
    )


@dataclass(frozen=True)
class RunPositions:
    """A run's camera positions at its frames' timestamps, with the ground truth and the
    body -> camera transform they are checked against."""

    timestamps_ns: np.ndarray  # (N,)
    positions: np.ndarray  # (N, 3) estimated camera positions
    ground_truth: GroundTruth
    T_BS: np.ndarray  # body -> left camera

    def covered_at(self, shifts_s: np.ndarray) -> RunPositions:
        """The frames inside the ground truth at every shift of ``shifts_s``."""
        return self._part(_covered_at_all_shifts(self.timestamps_ns, self.ground_truth, shifts_s))

    def halves(self) -> tuple[RunPositions, RunPositions]:
        """The first and the second half of the frames."""
        middle = len(self.timestamps_ns) // 2
        return self._part(slice(None, middle)), self._part(slice(middle, None))

    def _part(self, frames: np.ndarray | slice) -> RunPositions:
        """The run restricted to ``frames`` (a mask or a slice)."""
        stamps = np.asarray(self.timestamps_ns, dtype=np.int64)[frames]
        positions = np.asarray(self.positions, dtype=float)[frames]
        return RunPositions(stamps, positions, self.ground_truth, self.T_BS)

    def corrected_ate(self, shift_s: float = 0.0, lever_arm_m: np.ndarray | None = None) -> float:
        """:func:`corrected_ate` of this run (no correction: the plainly aligned ATE)."""
        lever = np.zeros(3) if lever_arm_m is None else lever_arm_m
        return corrected_ate(
            self.timestamps_ns, self.positions, self.ground_truth, self.T_BS, shift_s, lever
        )


def fit_correction(run: RunPositions, kind: CorrectionKind, shifts_s: np.ndarray) -> Correction:
    """The best correction of one kind for a run; a shift is scanned over ``shifts_s``."""
    stamps, positions, truth, T_BS = run.timestamps_ns, run.positions, run.ground_truth, run.T_BS
    if kind is CorrectionKind.LEVER_ARM:
        return fit_lever_arm(stamps, positions, truth, T_BS)
    if kind is CorrectionKind.BOTH:
        return fit_shift_and_lever_arm(stamps, positions, truth, T_BS, shifts_s)[1]
    scan = ate_versus_shift(stamps, positions, truth, T_BS, shifts_s)
    return Correction(kind, scan.best_shift_s, np.zeros(3), run.corrected_ate(scan.best_shift_s))


@dataclass(frozen=True)
class HeldOutCheck:
    """A correction fitted on one half of a run, applied to the other half.

    A correction that belongs to the reference lowers the ATE of the half it was not fitted
    on; one that only fits one stretch's errors does not carry over (it can raise it).
    """

    kind: CorrectionKind
    ate_plain_m: tuple[float, float]  # first, second half, each aligned on its own
    ate_corrected_m: tuple[float, float]  # each half with the other half's correction
    fits: tuple[Correction, Correction]  # fitted on the first, on the second half


def corrected_ate(
    timestamps_ns: np.ndarray,
    estimate_positions: np.ndarray,
    ground_truth: GroundTruth,
    T_BS: np.ndarray,
    shift_s: float,
    lever_arm_m: np.ndarray,
) -> float:
    """ATE (m) against the ground truth read at ``t + shift_s`` with the camera moved by
    ``lever_arm_m`` in the body frame (nothing fitted but the alignment)."""
    stamps = np.asarray(timestamps_ns, dtype=np.int64) + _shift_ns(shift_s)
    reference = _camera_positions(ground_truth, stamps, T_BS, np.asarray(lever_arm_m, float))[0]
    return aligned_ate(np.asarray(estimate_positions, dtype=float), reference)


def held_out_check(run: RunPositions, kind: CorrectionKind, shifts_s: np.ndarray) -> HeldOutCheck:
    """``fit_correction`` on each half of the frames, scored on the other half."""
    shifts = np.asarray(shifts_s, dtype=float)
    halves = run.covered_at(shifts).halves()
    first, second = (fit_correction(half, kind, shifts) for half in halves)
    plain = [half.corrected_ate() for half in halves]
    corrected = [
        half.corrected_ate(fit.shift_s, fit.lever_arm_m)
        for half, fit in zip(halves, (second, first), strict=True)
    ]
    return HeldOutCheck(kind, (plain[0], plain[1]), (corrected[0], corrected[1]), (first, second))
