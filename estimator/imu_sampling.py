"""How IMU samples are read between two frame times: the one rule the whole estimator uses.

The back end preintegrates the gyro and the accelerometer per frame interval, and the front
end's gyro prediction integrates the gyro over the same interval to centre its search windows;
both cut the interval at the samples and take one mean value per piece here, so the rotation
the search windows expect is the one the back end's factors will measure.
"""

from __future__ import annotations

import numpy as np

__all__ = ["sample_segments", "samples_cover"]


def sample_segments(
    timestamps_ns: np.ndarray, samples: np.ndarray, start_ns: int, end_ns: int
) -> tuple[np.ndarray, np.ndarray]:
    """Split [start, end] at the samples; one mean value (rate or specific force) per piece.

    The signal is interpolated linearly between samples (and held beyond the first/last
    sample), so each piece uses the average of its two end values (trapezoidal rule). Sample
    times rarely coincide with frame times; cutting at the exact frame times keeps the
    per-frame increments unbiased.
    """
    timestamps_ns = np.asarray(timestamps_ns, dtype=np.int64)
    values = np.asarray(samples, dtype=float)
    if end_ns <= start_ns:
        raise ValueError(f"IMU interval must have end > start (got {start_ns} .. {end_ns})")
    if len(timestamps_ns) == 0:
        raise ValueError("no IMU samples to integrate")
    if values.shape != (len(timestamps_ns), 3):
        raise ValueError(f"samples must be (M, 3) matching the timestamps, got {values.shape}")
    inside = timestamps_ns[(timestamps_ns > start_ns) & (timestamps_ns < end_ns)]
    breaks = np.concatenate([[start_ns], inside, [end_ns]]).astype(np.int64)
    # Interpolate relative to the first break so float64 keeps nanosecond resolution.
    t = (breaks - start_ns).astype(float)
    samples_t = (timestamps_ns - start_ns).astype(float)
    at_breaks = np.stack([np.interp(t, samples_t, values[:, axis]) for axis in range(3)], axis=1)
    return 0.5 * (at_breaks[:-1] + at_breaks[1:]), np.diff(breaks) * 1e-9


def samples_cover(timestamps_ns: np.ndarray, start_ns: int, end_ns: int, slack_ns: int) -> bool:
    """Whether the samples reach [start_ns, end_ns] but for ``slack_ns`` at either end, i.e.
    whether holding the first/last value (``sample_segments``) bridges no more than that."""
    stamps = np.asarray(timestamps_ns, dtype=np.int64)
    if end_ns <= start_ns or len(stamps) == 0:
        return False
    return bool(stamps[0] <= start_ns + slack_ns and stamps[-1] >= end_ns - slack_ns)
